"""benchmarks/policy/fidelity.py and its stage: the twin's first frames against the simulator's,
each start placed by its own demonstration's motion. A stand-in ``policy_env`` (a module in a
temporary folder, run by this Python as the simulator's venv would) draws the object where it is
put: tests never read ../shared."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.policy.fidelity import GROW, StartScore, by_bin, score_start, simulator_start

OBJECT, ROBOT = 10, [1, 2]

STAND_IN = '''
import numpy as np

class PickPlaceEnv:
    """Draws the object as a 6 x 6 square at column 100 x and row 100 y + 40, on a grey image."""

    fps, max_steps = 16.0, 180

    @classmethod
    def from_episode(cls, episode_dir, mask=False, **kw):
        return cls()

    def reset(self, seed=None, object_pose=None):
        x, y, yaw = object_pose
        rgb = np.full((60, 80, 3), 100, np.uint8)
        labels = np.zeros((60, 80), np.uint8)
        r, c = int(round(100 * y)) + 40, int(round(100 * x))
        rgb[r:r + 6, c:c + 6] = (200, 30, 30)
        labels[r:r + 6, c:c + 6] = 10
        return {"rgb": rgb, "mask": labels, "pose": (x, y, yaw)}

    def close(self):
        pass
'''


def _images(shift: int = 0, robot_at: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A grey 60 x 80 image with the object (label 10) as a 6 x 6 square at (20, 30 + shift) and
    optionally a robot (label 1) square."""
    rgb = np.full((60, 80, 3), 100, np.uint8)
    mask = np.zeros((60, 80), np.uint8)
    rgb[20:26, 30 + shift:36 + shift] = (200, 30, 30)
    mask[20:26, 30 + shift:36 + shift] = OBJECT
    if robot_at is not None:
        rgb[40:50, robot_at:robot_at + 10] = (10, 10, 10)
        mask[40:50, robot_at:robot_at + 10] = 1
    return rgb, mask


def test_a_start_drawn_where_the_simulator_has_it_scores_perfectly_and_a_shifted_one_does_not():
    sim = _images()
    same = score_start("e", *_images(), *sim, OBJECT, ROBOT, 0.0, 0.3)
    assert same.outline_iou == 1.0 and same.object_psnr == pytest.approx(100.0) and same.object_px == 36
    shifted = score_start("e", *_images(shift=2), *sim, OBJECT, ROBOT, 0.0, 0.3)
    assert shifted.outline_iou == pytest.approx(24 / 48) and shifted.object_psnr < 20.0
    assert shifted.rest_psnr == pytest.approx(100.0)  # the difference stays inside the object region
    assert same.area_ratio == shifted.area_ratio == 1.0  # moved, not grown
    twin_rgb, twin_mask = _images()
    twin_mask[26, 30:36] = OBJECT  # the twin's outline a row taller
    assert score_start("e", twin_rgb, twin_mask, *sim, OBJECT, ROBOT, 0.0, 0.3).area_ratio == pytest.approx(42 / 36)


def test_the_robot_standing_elsewhere_is_not_scored():
    """The twin's arm starts where its demonstration starts, the simulator's where the source did."""
    score = score_start("e", *_images(robot_at=0), *_images(robot_at=60), OBJECT, ROBOT, 0.0, 0.3)
    assert score.rest_psnr == pytest.approx(100.0) and score.object_psnr == pytest.approx(100.0)
    # the twin's fingers just under the object, inside its grown region: not the object's error
    twin_rgb, twin_mask = _images()
    twin_rgb[26:28, 30:36], twin_mask[26:28, 30:36] = 0, 2
    score = score_start("e", twin_rgb, twin_mask, *_images(), OBJECT, ROBOT, 0.0, 0.3)
    assert score.object_psnr == pytest.approx(100.0) and score.outline_iou == 1.0


def test_the_object_region_reaches_past_both_outlines():
    """An error just outside both outlines (a halo the twin draws) counts as the object's."""
    twin = _images()
    twin[0][20:26, 36:36 + GROW] = 0
    score = score_start("e", *twin, *_images(), OBJECT, ROBOT, 0.0, 0.3)
    assert score.object_psnr < 20.0 and score.rest_psnr == pytest.approx(100.0)


def _write_demonstration(folder: Path, T: np.ndarray, name: str = "box") -> Path:
    folder.mkdir(parents=True)
    segments = [{"kind": "motion", "object": None, "T": None},
                {"kind": "skill", "object": name, "T": T.tolist()}]
    (folder / "augmentation.json").write_text(json.dumps({"segments": segments}))
    (folder / "episode.json").write_text("{}")
    return folder


def _turn(deg: float, x: float, y: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def test_the_simulators_object_starts_where_the_demonstrations_first_skill_moves_the_source(tmp_path):
    source = _turn(10.0, 0.3, -0.08)
    folder = _write_demonstration(tmp_path / "episode_0000", _turn(-40.0, 0.05, 0.02))
    x, y, yaw = simulator_start(folder, source, "box")
    expected = _turn(-40.0, 0.05, 0.02) @ source
    assert (x, y) == pytest.approx((expected[0, 3], expected[1, 3])) and math.degrees(yaw) == pytest.approx(-30.0)
    with pytest.raises(ValueError, match="no skill moves 'can'"):
        simulator_start(folder, source, "can")


def test_starts_are_binned_by_their_turn_and_distance():
    def start(turn: float, distance: float, psnr: float) -> StartScore:
        return StartScore("e", turn, distance, psnr, 0.9, 1.1, 30.0, 40)

    bins = by_bin([start(-40, 0.25, 18.0), start(-30, 0.35, 20.0), start(0, 0.30, 24.0), start(30, 0.40, 22.0)])
    assert bins["all"]["starts"] == 4 and bins["all"]["object_psnr"] == pytest.approx(21.0)
    assert bins["clockwise_beyond_22_deg"] == {"starts": 2, "object_psnr": 19.0, "outline_iou": 0.9, "area_ratio": 1.1,
                                               "rest_psnr": 30.0}
    assert bins["within_22_deg"]["starts"] == 1 and bins["counter_clockwise_beyond_22_deg"]["object_psnr"] == 22.0
    assert bins["near_base_under_0.27_m"]["starts"] == 1 and bins["far_from_base_over_0.32_m"]["starts"] == 2


def test_the_stage_scores_each_demonstration_against_the_simulator_at_its_own_start(tmp_path):
    """B's two demonstrations: one drawn where the stand-in simulator draws its start, one two
    pixels off; the stage asks the simulator for each start by its own motion and keeps the scores."""
    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.policy.stages import Stages

    tools = tmp_path / "tools"
    tools.mkdir()
    (tools / "policy_env.py").write_text(STAND_IN)
    source = write_sample_episode(tmp_path / "sample", frames=8, width=160, height=120)
    T0 = np.load(source / "gt.npz")["T_base_box"][0]
    stages = Stages(source, tmp_path / "work", Path(sys.executable), tools, (0.05, 0.05, 30.0), (0.02, 0.02, 30.0), 10)
    moves = [_turn(0.0, 0.02, 0.01), _turn(0.0, -0.03, 0.0)]
    root = tmp_path / "work" / "augmented_2"
    for k, T in enumerate(moves):
        folder = _write_demonstration(root / f"episode_{k:04d}", T)
        start = T @ T0
        r, c = int(round(100 * start[1, 3])) + 40, int(round(100 * start[0, 3])) + (2 if k else 0)
        rgb = np.full((60, 80, 3), 100, np.uint8)
        mask = np.zeros((60, 80), np.uint8)
        rgb[r:r + 6, c:c + 6] = (200, 30, 30)
        mask[r:r + 6, c:c + 6] = 10
        for kind, image in (("rgb", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)), ("masks", mask)):
            (folder / kind).mkdir()
            cv2.imwrite(str(folder / kind / "000000.png"), image)
    (root / "augment_report.json").write_text(json.dumps({"requested": 2, "drawn": 2, "valid": 2, "reasons": {}}))
    report = stages.fidelity(2)
    first, second = report["starts"]
    assert first["episode"] == "episode_0000" and first["outline_iou"] == 1.0 and first["object_psnr"] > 90
    assert second["outline_iou"] < 0.7 and second["object_psnr"] < 20
    assert first["distance_m"] == pytest.approx(math.hypot(T0[0, 3] + 0.02, T0[1, 3] + 0.01))
    assert report["bins"]["all"]["starts"] == 2 and (tmp_path / "work" / "fidelity_2.png").stat().st_size > 0
    assert stages.fidelity(2) == report  # kept: not scored again
