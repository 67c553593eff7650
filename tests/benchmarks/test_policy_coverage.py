"""Success by an evaluation start's distance to the nearest training start."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.policy.coverage import nearest_distances, success_by_distance

HALF = (0.08, 0.08, math.radians(45))


def test_the_distance_is_in_half_ranges_to_the_nearest_training_start():
    training = np.array([[0.30, -0.08, 0.0], [0.20, -0.08, 0.0]])
    starts = np.array([[0.30, -0.08, 0.0],                     # on a training start
                       [0.24, -0.08, 0.0],                     # 4 cm from the nearer: half a half-range
                       [0.30, -0.08, math.radians(22.5)],      # a quarter turn of the half-range
                       [0.34, -0.04, math.radians(45)]])       # 4 cm, 4 cm and 45 deg from the first
    np.testing.assert_allclose(nearest_distances(starts, training, HALF), [0.0, 0.5, 0.5, math.sqrt(1.5)])


def test_turns_are_compared_the_short_way_round():
    training = np.array([[0.3, 0.0, math.pi - 0.01]])
    assert nearest_distances(np.array([[0.3, 0.0, -math.pi + 0.01]]), training, HALF)[0] == pytest.approx(
        0.02 / HALF[2])


def test_successes_are_counted_per_distance_bin():
    report = success_by_distance(np.array([0.1, 0.2, 0.4, 0.6, 0.9]), np.array([True, True, True, False, True]),
                                 edges=(0.25, 0.5))
    assert report["bins"] == {"under_0.25": {"starts": 2, "successes": 2}, "0.25_to_0.5": {"starts": 1, "successes": 1},
                              "over_0.5": {"starts": 2, "successes": 1}}
    assert report["median_distance_succeeded"] == 0.3 and report["median_distance_failed"] == 0.6
    assert success_by_distance(np.array([0.1]), np.array([True]))["median_distance_failed"] is None


def test_no_training_starts_or_a_zero_range_is_an_error():
    with pytest.raises(ValueError, match="training starts"):
        nearest_distances(np.zeros((2, 3)), np.zeros((0, 3)), HALF)
    with pytest.raises(ValueError, match="half-ranges"):
        nearest_distances(np.zeros((2, 3)), np.zeros((1, 3)), (0.08, 0.0, 1.0))


def test_training_starts_are_read_in_the_simulators_frame(tmp_path):
    """The source's first-frame pose; an augmented demonstration's first skill applied to it; a
    scripted demonstration's record."""
    import json

    from benchmarks.policy.stages import _source_start, _start_pose

    source = tmp_path / "source"
    source.mkdir()
    (source / "episode.json").write_text(json.dumps({"objects": ["box"]}))
    T0 = np.eye(4)
    T0[:3, 3] = (0.3, -0.08, 0.02)
    np.savez(source / "gt.npz", T_base_box=T0[None])
    assert _start_pose(source, _source_start(source)) == pytest.approx((0.3, -0.08, 0.0))

    c, s = math.cos(0.5), math.sin(0.5)
    skill = np.array([[c, -s, 0, 0.01], [s, c, 0, 0.02], [0, 0, 1, 0], [0, 0, 0, 1]])
    augmented = tmp_path / "augmented" / "episode_0000"
    augmented.mkdir(parents=True)
    (augmented / "augmentation.json").write_text(json.dumps({"segments": [
        {"kind": "motion"}, {"kind": "skill", "object": "box", "T": skill.tolist()}]}))
    x, y, yaw = _start_pose(augmented, _source_start(source))
    assert (x, y, yaw) == pytest.approx((c * 0.3 + s * 0.08 + 0.01, s * 0.3 - c * 0.08 + 0.02, 0.5))

    scripted = tmp_path / "oracle" / "demo_0001"
    scripted.mkdir(parents=True)
    (scripted.parent / "demos.json").write_text(json.dumps({"demos": [
        {"dir": "demo_0001", "object_pose": [0.25, -0.1, -0.3]}]}))
    assert _start_pose(scripted, _source_start(source)) == pytest.approx((0.25, -0.1, -0.3))
