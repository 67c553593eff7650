"""benchmarks.bench_augment_shared.in_simulator_frame: what the simulator is told of a new
demonstration, its objects' start, end and every frame's pose, is in the simulator's object frame,
so that the simulator draws and executes the object where the twin drew it. A tiny twin of the
built-in sample (its ground truth plays the simulator's): tests never read ../shared."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from benchmarks.bench_augment_shared import in_simulator_frame
from manisplat.augment.frames import to_centre_frame
from manisplat.augment.writer import OBJECT_POSES_FILE
from manisplat.episode import Episode
from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.outputs import twin_of
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainConfig


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """(the sample episode, a 5-iteration twin of it)."""
    episode = write_sample_episode(tmp_path_factory.mktemp("frame") / "ep", frames=32, fps=16.0, width=80, height=60)
    data = load_episode_data(episode)
    rec, alignments = build(data, make_plan(data), TrainConfig(iters=5))
    return episode, twin_of(rec, alignments)


def _replay_of_source(twin, parent: Path, out: Path) -> Path:
    """A "new" demonstration that moves the object as the source did: its poses as the twin drew
    them, its start and end in the centre frame as manisplat-augment writes them."""
    out.mkdir()
    for name in ("frames.csv", "episode.json"):
        shutil.copy(parent / name, out / name)
    objects = {name: {"T_start": to_centre_frame(twin, name, poses[0]).tolist(),
                      "T_end": to_centre_frame(twin, name, poses[-1]).tolist()}
               for name, poses in twin.object_poses.items()}
    (out / "augmentation.json").write_text(json.dumps({"objects": objects}))
    np.savez(out / OBJECT_POSES_FILE, **{name: np.asarray(p) for name, p in twin.object_poses.items()})
    return out


def test_the_drawn_poses_reach_the_simulator_in_its_own_frame(source, tmp_path: Path) -> None:
    parent, twin = source
    name = next(iter(twin.object_poses))
    truth = Episode.open(parent).gt()[f"T_base_{name}"]
    drawn = np.asarray(twin.object_poses[name])
    copy = in_simulator_frame(_replay_of_source(twin, parent, tmp_path / "new"), twin, parent, tmp_path / "sim")
    mapped = np.load(copy / OBJECT_POSES_FILE)[name]
    start = np.asarray(json.loads((copy / "augmentation.json").read_text())["objects"][name]["T_start"])
    assert mapped.shape == drawn.shape
    # the source's first pose is where the simulator had its object; the start agrees with the first frame
    np.testing.assert_allclose(mapped[0], truth[0], atol=1e-9)
    np.testing.assert_allclose(start, mapped[0], atol=1e-9)
    # every frame moves the simulator's object by the motion the twin's made
    for k in (len(drawn) // 2, len(drawn) - 1):
        np.testing.assert_allclose(mapped[k] @ np.linalg.inv(mapped[0]), drawn[k] @ np.linalg.inv(drawn[0]), atol=1e-9)


def test_a_demonstration_without_drawn_poses_gets_none(source, tmp_path: Path) -> None:
    parent, twin = source
    new = _replay_of_source(twin, parent, tmp_path / "new")
    (new / OBJECT_POSES_FILE).unlink()  # episodes augmented before the file existed
    assert not (in_simulator_frame(new, twin, parent, tmp_path / "sim") / OBJECT_POSES_FILE).exists()
