"""manisplat-reconstruct on a version 2 episode with two arms (a Cobot Magic): both arms drawn
and driven in the world frame, several objects prompted by name, each aligned with the arm that
handles it, and the prompts' usage errors named; the twin it writes (both arms, every camera),
shown by manisplat-view and augmented by manisplat-augment (each arm with its own box)."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest
import torch
import viser

from manisplat.augment.bimanual import MIN_ARM_CLEARANCE_M, BimanualPlanner
from manisplat.augment.cli import main as augment
from manisplat.augment.trajectory import AugmentConfig, Rejected
from manisplat.episode import Episode
from manisplat.exit_codes import ExitCode
from manisplat.episode.synthetic_arms import write_two_arm_sample_episode
from manisplat.reconstruct.cli import _cameras, main
from manisplat.reconstruct.config import TrainConfig
from manisplat.reconstruct.data import ReconstructionInputError, load_episode_data
from manisplat.reconstruct.masks import ObjectPrompt, complete_masks
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainStates
from manisplat.twin import Twin
from manisplat.view.app import Viewer
from manisplat.view.content import load_content


@pytest.mark.parametrize("prompts, message", [
    (["--object-point", "10,10", "--object-point", "20,20"], "2 object prompts: name each"),
    (["--object-point", "box=10,10", "--object-box", "box=1,1,5,5"], "one point or box per object"),
    (["--object-point", "=10,10"], "the name before '=' is empty"),
])
def test_several_prompts_must_each_name_their_object(tmp_path, capsys, prompts, message):
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path), "--out", str(tmp_path / "twin"), *prompts])
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def prompts_of(episode) -> list[str]:
    """Each box's start projected into the head camera's first frame, as ``--object-point NAME=U,V``."""
    camera = Episode.open(episode).cameras["cam_high"]
    prompts = []
    for name, start in (("box_left", (0.30, 0.12, 0.02)), ("box_right", (0.30, -0.12, 0.02))):
        x = np.linalg.inv(camera.T_mount_cam) @ np.array([*start, 1.0])
        u, v, w = camera.K @ x[:3]
        prompts += ["--object-point", f"{name}={u / w:.0f},{v / w:.0f}"]
    return prompts


@pytest.fixture(scope="module")
def wrist_episode(tmp_path_factory):
    return write_two_arm_sample_episode(tmp_path_factory.mktemp("two_arms") / "ep", duration=3.0, wrist_cameras=True)


@pytest.fixture(scope="module")
def two_arms(wrist_episode, tmp_path_factory):
    """The built-in two-arm sample's twin from its three cameras: --no-masks (both arms drawn, both
    boxes prompted by name in the head camera's first frame), a few iterations; (output folder,
    its metrics)."""
    out = tmp_path_factory.mktemp("two_arms_twin") / "twin"
    assert main([str(wrist_episode), "--out", str(out), "--no-masks", "--iters", "10", "-q",
                 *prompts_of(wrist_episode)]) == 0
    return out, json.loads((out / "metrics.json").read_text())


def test_each_object_follows_the_arm_that_handles_it_in_the_world_frame(two_arms):
    """Each box is aligned with its own arm's TCP and gripper (the right arm starts 0.3 s later):
    following the other arm would put it centimetres off its true world pose."""
    _, metrics = two_arms
    for name in ("box_left", "box_right"):
        anchored = metrics["pose_anchored"][name]
        assert anchored["moved_frames"] > 10
        assert anchored["et_cm"] < 0.5 and anchored["final"]["et_cm"] < 0.5, (name, anchored)


def test_both_arms_are_drawn_and_every_camera_is_scored(two_arms):
    out, metrics = two_arms
    for arm in ("left", "right"):
        assert (out / f"robot_{arm}_link6.ply").is_file()
    cameras = metrics["cameras"]
    assert set(cameras) == {"cam_high", "cam_left_wrist", "cam_right_wrist"}
    for name, scores in cameras.items():
        assert all(scores["psnr"][k] is not None for k in ("full", "robot", "object")), name
    assert metrics["psnr"] == cameras["cam_high"]["psnr"]  # the top-level figures are the head camera's
    assert metrics["rasterize_mode"] == "antialiased", "several cameras trained: --rasterize-mode auto antialiases"
    assert metrics["eps2d"] == 0.1, "the antialiased mode's own dilation"
    assert metrics["sh_degree"] == 3, "several cameras trained: --sh-degree auto learns a third band"
    assert metrics["lambda_mask"] == 0.0, "every camera's masks drawn: no mask loss by default"
    assert metrics["lambda_smooth"] == 1.0, "wrist cameras trained: the corrections' smoothness on by default"
    assert metrics["light_response"] is True, "wrist cameras trained: the parts' response to the light on by default"
    assert sorted(p.name for p in (out / "renders" / "cam_left_wrist" / "sheets").iterdir())


def test_the_twin_keeps_both_arms_and_every_camera_where_they_were(two_arms, wrist_episode):
    """twin.json + twin.pt of a two-arm, three-camera episode: each arm at its base, the head camera
    fixed, each wrist camera riding on its arm's link6 (at the simulator's true pose per frame),
    and each camera's render showing the robot where the episode's masks have it."""
    out, _ = two_arms
    twin = Twin.load(out)
    episode = Episode.open(wrist_episode)
    assert twin.frame == "world" and twin.arm_names == ("left", "right")
    for arm in twin.arms:
        np.testing.assert_array_equal(arm.T_world_base, episode.arms[arm.name].T_world_base)
    assert list(twin.cameras) == ["cam_high", "cam_left_wrist", "cam_right_wrist"]
    assert twin.reference.fixed and twin.cameras["cam_right_wrist"].mount == "right/link6"
    moving = [*twin.graph.links.values(), *twin.graph.objects.values()]
    assert all("light_gain" in g.params for g in moving), "the parts' response to the light is kept"
    gt = np.load(wrist_episode / "gt.npz")
    robot_values = [v for v, name in episode.meta.labels.items() if name.startswith("robot/")]
    for camera in twin.cameras:
        for f in (5, 25):
            links = twin.robot.forward_kinematics(torch.as_tensor(twin.q[f]), torch.as_tensor(twin.gripper[f]))
            if camera != "cam_high":
                np.testing.assert_allclose(twin.camera_pose(camera, links), gt[f"T_world_cam_{camera}"][f], atol=1e-4)
            view = twin.render_frame(f, camera=camera)
            truth = np.isin(episode.mask(f, camera), robot_values)
            ours = np.isin(view.labels, robot_values)
            assert view.rgb.shape == (*truth.shape, 3)
            assert (truth & ours).sum() / (truth | ours).sum() > 0.6, (camera, f)


def test_the_viewer_shows_a_two_arm_twin_with_its_wrist_cameras(two_arms):
    out, _ = two_arms
    content = load_content(out)
    assert set(content.arms) == {"left", "right"}
    assert {name: cam.mount for name, cam in content.cameras.items()} == {
        "cam_high": "world", "cam_left_wrist": "left/link6", "cam_right_wrist": "right/link6"}
    demo = content.demos[0]
    twin = Twin.load(out)
    np.testing.assert_array_equal(content.twin_render(demo, 7), twin.render_frame(7).rgb)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    viewer = Viewer(content, server)
    try:
        viewer.set_frame(7)
        links = twin.robot.forward_kinematics(torch.as_tensor(twin.q[7]), torch.as_tensor(twin.gripper[7])).numpy()
        for arm in ("left", "right"):  # each arm's link frames (in its base) carry that arm's Gaussians
            handle = viewer._link_frames[arm]["link6"]
            base = content.arms[arm].T_world_base
            world = base[:3, :3] @ np.asarray(handle.position) + base[:3, 3]
            np.testing.assert_allclose(world, links[twin.robot.link_names.index(f"{arm}/link6"), :3, 3], atol=1e-6)
        assert len(viewer._splats) == len(list(twin.graph.nodes()))
    finally:
        viewer.close()
        server.stop()


@pytest.fixture(scope="module")
def augmented(two_arms, tmp_path_factory):
    """manisplat-augment on the two-arm twin: two new demonstrations; (twin folder, output folder)."""
    out, _ = two_arms
    aug = tmp_path_factory.mktemp("two_arm_aug") / "aug"
    assert augment([str(out), "--n", "2", "--out", str(aug), "--seed", "1", "-q"]) == ExitCode.OK
    return out, aug


def _held(poses: np.ndarray) -> np.ndarray:
    """[T] bool: frames where an object is off both its first and its last pose (carried)."""
    return (np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1) > 1e-3) & \
        (np.linalg.norm(poses[:, :3, 3] - poses[-1, :3, 3], axis=1) > 1e-3)


def test_each_arm_moves_its_own_box_and_carries_it_as_the_source_did(augmented):
    """Each new demonstration (version 2: both arms with their commands, every camera with depth
    and masks) starts each box elsewhere, and the arm that handles it carries it rigidly in its
    gripper (the box in that arm's TCP frame constant while carried)."""
    twin_dir, aug = augmented
    twin = Twin.load(twin_dir)
    report = json.loads((aug / "augment_report.json").read_text())
    assert report["valid"] == 2 and report["min_arm_clearance_m"] >= 0.005
    for k in range(2):
        ep = Episode.open(aug / f"episode_{k:04d}")
        assert list(ep.arms) == ["left", "right"]
        assert list(ep.cameras) == ["cam_high", "cam_left_wrist", "cam_right_wrist"]
        assert all(ep.has_images(kind, cam) for cam in ep.cameras for kind in ("depth", "masks"))
        poses = np.load(ep.path / "object_poses.npz")
        for arm, box in (("left", "box_left"), ("right", "box_right")):
            frames = ep.arm_frames(arm)
            assert frames.actions is not None
            assert np.linalg.norm(poses[box][0, :3, 3] - twin.object_poses[box][0, :3, 3]) > 0.002
            tcp = ep.arms[arm].T_world_base @ twin.robot.arms[arm].tcp_pose(torch.as_tensor(frames.q)).numpy()
            held = _held(poses[box])
            assert held.sum() >= 5, (arm, held.sum())
            in_tcp = np.linalg.inv(tcp[held]) @ poses[box][held]
            np.testing.assert_allclose(in_tcp, np.broadcast_to(in_tcp[0], in_tcp.shape), atol=1e-5)


def test_a_wrist_camera_sees_the_moved_box_from_its_link_at_the_new_joints(augmented):
    """Where the episode says the left wrist camera is (its arm's base, FK of the new joints,
    T_mount_cam), the carried box projects onto pixels its written masks label as the box."""
    twin_dir, aug = augmented
    twin = Twin.load(twin_dir)
    ep = Episode.open(aug / "episode_0000")
    camera = ep.cameras["cam_left_wrist"]
    box_value = next(v for v, name in ep.meta.labels.items() if name == "object/box_left")
    poses = np.load(ep.path / "object_poses.npz")["box_left"]
    frames = ep.arm_frames("left")
    robot = twin.robot.arms["left"]
    seen = 0
    for f in np.flatnonzero(_held(poses))[::3]:
        T_link = robot.forward_kinematics(torch.as_tensor(frames.q[f]), torch.as_tensor(frames.gripper[f])).numpy()
        T_cam = ep.arms["left"].T_world_base @ T_link[robot.link_names.index("link6")] @ camera.T_mount_cam
        centre = twin_centre(twin, "box_left", poses[f])
        x = np.linalg.inv(T_cam) @ np.append(centre, 1.0)
        u, v = (camera.K @ x[:3])[:2] / x[2]
        window = ep.mask(int(f), "cam_left_wrist")[max(0, int(v) - 3):int(v) + 4, max(0, int(u) - 3):int(u) + 4]
        seen += bool(x[2] > 0 and (window == box_value).any())
    assert seen >= 2


def test_the_viewer_plays_the_new_two_arm_demonstrations_over_their_twin(augmented):
    _, aug = augmented
    content = load_content(aug)
    assert content.kind == "augmentation" and set(content.arms) == {"left", "right"} and content.twin is not None
    assert [d.name for d in content.demos][1:] == ["episode_0000", "episode_0001"]
    new = content.demos[1]
    poses = np.load(aug / "episode_0000" / "object_poses.npz")
    np.testing.assert_array_equal(content.object_poses_at(new, 4)["box_left"], poses["box_left"][4])
    head = content.cameras["cam_high"]
    assert content.twin_render(new, 4).shape == (head.height, head.width, 3)


def twin_centre(twin: Twin, name: str, T_world_obj: np.ndarray) -> np.ndarray:
    """The object's bounding-box centre (world) at pose ``T_world_obj``."""
    from manisplat.augment.frames import centre_offset

    return (T_world_obj @ centre_offset(twin, name))[:3, 3]


def test_arms_that_would_come_too_close_are_rejected_naming_the_links(two_arms):
    out, _ = two_arms
    planner = BimanualPlanner(Twin.load(out))
    assert planner.run({}, AugmentConfig()).validation["min_arm_clearance_m"] >= MIN_ARM_CLEARANCE_M
    shifted = planner.arms["left"].T_world_base.copy()
    shifted[1, 3] -= 0.05  # the right arm's base 5 cm beside the left's
    planner.arms["right"].T_world_base = shifted
    with pytest.raises(Rejected) as rejected:
        planner.run({}, AugmentConfig())
    assert rejected.value.reason == "arm_collision" and "left/" in rejected.value.detail


def test_arms_that_would_meet_on_the_way_are_cleared_by_one_waiting_at_its_start(two_arms, monkeypatch):
    """The right arm's base 50 cm beside the left's: moving at once, the wrists meet halfway; with
    the left arm 1.5 s late they pass 5 mm apart or more. The waiting arm holds its first state
    (joints, gripper and commands) and then moves as planned."""
    out, _ = two_arms
    planner = BimanualPlanner(Twin.load(out))
    alone = planner.run({}, AugmentConfig()).arms["left"]
    shifted = planner.arms["left"].T_world_base.copy()
    shifted[1, 3] -= 0.50
    planner.arms["right"].T_world_base = shifted
    traj = planner.run({}, AugmentConfig())
    waited = traj.validation["waited"]
    assert waited["without"]["min_arm_clearance_m"] < MIN_ARM_CLEARANCE_M <= traj.validation["min_arm_clearance_m"]
    assert waited["arm"] == "left" and waited["s"] > 0
    wait = round(waited["s"] * planner.fps)
    left = traj.arms["left"]
    np.testing.assert_array_equal(left.q[:wait + 1], np.broadcast_to(alone.q[0], (wait + 1, 6)))
    np.testing.assert_array_equal(left.action_q[:wait], np.broadcast_to(alone.q[0], (wait, 6)))
    np.testing.assert_array_equal(left.q[wait:], alone.q[:len(left.q) - wait])  # (alone: held to the right arm's end)
    assert left.segments[0]["kind"] == "wait" and left.segments[1]["frames"][0] == wait
    monkeypatch.setattr("manisplat.augment.bimanual.WAITS_S", ())
    with pytest.raises(Rejected) as rejected:
        planner.run({}, AugmentConfig())
    assert rejected.value.reason == "arm_collision"


def test_explicit_poses_are_refused_for_two_arms(two_arms, tmp_path, capsys):
    out, _ = two_arms
    poses = tmp_path / "poses.json"
    poses.write_text("[]")
    assert augment([str(out), "--poses", str(poses), "--out", str(tmp_path / "aug"), "-q"]) == ExitCode.BAD_INPUT
    assert "arms left, right" in capsys.readouterr().err


def test_the_cameras_trained_are_those_named_and_the_fixed_one_seeds_the_scene(wrist_episode):
    assert _cameras(wrist_episode, None) == ("cam_high", ["cam_left_wrist", "cam_right_wrist"])
    assert _cameras(wrist_episode, ["cam_left_wrist", "cam_high"]) == ("cam_high", ["cam_left_wrist"])
    assert _cameras(wrist_episode, ["cam_high"]) == ("cam_high", [])
    with pytest.raises(ReconstructionInputError, match="no camera cam_low"):
        _cameras(wrist_episode, ["cam_high", "cam_low"])


def test_a_wrist_camera_is_posed_at_each_frame_by_forward_kinematics(wrist_episode):
    gt = np.load(wrist_episode / "gt.npz")
    for camera in ("cam_left_wrist", "cam_right_wrist"):
        view = load_episode_data(wrist_episode, camera=camera, load_meshes=False)
        assert view.riding and view.viewmat.shape == (view.n_frames, 4, 4)
        T_world_cam = torch.linalg.inv(view.viewmat.double()).numpy()
        np.testing.assert_allclose(T_world_cam, gt[f"T_world_cam_{camera}"], atol=2e-5)


def head_view_with_drawn_masks(episode):
    """The head camera's view of ``episode`` without its masks, the robot's and each prompted box's
    drawn instead (as ``--no-masks`` draws them)."""
    data = load_episode_data(episode, use_masks=False)
    links = [n for n in data.robot.link_names if data.robot.visuals.get(n)]
    names = prompts_of(episode)[1::2]
    complete_masks(data, links, [ObjectPrompt(t.split("=")[0], point=tuple(map(float, t.split("=")[1].split(","))))
                                 for t in names], progress=False)
    return data


def test_wrist_cameras_masks_are_drawn_from_the_robot_and_the_objects_at_their_poses(wrist_episode):
    """After alignment, each wrist camera's masks (robot at FK, each box's model at its pseudo
    pose) cover what its own simulated masks say, robot and boxes alike."""
    data = head_view_with_drawn_masks(wrist_episode)
    views = {name: load_episode_data(wrist_episode, camera=name, use_masks=False)
             for name in ("cam_left_wrist", "cam_right_wrist")}
    build(data, make_plan(data), TrainConfig(iters=1), views=views, check_extrinsic=False)  # the sample's rig is exact
    for name, view in views.items():
        for role in ("robot", "object"):
            drawn = torch.stack([torch.isin(view.masks[f], torch.tensor(
                sorted(view.labels.robot if role == "robot" else view.labels.objects), dtype=torch.uint8))
                for f in range(view.n_frames)])
            truth = torch.stack([view.eval_region(f, role) for f in range(view.n_frames)])
            iou = float((drawn & truth).sum() / (drawn | truth).sum())
            # the boxes' simulated masks carry the painter's notch where a finger meets the box
            assert iou > (0.85 if role == "robot" else 0.6), (name, role, iou)


def _head_and_left_wrist_views(episode):
    """The head camera's view of ``episode`` and its left wrist camera's, with the episode's masks
    (a test of what training does with them need not draw them, nor check the exact rig)."""
    return load_episode_data(episode), {"cam_left_wrist": load_episode_data(episode, camera="cam_left_wrist")}


def test_a_fixed_cameras_gradients_on_the_objects_alone_are_weighed(wrist_episode):
    """With --fixed-camera-weight W, a head camera frame's gradients on the objects' Gaussians are
    W times what its loss gave them; the robot's and the background's are as given, and so is
    everything a wrist camera's frame gives."""
    data, views = _head_and_left_wrist_views(wrist_episode)
    rec, _ = build(data, make_plan(data), TrainConfig(iters=1, fixed_camera_weight=7.0, shadows=False), views=views,
                   check_extrinsic=False)
    frame = rec.plan.train_frames[len(rec.plan.train_frames) // 2]
    nodes = {node.name: node for node in rec.graph.nodes()}
    objects = {f"object/{name}" for name in ("box_left", "box_right")}
    for camera, expected in ((None, 7.0), ("cam_left_wrist", 1.0)):
        rec.optimizer.zero_grad(set_to_none=True)
        rec.losses(frame, camera)[0].backward()
        given = {(node.name, k): p.grad.clone() for node in rec.graph.nodes()
                 for k, p in node.gaussians.params.items() if p.grad is not None}
        rec._weigh_fixed_camera(camera)
        assert {node for node, _ in given} >= objects | {"background"}
        for (node, k), grad in given.items():
            weighed = nodes[node].gaussians.params[k].grad
            factor = expected if node in objects else 1.0
            torch.testing.assert_close(weighed, grad * factor, msg=f"{camera} {node}.{k}")
        seen = {node for (node, k), grad in given.items() if node in objects and k == "sh0" and grad.abs().sum() > 0}
        assert seen == objects if camera is None else seen, camera  # the left wrist camera sees its own box


def test_the_reference_camera_must_be_fixed(wrist_episode, tmp_path, capsys):
    assert main([str(wrist_episode), "--out", str(tmp_path / "t"), "--cameras", "cam_left_wrist", "--no-masks",
                 *prompts_of(wrist_episode)]) == 2
    assert "none is fixed" in capsys.readouterr().err


def test_a_fixed_cameras_share_of_the_iterations_is_drawn_as_asked():
    """With a fixed camera's share S, about S of the iterations draw the head camera's frames and
    the rest the wrist cameras' alike; without one every (camera, frame) pair is drawn alike, as
    one uniform choice over them all."""
    import collections
    import random

    wrists = {"cam_left_wrist", "cam_right_wrist"}
    every = [(camera, frame) for camera in (None, *sorted(wrists)) for frame in range(0, 40, 3)]
    counts = {}
    for share in (None, 0.6):
        rng = random.Random(3)
        drawn = [TrainStates(every, wrists, share).draw(rng) for _ in range(6000)]
        counts[share] = collections.Counter(camera for camera, _ in drawn)
        assert set(drawn) == set(every)
    assert counts[None][None] / 6000 == pytest.approx(1 / 3, abs=0.02)
    assert counts[0.6][None] / 6000 == pytest.approx(0.6, abs=0.02)
    for wrist in wrists:
        assert counts[0.6][wrist] / 6000 == pytest.approx(0.2, abs=0.02)
    uniform, drawn_alike = random.Random(5), random.Random(5)
    alike = TrainStates(every, wrists, None)
    assert [alike.draw(drawn_alike) for _ in range(50)] == [uniform.choice(every) for _ in range(50)]


def test_a_fixed_cameras_share_needs_both_kinds_of_camera(wrist_episode, tmp_path, capsys):
    states = [(None, 0), ("cam_left_wrist", 0)]
    for riding in (set(), {None, "cam_left_wrist"}):
        with pytest.raises(ValueError, match="needs fixed and riding cameras trained"):
            TrainStates(states, riding, 0.5)
    for share in (0.0, 1.0):
        with pytest.raises(ValueError, match="within"):
            TrainStates(states, {"cam_left_wrist"}, share)
    assert main([str(wrist_episode), "--out", str(tmp_path / "t"), "--cameras", "cam_high", "--no-masks", "-q",
                 "--iters", "1", "--fixed-camera-share", "0.5", *prompts_of(wrist_episode)]) == 2
    assert "--fixed-camera-share: no camera riding on an arm is trained" in capsys.readouterr().err
    for value in ("0", "1", "x"):
        with pytest.raises(SystemExit) as exit_:
            main([str(wrist_episode), "--out", str(tmp_path / "t"), "--fixed-camera-share", value])
        assert exit_.value.code == 2 and "argument --fixed-camera-share:" in capsys.readouterr().err


def test_a_checkpoint_resumes_only_with_the_share_it_was_trained_with(wrist_episode):
    """A reconstruction draws its head camera's frames as the fixed ones and its wrist camera's as
    the riding ones, and resumes only a checkpoint trained with its own share (unset before it)."""
    data, views = _head_and_left_wrist_views(wrist_episode)

    def reconstruction(share):
        return build(data, make_plan(data), TrainConfig(iters=1, fixed_camera_share=share, shadows=False),
                     views=views, check_extrinsic=False)[0]

    shared = reconstruction(0.5)
    states = shared._train_states()  # the head camera's pairs fixed, the wrist camera's riding
    assert ({c for c, _ in states.fixed}, {c for c, _ in states.riding}, states.fixed_share) == \
        ({None}, {"cam_left_wrist"}, 0.5)
    state, unshared = shared.state_dict(), reconstruction(None)
    with pytest.raises(ValueError, match="trained with --fixed-camera-share 0.5, this run asks for alike"):
        unshared.load_state_dict(state)
    del state["config"]["fixed_camera_share"]  # a checkpoint from before the option: every camera alike
    unshared.config.fixed_camera_share = 0.7
    with pytest.raises(ValueError, match="trained with --fixed-camera-share alike, this run asks for 0.7"):
        unshared.load_state_dict(state)
    unshared.config.fixed_camera_share = None
    unshared.load_state_dict(state)
