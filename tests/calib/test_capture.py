import numpy as np

from manisplat.calib.capture import PoseAdvisor, capture
from manisplat.calib.cli import main
from manisplat.calib.episode_solve import solve_episode
from manisplat.calib.poses import make_T, pose_difference, rodrigues
from manisplat.calib.synth import default_truth, write_latency_episode
from manisplat.drivers.replay import EpisodeArm, EpisodeCamera
from manisplat.episode import Episode
from manisplat.robot import builtin_piper


def test_advisor_says_which_poses_add_information():
    adv = PoseAdvisor(min_new_angle_deg=15)
    T0 = make_T(np.eye(3), [0.3, 0, 0.2])
    assert adv.assess(T0).adds
    adv.add(T0)
    near = adv.assess(T0 @ make_T(rodrigues([0, 0, np.radians(5)]), [0.01, 0, 0]))
    assert not near.adds and "little new information" in near.message
    far = adv.assess(T0 @ make_T(rodrigues([np.radians(30), 0, 0]), [0, 0, 0]))
    assert far.adds and far.nearest_deg > 29
    adv.add(T0 @ make_T(rodrigues([0, 0, np.radians(30)]), [0, 0, 0]))
    adv.add(T0 @ make_T(rodrigues([0, 0, np.radians(60)]), [0, 0, 0]))
    # a third rotation about z adds little diversity; a rotation about x widens the axis spread
    assert adv.assess(T0 @ make_T(rodrigues([np.radians(25), 0, 0]), [0, 0, 0])).spread_after_deg > 5
    assert "poses" in adv.summary()


def test_capture_from_replayed_arm_and_camera_then_solve(tmp_path, spec):
    """The capture loop on the project's arm and camera replays (no hardware): still poses that
    add information are recorded automatically and the result solves."""
    truth = default_truth(spec)
    write_latency_episode(tmp_path / "session", spec, truth, rng=np.random.default_rng(3), duration_s=16.0, fps=6.0,
                          move_s=(0.6, 0.8), pause_s=(1.4, 1.6), spread=np.array([0.3, 0.25, 0.25, 0.6, 0.45, 0.9]),
                          blur_sigma=0.6)
    msgs = []
    n = capture(EpisodeArm(tmp_path / "session"), EpisodeCamera(tmp_path / "session"), builtin_piper(), spec,
                tmp_path / "out", auto=True, settle_s=0.6, frames_per_pose=2, say=msgs.append)
    assert n >= 6
    assert any("adds information" in m for m in msgs)
    ep = Episode.open(tmp_path / "out")
    assert len(ep) == 2 * n and "pose" in ep.frames.extra and ep.meta.complete
    solved = solve_episode(tmp_path / "out", spec)
    rot, trans = pose_difference(solved.result.T_mount_cam, truth.T_base_cam)
    assert rot < 0.1 and trans < 1.0
    # the raw session, moving frames included: those are refused by the joints.csv speed check
    raw = solve_episode(tmp_path / "session", spec)
    moving = [i for i, why in raw.rejected.items() if why.startswith("arm moving")]
    assert 10 < len(moving) < len(Episode.open(tmp_path / "session")) - 10
    rot, trans = pose_difference(raw.result.T_mount_cam, truth.T_base_cam)
    assert rot < 0.1 and trans < 1.0


def test_capture_command_with_replay(tmp_path, spec):
    from manisplat.calib.board import save_board
    truth = default_truth(spec)
    write_latency_episode(tmp_path / "session", spec, truth, rng=np.random.default_rng(4), duration_s=3.0, fps=4.0,
                          move_s=(0.6, 0.8), pause_s=(1.2, 1.3))
    save_board(tmp_path / "board.json", spec)
    code = main(["capture", "--replay", str(tmp_path / "session"), "--board", str(tmp_path / "board.json"),
                 "--out", str(tmp_path / "out"), "--auto", "--settle", "0.6", "--frames-per-pose", "1"])
    assert code == 5  # fewer than 3 poses in 3 s: "not enough data", with the episode written
    assert Episode.open(tmp_path / "out").meta.complete
