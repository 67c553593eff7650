"""manisplat-view on a version 2 episode (two arms, three cameras) without a browser: each arm's
links at ``T_world_base @ FK``, each camera's frustum at its mount (the wrist cameras riding on
link6), each camera's image, the head camera's depth as points in the world, the video with every
camera side by side, and clear errors for what cannot be placed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import av
import numpy as np
import pytest
import torch
import viser

from manisplat.episode import ArmInfo, CameraInfo
from manisplat.episode.reader import Episode
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.geometry.rotation import quat_to_matrix
from manisplat.render.sheets import labelled_sheet
from manisplat.view.app import Viewer
from manisplat.view.cli import main
from manisplat.view.content import ViewInputError, load_content
from manisplat.view.video import write_video

W, H, FRAMES, FPS = 48, 36, 8, 10.0
DEPTH_M = 0.6
"""The head camera sees a plane 0.6 m below it: 0.15 m above the world's origin."""


def _pose(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = xyz
    return T


T_WORLD_BASE = {"left": _pose(0.0, (0.0, 0.3, 0.0)), "right": _pose(12.0, (0.05, -0.3, 0.0))}
T_HIGH = np.array([[0.0, -1.0, 0.0, 0.3], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.75], [0.0, 0.0, 0.0, 1.0]])
T_WRIST = np.array([[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.075], [0.0, 0.0, -1.0, 0.05], [0.0, 0.0, 0.0, 1.0]])
MOUNTS = {"cam_high": ("world", T_HIGH), "cam_left_wrist": ("left/link6", T_WRIST),
          "cam_right_wrist": ("right/link6", T_WRIST)}
COLOURS = {"cam_high": (200, 60, 40), "cam_left_wrist": (40, 180, 60), "cam_right_wrist": (50, 70, 220)}


def _joints(arm: str, i: int) -> list[float]:
    """Seven values (6 joints rad, gripper m) that move over the episode, differently per arm."""
    s = 1.0 if arm == "left" else -1.0
    x = i / (FRAMES - 1)
    return [s * 0.4 * x, 0.6 + 0.5 * x, -0.9 + 0.3 * x, s * 0.2, 0.5 - 0.4 * x, s * 0.8 * x, 0.01 + 0.05 * x]


def _image(camera: str, i: int) -> np.ndarray:
    """A smooth image per camera and frame (H.264 keeps it close)."""
    v, u = np.mgrid[0:H, 0:W]
    base = np.array(COLOURS[camera], np.float64)
    shade = 0.6 + 0.4 * (u / W) * (1 - v / (2 * H)) + 0.02 * i
    return np.clip(base * shade[..., None], 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def cobot(tmp_path_factory) -> Path:
    """A Cobot Magic-like version 2 episode: arms left and right, cam_high (with depth) and two wrist cameras."""
    path = tmp_path_factory.mktemp("view_v2") / "cobot"
    arms = [ArmInfo(name=a, T_world_base=T) for a, T in T_WORLD_BASE.items()]
    cameras = [CameraInfo(name=c, width=W, height=H, K=[[40.0, 0, 23.5], [0, 40.0, 17.5], [0, 0, 1]], mount=m,
                          T_mount_cam=T) for c, (m, T) in MOUNTS.items()]
    depth = np.full((H, W), round(DEPTH_M / 0.001), np.uint16)
    with EpisodeWriterV2(path, arms, cameras, FPS, source="simulation", depth_scale=0.001) as writer:
        for i in range(FRAMES):
            writer.add_frame(i / FPS, {a: _joints(a, i) for a in T_WORLD_BASE},
                             {c: _image(c, i) for c in MOUNTS}, depth={"cam_high": depth})
    return path


@pytest.fixture
def server(free_port):
    srv = viser.ViserServer(host="127.0.0.1", port=free_port, verbose=False)
    yield srv
    srv.stop()


def _matrix(handle) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(torch.as_tensor(np.array(handle.wxyz), dtype=torch.float64)).numpy()
    T[:3, 3] = handle.position
    return T


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def test_every_arm_and_camera_is_loaded(cobot):
    content = load_content(cobot)
    assert content.kind == "episode" and list(content.arms) == ["left", "right"] and content.notes == []
    assert list(content.cameras) == list(MOUNTS)
    for name, (mount, T) in MOUNTS.items():
        assert content.cameras[name].mount == mount and np.array_equal(content.cameras[name].T_mount_cam, T)
    demo = content.demos[0]
    for arm, T in T_WORLD_BASE.items():
        assert np.array_equal(content.arms[arm].T_world_base, T)
        q = np.array([_joints(arm, i) for i in range(FRAMES)])
        assert np.array_equal(demo.arms[arm].q, q[:, :6]) and np.array_equal(demo.arms[arm].gripper, q[:, 6])
    with pytest.raises(ValueError, match="arms left, right"):
        content.robot


def test_arms_links_tcps_frustums_and_images_are_placed_in_the_world(cobot, server):
    content = load_content(cobot)
    episode = Episode.open(cobot)
    viewer = Viewer(content, server)
    try:
        wrist_poses = []
        for frame in (0, FRAMES - 1):
            viewer.set_frame(frame)
            demo = content.demos[0]
            for arm, T_world_base in T_WORLD_BASE.items():
                robot = content.arms[arm].robot
                q, gripper = demo.arms[arm].q[frame], demo.arms[arm].gripper[frame]
                links = robot.forward_kinematics(torch.as_tensor(q), torch.as_tensor(gripper)).numpy()
                base = _matrix(viewer._arm_bases[arm])
                assert np.allclose(base, T_world_base, atol=1e-6), arm
                for k, link in enumerate(robot.link_names):
                    shown = base @ _matrix(viewer._link_frames[arm][link])
                    assert np.allclose(shown, T_world_base @ links[k], atol=1e-6), (arm, link)
                camera = f"cam_{arm}_wrist"
                expected = T_world_base @ links[robot.link_names.index("link6")] @ T_WRIST
                assert np.allclose(_matrix(viewer._frustums[camera]), expected, atol=1e-6), camera
                wrist_poses.append(expected)
                tcp = T_world_base @ robot.tcp_pose(torch.as_tensor(q)).numpy()
                assert np.allclose(viewer._tcp_markers[arm].position, tcp[:3, 3], atol=1e-6), arm
            assert np.allclose(_matrix(viewer._frustums["cam_high"]), T_HIGH, atol=1e-6)
            for camera in MOUNTS:
                recorded = episode.rgb(frame, camera)
                assert np.array_equal(viewer._recorded[camera].image, recorded), camera
                assert np.array_equal(viewer._frustums[camera].image, recorded), camera
        assert np.abs(wrist_poses[0][:3, 3] - wrist_poses[2][:3, 3]).max() > 0.02  # the wrist camera moved
    finally:
        viewer.close()


def test_the_head_cameras_depth_is_points_in_the_world(cobot, server):
    viewer = Viewer(load_content(cobot), server)
    try:
        assert list(viewer._depth_clouds) == ["cam_high"]  # the wrist cameras have no depth
        points = np.asarray(viewer._depth_clouds["cam_high"].points, np.float64)
        assert len(points) == W * H
        assert np.allclose(points[:, 2], 0.75 - DEPTH_M, atol=1e-3)  # in the world, not the camera
        centre = points.mean(axis=0)
        assert np.allclose(centre[:2], [0.3, 0.0], atol=0.02)  # under the camera
    finally:
        viewer.close()


def test_the_video_shows_every_camera_side_by_side_under_its_name(cobot, tmp_path):
    content = load_content(cobot)
    result = write_video(content, tmp_path / "cobot.mp4")
    header = result.height - H
    assert (result.frames, result.width) == (FRAMES, 3 * W) and header > 0
    with av.open(str(tmp_path / "cobot.mp4")) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == FRAMES
    expected = labelled_sheet(np.zeros((H, 3 * W, 3), np.uint8), tuple(MOUNTS), f"frame 5  t = {5 / FPS:.2f} s")
    assert _psnr(frames[5][:header], expected[:header]) > 25
    for k, camera in enumerate(MOUNTS):
        assert _psnr(frames[5][header:, k * W:(k + 1) * W], _image(camera, 5)) > 30, camera
    assert main([str(cobot), "--video", str(tmp_path / "cli.mp4"), "-q"]) == 0


@pytest.mark.parametrize("damage, named", [
    (("cameras", "cam_left_wrist", "T_mount_cam", None), "camera cam_left_wrist has no T_mount_cam"),
    (("arms", "right", "T_world_base", None), "arm right has no T_world_base"),
    (("cameras", "cam_right_wrist", "mount", "right/link99"), "camera cam_right_wrist rides on 'right/link99'"),
])
def test_what_cannot_be_placed_is_named(cobot, tmp_path, damage, named, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(cobot, broken)
    meta = json.loads((broken / "episode.json").read_text())
    group, name, key, value = damage
    meta[group][name][key] = value
    (broken / "episode.json").write_text(json.dumps(meta))
    with pytest.raises(ViewInputError, match=named):
        load_content(broken)
    assert main([str(broken), "--video", str(tmp_path / "v.mp4"), "-q"]) == 2
    assert named in capsys.readouterr().err


def test_a_version_1_wrist_camera_rides_on_its_link(tmp_path):
    from manisplat.episode.synthetic import write_sample_episode

    episode = write_sample_episode(tmp_path / "v1", frames=8, width=32, height=24)
    meta = json.loads((episode / "episode.json").read_text())
    meta["camera"].update(mount="link6", T_mount_cam=T_WRIST.tolist())
    (episode / "episode.json").write_text(json.dumps(meta))
    content = load_content(episode)
    assert list(content.arms) == ["arm"] and np.array_equal(content.arms["arm"].T_world_base, np.eye(4))
    (name, camera), = content.cameras.items()
    assert camera.mount == "arm/link6"
    demo, robot = content.demos[0], content.robot
    for i in (0, 7):
        link6 = robot.link_pose(torch.as_tensor(demo.q[i]), "link6", torch.as_tensor(demo.gripper[i])).numpy()
        assert np.allclose(content.camera_pose(name, demo, i), link6 @ T_WRIST, atol=1e-9)
