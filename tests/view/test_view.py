"""manisplat-view without a browser: what each kind of folder loads, the Gaussians as viser draws
them, depth as points, the viewer's state (links at their FK poses, demonstrations switched), the
--video replay, and clear errors for what cannot be shown."""

from __future__ import annotations

import json
import shutil

import av
import numpy as np
import pytest
import torch
import viser

from manisplat.geometry.rotation import quat_to_matrix
from manisplat.render.sheets import labelled_sheet
from manisplat.scene.gaussians import GaussianSet
from manisplat.view.app import Viewer, depth_points
from manisplat.view.cli import main
from manisplat.view.content import ViewInputError, load_content
from manisplat.view.splats import splat_arrays
from manisplat.view.video import orbit_pose, write_video


@pytest.fixture
def server(free_port):
    srv = viser.ViserServer(host="127.0.0.1", port=free_port, verbose=False)
    yield srv
    srv.stop()


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def test_each_kind_of_folder_loads(folders):
    episode = load_content(folders["episode"])
    assert episode.kind == "episode" and episode.twin is None and len(episode.demos) == 1
    assert episode.demos[0].episode is not None and episode.notes == []
    recon = load_content(folders["recon"])  # the episode "demo" lies beside the twin: found by name
    assert recon.kind == "reconstruction" and recon.twin is not None and recon.demos[0].episode is not None
    assert set(recon.demos[0].object_poses) == {"box"} and recon.demos[0].object_poses["box"].shape == (32, 4, 4)
    aug = load_content(folders["aug"])
    assert aug.kind == "augmentation" and [d.name for d in aug.demos] == ["demo", "episode_0000"]
    new = aug.demos[1]
    assert new.validation is not None and new.object_poses["box"].shape == (len(new), 4, 4)


def test_what_is_missing_is_named(folders, tmp_path):
    lonely = tmp_path / "twin"
    shutil.copytree(folders["recon"], lonely)  # no episode beside it
    content = load_content(lonely)
    assert content.demos[0].episode is None and "pass --episode EP" in content.notes[0]
    assert load_content(lonely, episode=folders["episode"]).demos[0].episode is not None
    aug = tmp_path / "aug"
    shutil.copytree(folders["aug"], aug)
    report = json.loads((aug / "augment_report.json").read_text())
    (aug / "augment_report.json").write_text(json.dumps({**report, "recon": "moved_twin"}))
    with pytest.raises(ViewInputError, match="was not found beside it or here; pass --twin"):
        load_content(aug)
    assert load_content(aug, twin=folders["recon"]).twin is not None
    (lonely / "twin.json").unlink()
    with pytest.raises(ViewInputError, match="without twin.json"):
        load_content(lonely)
    with pytest.raises(ViewInputError, match="neither an episode"):
        load_content(tmp_path)


def test_splats_are_the_gaussians_covariances():
    rng = np.random.default_rng(0)
    n = 50
    quats = torch.as_tensor(rng.normal(size=(n, 4)))
    params = {"means": torch.as_tensor(rng.normal(size=(n, 3))), "quats": quats,
              "scales": torch.as_tensor(rng.uniform(-5, -2, (n, 3))), "opacities": torch.as_tensor(rng.normal(size=n)),
              "sh0": torch.as_tensor(rng.normal(size=(n, 3)) * 0.3)}
    arrays = splat_arrays(GaussianSet({k: v.float() for k, v in params.items()}))
    R = quat_to_matrix(quats).numpy()
    s = np.exp(params["scales"].numpy())
    expected = R @ (s[:, :, None] ** 2 * np.transpose(R, (0, 2, 1)))
    assert np.allclose(arrays.covariances, expected, rtol=1e-4, atol=1e-12)
    assert np.allclose(np.linalg.eigvalsh(arrays.covariances), np.sort(s ** 2, axis=1), rtol=1e-3)
    assert arrays.opacities.shape == (n, 1) and np.allclose(arrays.opacities[:, 0], torch.sigmoid(
        params["opacities"]).numpy(), atol=1e-6)
    assert arrays.rgbs.min() >= 0 and arrays.rgbs.max() <= 1


def test_depth_becomes_points_in_the_base_frame():
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # looking down from 1 m
    T_base_cam[:3, 3] = [0.2, 0.1, 1.0]
    depth = np.full((48, 64), 0.7, np.float32)
    depth[0, 0], depth[1, 1] = 0.0, np.nan
    rgb = np.zeros((48, 64, 3), np.uint8)
    points, colors = depth_points(depth, rgb, K, T_base_cam)
    assert len(points) == 48 * 64 - 2 and colors.shape == (len(points), 3)
    assert np.allclose(points[:, 2], 0.3, atol=1e-6)  # the plane 0.7 m below the camera
    centre = points[np.argmin(np.abs(points[:, 0] - 0.2) + np.abs(points[:, 1] - 0.1))]
    assert np.allclose(centre[:2], [0.2, 0.1], atol=0.01)
    assert len(depth_points(depth, rgb, K, T_base_cam, limit=100)[0]) <= 100


def test_the_viewer_moves_the_links_to_their_fk_poses(folders, server):
    content = load_content(folders["aug"])
    viewer = Viewer(content, server)
    try:
        for demo_index, frame in ((0, 20), (1, len(content.demos[1]) - 1)):
            viewer.select(demo_index)
            viewer.set_frame(frame)
            demo = content.demos[demo_index]
            links = content.robot.forward_kinematics(torch.as_tensor(demo.q[frame]),
                                                     torch.as_tensor(demo.gripper[frame])).numpy()
            for k, name in enumerate(content.robot.link_names):
                handle = viewer._link_frames["arm"][name]
                assert np.allclose(handle.position, links[k, :3, 3], atol=1e-6), name
                R = quat_to_matrix(torch.as_tensor(np.array(handle.wxyz), dtype=torch.float64)).numpy()
                assert np.allclose(R, links[k, :3, :3], atol=1e-6), name
            box = viewer._object_frames["box"]
            assert np.allclose(box.position, demo.object_poses["box"][frame][:3, 3], atol=1e-6)
            assert int(viewer._slider.value) == frame and viewer._slider.max == len(demo) - 1
        assert viewer.set_frame(10_000) is None and viewer.frame == len(content.demos[1]) - 1  # clamped
    finally:
        viewer.close()


def test_video_of_a_reconstruction_is_recorded_beside_twin_under_labels(folders, tmp_path):
    content = load_content(folders["recon"])
    result = write_video(content, tmp_path / "twin.mp4")
    header = result.height - 48
    assert (result.frames, result.width) == (32, 128) and header > 0
    assert not (tmp_path / "twin.partial.mp4").exists()
    with av.open(str(tmp_path / "twin.mp4")) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 32
    demo = content.demos[0]
    expected = labelled_sheet(np.zeros((48, 128, 3), np.uint8), ("recorded", "twin"), f"frame 5  t = {demo.t[5]:.2f} s")
    assert _psnr(frames[5][:header], expected[:header]) > 25  # the header names both halves and the frame
    assert _psnr(frames[5][header:, :64], demo.episode.rgb(5)) > 30  # left: the recording (H.264 CRF 20)
    twin_view = content.twin.render(demo.q[5], demo.gripper[5], {k: v[5] for k, v in demo.object_poses.items()}).rgb
    assert _psnr(frames[5][header:, 64:], twin_view) > 30  # right: the twin


def test_an_orbit_turns_the_camera_about_the_scene(folders, tmp_path):
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.5]
    turned = orbit_pose(T, np.array([0.0, 0.0, 0.2]), np.pi / 2)
    assert np.allclose(turned[:3, 3], [0.0, 1.0, 0.5]) and np.allclose(turned[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    content = load_content(folders["aug"])
    result = write_video(content, tmp_path / "orbit.mp4", orbit_deg=120)
    assert result.frames == sum(len(d) for d in content.demos) and (result.width, result.height) == (64, 48)
    with av.open(str(tmp_path / "orbit.mp4")) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    first = content.twin.render_frame(0).rgb  # the orbit starts at the episode's camera
    assert _psnr(frames[0], first) > 30
    demo, i = content.demos[-1], len(content.demos[-1]) - 1  # and ends turned 120 deg about the TCP path's middle
    target = content.robot.tcp_pose(torch.as_tensor(demo.q)).numpy()[:, :3, 3].mean(axis=0)
    poses = {k: v[i] for k, v in demo.object_poses.items()}
    turned = content.twin.render(demo.q[i], demo.gripper[i], poses,
                                 T_base_cam=orbit_pose(content.twin.T_base_cam, target, np.deg2rad(120))).rgb
    unturned = content.twin.render(demo.q[i], demo.gripper[i], poses).rgb
    assert _psnr(frames[-1], turned) > 30 and _psnr(frames[-1], unturned) < _psnr(frames[-1], turned) - 3


def test_command_line_errors(folders, tmp_path, capsys):
    assert main([str(tmp_path / "none")]) == 2
    assert "no such folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([str(folders["episode"]), "--orbit", "30"])
    assert exc.value.code == 2
    assert main([str(folders["episode"]), "--video", str(tmp_path / "ep.mp4"), "-q"]) == 0
    with pytest.raises(SystemExit) as exc:
        main([str(folders["episode"]), "--video", str(tmp_path / "ep.mp4")])
    assert exc.value.code == 2 and "exists; pass --overwrite" in capsys.readouterr().err
    assert main([str(folders["episode"]), "--video", str(tmp_path / "o.mp4"), "--orbit", "30"]) == 2
    assert "--orbit needs a twin" in capsys.readouterr().err
    report = json.loads((folders["aug"] / "augment_report.json").read_text())
    assert report["written"] == 1


@pytest.mark.parametrize("damage", ["missing", "garbage"])
def test_a_twin_without_its_tensors_is_a_one_line_error(folders, tmp_path, capsys, damage):
    broken = tmp_path / "twin"
    shutil.copytree(folders["recon"], broken)
    if damage == "missing":
        (broken / "twin.pt").unlink()
    else:
        (broken / "twin.pt").write_bytes(b"not a torch file")
    assert main([str(broken), "--video", str(tmp_path / "v.mp4"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "twin.pt" in err and ("missing" in err if damage == "missing" else "unreadable" in err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_the_command_serves_on_localhost_says_where_and_stops_on_sigterm(folders, free_port):
    import signal
    import subprocess
    import sys
    import urllib.request

    port = free_port
    proc = subprocess.Popen([sys.executable, "-m", "manisplat.view.cli", str(folders["recon"]), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # blocks until the server is up
        assert line.startswith(f"manisplat-view: {folders['recon']} (twin) at http://127.0.0.1:{port}"), line
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
        assert proc.stdout.read() == ""  # one line on stdout: viser's own banner is not printed
    finally:
        proc.kill()
