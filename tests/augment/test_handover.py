"""A handover (one box passed from the left gripper to the right) reconstructed from the built-in
two-arm sample and augmented: one skill shared by both arms, moved rigidly as one to a new
handover point; the giver picks the box at its new start, the taker places it at its new place,
and both enter the handover at the same frame; the box rides in each gripper in turn."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from manisplat.align.acting_arm import Hold
from manisplat.augment.bimanual import MIN_ARM_CLEARANCE_M, BimanualPlanner
from manisplat.augment.cli import build_parser, main as augment
from manisplat.augment.commands import SourceCommands
from manisplat.augment.handover import HANDOVER_RANGE, HANDOVER_SKILL, entry_delays, find_handover
from manisplat.augment.source import SourceError
from manisplat.augment.trajectory import GRIPPER_OPEN, AugmentConfig, Rejected, augmenter_for
from manisplat.episode import Episode
from manisplat.episode.synthetic_arms import write_two_arm_sample_episode
from manisplat.exit_codes import ExitCode
from manisplat.reconstruct.cli import main as reconstruct
from manisplat.twin import Twin
from manisplat.twin.commands import CommandRelation, led

SEED = 1  # a sample whose targets the twin's arms reach (several others leave the left arm's reach)


@pytest.fixture(scope="module")
def twin_folder(tmp_path_factory):
    """The twin of the built-in handover sample (10 s, head camera) after a few iterations."""
    root = tmp_path_factory.mktemp("handover")
    episode = write_two_arm_sample_episode(root / "ep", duration=10.0, task="handover")
    assert reconstruct([str(episode), "--out", str(root / "twin"), "--iters", "10", "-q"]) == 0
    return root / "twin"


@pytest.fixture(scope="module")
def planner(twin_folder):
    return BimanualPlanner(Twin.load(twin_folder))


@pytest.fixture(scope="module")
def handed(planner):
    """One new handover: (targets, trajectory)."""
    targets = planner.sample_targets(np.random.default_rng(SEED))
    return targets, planner.run(targets, AugmentConfig(seed=SEED))


def world_tcp(planner, arm: str, q: np.ndarray) -> np.ndarray:
    return planner.arms[arm].T_world_base @ planner.arms[arm].robot.tcp_pose(torch.as_tensor(q)).numpy()


def test_the_giver_picks_and_lets_go_the_taker_closes_and_places_around_one_shared_skill(planner):
    (handover,) = planner.handovers
    assert (handover.object, handover.giver, handover.taker) == ("box", "left", "right")
    assert handover.grasp < handover.takeover < handover.release  # both hold it in between
    skill = handover.skill
    assert skill.start < handover.grasp and handover.release < skill.end
    left, right = planner.arms["left"].phases["box"], planner.arms["right"].phases["box"]
    assert [p.name for p in left] == ["S_pick", HANDOVER_SKILL] and [p.name for p in right] == [HANDOVER_SKILL, "S_place"]
    assert left[1] == right[0] == skill
    # the giver leaves the box at the handover pose; the taker finds it there
    np.testing.assert_allclose(planner.arms["left"].to_world(planner.arms["left"].object_poses["box"][-1]),
                               handover.T_world_obj, atol=1e-12)
    np.testing.assert_allclose(planner.arms["right"].to_world(planner.arms["right"].object_poses["box"][0]),
                               handover.T_world_obj, atol=1e-12)


def test_both_arms_enter_the_handover_together_moved_by_the_same_transform(planner, handed):
    targets, traj = handed
    (handover,) = planner.handovers
    segments = {arm: next(s for s in traj.arms[arm].segments if s["name"] == HANDOVER_SKILL) for arm in traj.arms}
    assert segments["left"]["frames"] == segments["right"]["frames"] == traj.validation["handover"]["frames"]
    moved = {arm: planner.arms[arm].T_world_base @ np.array(s["T"]) @ np.linalg.inv(planner.arms[arm].T_world_base)
             for arm, s in segments.items()}  # each arm's skill transform, in the world
    np.testing.assert_allclose(moved["left"], moved["right"], atol=1e-9)
    new_handover = planner.arms["right"].to_world(targets["right"]["box"].T_start)
    np.testing.assert_allclose(moved["left"] @ handover.T_world_obj, new_handover, atol=1e-9)
    offset = new_handover[:3, 3] - handover.T_world_obj[:3, 3]
    assert np.all(np.abs(offset) <= HANDOVER_RANGE) and np.linalg.norm(offset) > 1e-3
    first, last = segments["left"]["frames"]
    source = np.arange(handover.skill.start, handover.skill.end)
    for arm in ("left", "right"):  # every frame of the shared skill: the source's TCP moved by that transform
        source_tcp = world_tcp(planner, arm, planner.arms[arm].q[source])
        np.testing.assert_allclose(world_tcp(planner, arm, traj.arms[arm].q[first:last + 1]),
                                   moved["left"] @ source_tcp, atol=2e-4)
    waited = traj.validation["handover"]["waited_s"]
    assert sorted(waited.values())[0] == 0 and traj.arms["right"].segments[0]["kind"] == "wait"


def test_the_box_rides_in_the_left_gripper_then_in_the_right_one(planner, handed):
    """From its new start the box is carried rigidly by the left TCP, then (from the taker's
    takeover) by the right TCP, and left at the new place."""
    targets, traj = handed
    (handover,) = planner.handovers
    box = traj.object_poses["box"]
    np.testing.assert_allclose(box[0], planner.arms["left"].to_world(targets["left"]["box"].T_start), atol=1e-9)
    np.testing.assert_allclose(box[-1], planner.arms["right"].to_world(targets["right"]["box"].T_place), atol=1e-9)
    takeover = traj.validation["handover"]["takeover_frame"]
    assert takeover == traj.validation["handover"]["frames"][0] + handover.takeover - handover.skill.start
    moving = np.flatnonzero(np.linalg.norm(np.diff(box[:, :3, 3], axis=0), axis=1) > 1e-6)
    for arm, frames in (("left", np.arange(moving[0] + 1, takeover)), ("right", np.arange(takeover, moving[-1] + 1))):
        in_tcp = np.linalg.inv(world_tcp(planner, arm, traj.arms[arm].q[frames])) @ box[frames]
        assert len(frames) >= 5
        np.testing.assert_allclose(in_tcp, np.broadcast_to(in_tcp[0], in_tcp.shape), atol=1e-6)
    # closed: commanded narrower than open (the source's recorded commands close on the box's width)
    closed = {arm: traj.arms[arm].action_gripper < GRIPPER_OPEN - 0.005 for arm in traj.arms}
    assert closed["left"][takeover - 1] and closed["right"][takeover]  # both hold it across the takeover
    assert not closed["left"][-1] and not closed["right"][-1]


def test_the_grippers_meeting_as_in_the_source_are_not_counted_as_a_collision(planner, handed):
    """Inside the shared skill the two grippers come as close as the source brought them (within
    the 5 mm clearance); measured without the source's own pairs the demonstration would fail."""
    _, traj = handed
    assert traj.validation["min_arm_clearance_m"] >= MIN_ARM_CLEARANCE_M
    assert traj.validation["handover"]["source_pairs_allowed"]
    unexempted = planner.check.closest(traj.arms, traj.object_poses)
    assert unexempted[0] < MIN_ARM_CLEARANCE_M and "link" in unexempted[2]


def test_an_arm_that_must_slow_the_handover_down_sets_the_pace_of_both(twin_folder):
    """The left arm's velocity limits lowered until its half of the handover must be slowed: the
    right arm is planned again at the same pace, both play the skill on the same frames, and the
    box changes hands on the frame the slowed skill reaches the takeover."""
    planner = BimanualPlanner(Twin.load(twin_folder))
    augmenter_for(planner.arms["left"]).vlim *= 0.25
    traj = planner.run(planner.sample_targets(np.random.default_rng(SEED)), AugmentConfig(seed=SEED))
    segments = {arm: next(s for s in traj.arms[arm].segments if s["name"] == HANDOVER_SKILL) for arm in traj.arms}
    assert segments["left"]["slowed"] == segments["right"]["slowed"] > 1.2
    assert segments["left"]["frames"] == segments["right"]["frames"]
    (handover,) = planner.handovers
    takeover = traj.validation["handover"]["takeover_frame"]
    first, last = segments["right"]["frames"]
    source_time = handover.skill.start + (takeover - first) * (handover.skill.end - 1 - handover.skill.start) / (last - first)
    assert handover.takeover <= source_time < handover.takeover + segments["right"]["slowed"]
    box = traj.object_poses["box"]
    tcp = {arm: world_tcp(planner, arm, traj.arms[arm].q) for arm in ("left", "right")}
    for arm, frames in (("left", range(takeover - 4, takeover)), ("right", range(takeover, takeover + 4))):
        in_tcp = np.linalg.inv(tcp[arm][list(frames)]) @ box[list(frames)]
        np.testing.assert_allclose(in_tcp, np.broadcast_to(in_tcp[0], in_tcp.shape), atol=1e-6)


def test_a_new_place_presses_where_the_source_s_commands_pressed(twin_folder):
    """The source's right-arm commands pressing up to 0.01 rad past its joint 2 through its place
    skill (rising and falling smoothly): the new commands press as much at the same source times,
    on top of the lead; before the place they only lead."""
    twin = Twin.load(twin_folder)
    place = next(p for p in twin.phases["box"] if p.name == "S_place")
    press = np.zeros(len(twin.q))
    press[place.start:place.end] = 0.01 * np.sin(np.linspace(0, np.pi, place.end - place.start)) ** 2
    pressed = np.zeros_like(twin.q)
    pressed[:, 6 + 1] = press  # the right arm's joint 2
    twin = twin.with_demonstration(replace(twin.demonstration, commands=CommandRelation(0.4, pressed)))
    planner = BimanualPlanner(twin)
    traj = planner.run(planner.sample_targets(np.random.default_rng(SEED)), AugmentConfig(seed=SEED))
    right, source = traj.arms["right"], planner.arms["right"]
    commands = SourceCommands(source.commands, 6, twin.fps)
    segment = next(s for s in right.segments if s["name"] == "S_place")
    (first, last), (begin, end) = segment["frames"], segment["source_frames"]
    played = np.linspace(begin, end, last - first + 1)
    expected = commands.press_at(played, begin, end)[:, 1]
    pressed = right.action_q[first:last + 1, 1] - led(right.q, commands.lead)[first:last + 1, 1]
    np.testing.assert_allclose(pressed, expected, atol=1e-9)
    assert expected.max() > 0.008
    np.testing.assert_allclose(right.action_q[:first], led(right.q, commands.lead)[:first], atol=1e-12)


def test_arms_playing_the_handover_at_different_paces_are_refused(planner, handed):
    _, traj = handed
    segments = {arm: [dict(s) for s in t.segments] for arm, t in traj.arms.items()}
    next(s for s in segments["right"] if s["name"] == HANDOVER_SKILL)["slowed"] = 1.3
    with pytest.raises(Rejected) as rejected:
        entry_delays(segments, planner.handovers[0])
    assert rejected.value.reason == "handover_timing" and "x1.30 by the right arm" in rejected.value.detail


def test_augment_writes_handed_over_demonstrations(twin_folder, tmp_path):
    out = tmp_path / "aug"
    assert augment([str(twin_folder), "--n", "1", "--out", str(out), "--seed", "3", "--max-samples", "12",
                    "-q"]) == ExitCode.OK
    report = json.loads((out / "augment_report.json").read_text())
    assert report["valid"] == 1 and report["ranges"]["handover"] == list(HANDOVER_RANGE)
    ep = Episode.open(out / "episode_0000")
    record = json.loads((ep.path / "augmentation.json").read_text())
    assert record["validation"]["handover"]["giver"] == "left"
    assert [s["name"] for s in record["arms"]["right"]["segments"]][:2] == ["W_wait", "M_approach"]
    assert len(ep.arm_frames("left").q) == len(ep.arm_frames("right").q) == len(ep)


def test_a_new_start_moves_both_arms_and_keeps_the_object_poses_of_the_seed(twin_folder, tmp_path):
    """--start-range on a two-arm twin: each arm's first frame is its source's first joints moved by
    up to the range (recorded per arm), the rest of the demonstration as planned from there, and the
    same seed draws the same object and handover poses as without it."""
    runs = {}
    for deg in (0, 5):
        out = tmp_path / f"aug{deg}"
        assert augment([str(twin_folder), "--n", "1", "--out", str(out), "--seed", "3", "--max-samples", "12",
                        "--start-range", str(deg), "-q"]) == ExitCode.OK
        runs[deg] = out
    twin = Twin.load(twin_folder)
    source = twin.arm_tracks()
    offsets = []
    for arm in ("left", "right"):
        first = Episode.open(runs[5] / "episode_0000").arm_frames(arm).q[0]
        record = json.loads((runs[5] / "episode_0000" / "augmentation.json").read_text())["arms"][arm]["planner"]
        offset = np.degrees(first - source[arm][0][0])
        np.testing.assert_allclose(record["start_offset_deg"], offset, atol=2e-3)
        assert np.abs(offset).max() <= 5 + 1e-6
        offsets.append(np.abs(offset).max())
    assert min(offsets) > 0.5  # both arms moved
    objects = [json.loads((runs[deg] / "episode_0000" / "augmentation.json").read_text())["objects"] for deg in (0, 5)]
    for name in objects[0]:
        np.testing.assert_allclose(objects[1][name]["T_start"], objects[0][name]["T_start"], atol=1e-9)


def test_the_handover_range_option_defaults_to_the_library_s():
    assert build_parser().parse_args(["twin", "--out", "o"]).handover_range == list(HANDOVER_RANGE)


# ------------------------------------------------------------------ handovers the augmenter refuses
T = 60


def track(grasp: int, release: int | None = None) -> np.ndarray:
    """A gripper opening [T]: closes over 3 frames from ``grasp``, opens over 3 from ``release``."""
    keys_t, keys_w = [0, grasp, grasp + 3], [0.07, 0.07, 0.038]
    if release is not None:
        keys_t, keys_w = keys_t + [release, release + 3], keys_w + [0.038, 0.07]
    return np.interp(np.arange(T), keys_t, keys_w)


def scene(right_offset: float = 0.0):
    """The box (at 0.3, 0, 0.14) held by the left TCP from frame 10; the right TCP beside it closes
    at 25 and holds from 28; the left opens at 35 (``right_offset`` m moves the right TCP away)."""
    box = np.tile(np.eye(4), (T, 1, 1))
    box[:, :3, 3] = [0.3, 0.0, 0.14]
    tcp = {"left": np.tile([0.3, 0.0, 0.15], (T, 1)), "right": np.tile([0.3, 0.0, 0.13 - right_offset], (T, 1))}
    return tcp, {"left": track(10, 35), "right": track(25)}, box


def test_a_handover_found_in_tracks_names_its_frames():
    tcp, gripper, box = scene()
    handover = find_handover("box", [Hold("left", 0), Hold("right", 28)], tcp, gripper, box)
    assert (handover.grasp, handover.takeover, handover.release) == (26, 28, 36)  # 5 mm into each closing/opening


def test_a_giver_that_never_lets_go_is_refused():
    tcp, gripper, box = scene()
    gripper["left"] = track(10)
    with pytest.raises(SourceError, match="the left arm never lets go of it"):
        find_handover("box", [Hold("left", 0), Hold("right", 28)], tcp, gripper, box)


def test_a_taker_closing_far_from_the_handover_spot_is_refused():
    tcp, gripper, box = scene(right_offset=0.2)
    with pytest.raises(SourceError, match="the right arm's TCP is 21.0 cm from the handover spot"):
        find_handover("box", [Hold("left", 0), Hold("right", 28)], tcp, gripper, box)


def test_an_object_changing_hands_twice_is_refused():
    tcp, gripper, box = scene()
    with pytest.raises(SourceError, match="changes hands 2 times"):
        find_handover("box", [Hold("left", 0), Hold("right", 28), Hold("left", 50)], tcp, gripper, box)
