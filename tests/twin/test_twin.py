"""The twin a reconstruction writes: loaded from its folder alone, it renders the training states
as the trainer does, and new states (objects moved) where geometry says they are."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from manisplat.episode import Episode
from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.outputs import write_twin
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainConfig
from manisplat.twin import Twin, TwinFormatError
from manisplat.twin.commands import led


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A briefly trained reconstruction of a small sample, its twin folder, and its episode (moved
    away after writing, so that loading cannot lean on it)."""
    root = tmp_path_factory.mktemp("twin")
    episode = write_sample_episode(root / "ep", frames=16, width=80, height=60)
    data = load_episode_data(episode)
    rec, alignments = build(data, make_plan(data), TrainConfig(iters=30, shadow_start=10, eval_every=1000,
                                                                  shadow_casters="meshes", rasterize_mode="antialiased"))
    rec.train(progress=False)
    out = root / "twin"
    write_twin(rec, alignments, out)
    moved = shutil.move(str(episode), str(root / "elsewhere"))
    return rec, out, Episode.open(moved)


def test_the_twin_renders_the_training_state_as_the_trainer_does(trained):
    rec, out, _ = trained
    twin = Twin.load(out)
    assert twin.graph.shadows is not None, "the learned light must travel with the twin"
    assert twin.graph.shadows.receivers == "all"
    assert rec.graph.shadows.has_casters, "the built-in robot's link meshes cast the shadows"
    torch.testing.assert_close(twin.graph.shadows.caster_points, rec.graph.shadows.caster_points)
    torch.testing.assert_close(twin.graph.shadows.moving_strength, rec.graph.shadows.moving_strength)
    moving = rec.graph.shadows.moving_strength_logit
    assert rec.optimizer.state[moving]["step"] > 0, "the moving parts' shadow strength is learned"
    evaluation = rec.evaluation_poses()
    for frame in (0, 7, 15):
        with torch.no_grad():
            # the scene itself: the twin has no camera exposure (the trainer's render(frame) applies the frame's gains)
            expected = rec.render_state(rec.data.link_poses[frame], rec.object_poses(frame, evaluation),
                                        rec.data.link_quats[frame])[0].clamp(0, 1).numpy()
        view = twin.render_frame(frame)
        assert view.rgb.shape == (60, 80, 3) and view.rgb.dtype == np.uint8
        assert np.abs(view.rgb / 255.0 - expected).max() <= 1 / 255 + 1e-6


def test_depth_and_labels_agree_with_the_episode(trained):
    _, out, episode = trained
    twin = Twin.load(out)
    robot_values = [v for v, name in episode.meta.labels.items() if name.startswith("robot/")]
    for frame in (3, 12):
        view = twin.render_frame(frame)
        truth = episode.mask(frame)
        robot_true, robot_ours = np.isin(truth, robot_values), np.isin(view.labels, robot_values)
        iou = (robot_true & robot_ours).sum() / (robot_true | robot_ours).sum()
        assert iou > 0.7, f"robot label IoU {iou:.2f} at frame {frame}"
        depth = episode.depth(frame)
        valid = (depth > 0) & (view.depth > 0)
        assert valid.sum() > 0.9 * (depth > 0).sum(), "the twin renders no depth where the episode has some"
        assert np.median(np.abs(view.depth[valid] - depth[valid])) < 0.01  # m


def test_a_moved_object_is_rendered_where_it_was_moved(trained):
    _, out, episode = trained
    twin = Twin.load(out)
    box = [v for v, name in episode.meta.labels.items() if name == "object/box"][0]
    frame = 0  # resting on the table, in view
    pose = twin.object_poses["box"][frame].copy()
    shifted = pose.copy()
    shifted[:2, 3] += [0.05, -0.04]
    views = [twin.render(twin.q[frame], twin.gripper[frame], {"box": T}) for T in (pose, shifted)]
    centres = []
    for view in views:
        rows, cols = np.nonzero(view.labels == box)
        assert len(rows) > 5
        centres.append(np.array([cols.mean(), rows.mean()]))
    # where the camera model says the box's centre moved (its canonical origin, projected)
    K, V = twin.K, np.linalg.inv(twin.T_base_cam)
    centre_obj = np.array([*np.asarray(twin.graph.objects["box"].params["means"].detach().mean(0)), 1.0])
    projected = []
    for T in (pose, shifted):
        cam = V @ T @ centre_obj
        projected.append((K @ (cam[:3] / cam[2]))[:2])
    moved_image, moved_model = centres[1] - centres[0], projected[1] - projected[0]
    assert np.linalg.norm(moved_image - moved_model) < 0.25 * np.linalg.norm(moved_model) + 1.0


def test_the_twin_file_holds_tensors_only(trained):
    _, out, _ = trained
    tensors = torch.load(out / "twin.pt", weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in tensors.values())


def test_a_missing_or_damaged_twin_is_named(trained, tmp_path):
    _, out, _ = trained
    with pytest.raises(TwinFormatError, match="twin.json"):
        Twin.load(tmp_path)
    copy = tmp_path / "damaged"
    shutil.copytree(out, copy)
    data = (copy / "twin.pt").read_bytes()
    (copy / "twin.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(TwinFormatError, match="twin.pt"):
        Twin.load(copy)
    (copy / "twin.pt").unlink()
    with pytest.raises(TwinFormatError, match="missing"):
        Twin.load(copy)


def test_the_support_map_travels_with_the_twin(trained):
    """Measured from the sample's depth at write time, loaded from twin.pt alone: the sample's
    table is flat, so a box-sized footprint on it has no step."""
    rec, out, _ = trained
    support = Twin.load(out).support
    assert support is not None and np.isfinite(support.heights).sum() > 500
    from scipy.ndimage import uniform_filter

    seen = uniform_filter(np.isfinite(support.heights).astype(float), size=9)  # fraction seen around each cell
    iy, ix = np.unravel_index(np.argmax(seen), seen.shape)
    centre = np.array(support.origin) + support.cell * np.array([ix, iy])
    a = np.linspace(-0.02, 0.02, 9)
    footprint = np.stack(np.meshgrid(a, a), -1).reshape(-1, 2) + centre
    assert abs(np.nanmedian(support.height_at(footprint))) < 0.003  # the table is the base's z = 0 plane
    assert support.edge_drop(footprint) < 0.0025


def test_the_source_s_commands_travel_with_the_twin_as_its_joints_led_and_pressed(trained):
    """frames.csv's commands, as recorded against its joints (not the twin's retimed joints),
    given back by the lead and press the twin loads; its gripper commands as they are."""
    _, out, episode = trained
    frames = episode.frames
    commands = Twin.load(out).commands
    np.testing.assert_allclose(led(frames.q, commands.lead) + commands.press, frames.actions[:, :6], atol=1e-12)
    np.testing.assert_array_equal(commands.gripper, frames.actions[:, 6:7])


def test_a_twin_written_in_version_1_still_loads_and_renders_the_same(trained, tmp_path):
    """Twins written before several arms and cameras (version 1: ``robot`` and ``camera``
    sections, one arm, a fixed camera ``T_base_cam``) load as the same twin."""
    _, out, _ = trained
    old = tmp_path / "old"
    shutil.copytree(out, old)
    meta = json.loads((old / "twin.json").read_text())
    arm, camera = meta.pop("arms")[0], meta.pop("cameras")[0]
    meta.update(version=1, robot={"description": arm["description"], "link_order": meta.pop("link_order"),
                                  "model": arm["model"], "joint_names": arm["joint_names"]},
                camera={"name": camera["name"], "width": camera["width"], "height": camera["height"],
                        "K": camera["K"], "T_base_cam": camera["T_mount_cam"]})
    del meta["frame"]
    (old / "twin.json").write_text(json.dumps(meta))
    before, after = Twin.load(out), Twin.load(old)
    assert after.frame == "base" and after.arm_names == ("arm",) and after.camera_name == before.camera_name
    np.testing.assert_array_equal(after.T_base_cam, before.T_base_cam)
    np.testing.assert_array_equal(after.render_frame(9).rgb, before.render_frame(9).rgb)
    meta["version"] = 3
    (old / "twin.json").write_text(json.dumps(meta))
    with pytest.raises(TwinFormatError, match="version 3"):
        Twin.load(old)


def test_a_twin_written_before_shadow_receivers_keeps_its_shadows_on_the_background(trained, tmp_path):
    """Its moving parts were trained without receiving shadows: they must render as they were
    trained (shadows on the background only), not darkened by a strength they never had."""
    old = _without_light_fields(trained[1], tmp_path / "old", ["receivers"], ["moving_strength_logit"])
    shadows = Twin.load(old).graph.shadows
    assert shadows.receivers == "background" and shadows.moving_strength is None


def test_the_twin_draws_its_gaussians_in_the_mode_they_were_fitted_in(trained, tmp_path):
    """Trained antialiased, loaded antialiased with the mode's 0.1 px^2 dilation (drawn classic,
    the same Gaussians render otherwise); twins from before the option are classic, twins from
    before the modes' own dilations keep 0.3; an unknown mode or dilation is named."""
    twin = Twin.load(trained[1])
    assert twin.graph.rasterize_mode == "antialiased" and twin.graph.eps2d == 0.1
    antialiased = twin.render_frame(5).rgb
    twin.graph.rasterize_mode = "classic"
    assert np.abs(twin.render_frame(5).rgb.astype(int) - antialiased).max() > 8
    old = tmp_path / "old"
    shutil.copytree(trained[1], old)
    meta = json.loads((old / "twin.json").read_text())
    del meta["eps2d"]
    (old / "twin.json").write_text(json.dumps(meta))
    older = Twin.load(old)
    assert (older.graph.rasterize_mode, older.graph.eps2d) == ("antialiased", 0.3)
    assert np.abs(older.render_frame(5).rgb.astype(int) - antialiased).max() > 2, "drawn with the twin's own dilation"
    del meta["rasterize_mode"]
    (old / "twin.json").write_text(json.dumps(meta))
    assert (Twin.load(old).graph.rasterize_mode, Twin.load(old).graph.eps2d) == ("classic", 0.3)
    meta["eps2d"] = -1
    (old / "twin.json").write_text(json.dumps(meta))
    with pytest.raises(TwinFormatError, match="eps2d -1 is not a finite dilation"):
        Twin.load(old)
    del meta["eps2d"]
    meta["rasterize_mode"] = "mip"
    (old / "twin.json").write_text(json.dumps(meta))
    with pytest.raises(TwinFormatError, match="rasterize_mode 'mip' is not one of"):
        Twin.load(old)


def test_a_twin_written_before_mesh_casters_casts_from_the_links_gaussians(trained, tmp_path):
    old = _without_light_fields(trained[1], tmp_path / "old", ["casters"], ["caster_points", "caster_links"])
    twin = Twin.load(old)
    assert not twin.graph.shadows.has_casters
    assert twin.render_frame(3).rgb.shape == (60, 80, 3)


def _without_light_fields(twin: Path, old: Path, meta_keys: list[str], tensor_keys: list[str]) -> Path:
    """A copy of the twin folder ``twin`` in ``old`` as a version without those fields of the light wrote it."""
    shutil.copytree(twin, old)
    meta = json.loads((old / "twin.json").read_text())
    for key in meta_keys:
        del meta["shadows"][key]
    (old / "twin.json").write_text(json.dumps(meta))
    tensors = torch.load(old / "twin.pt", weights_only=True)
    for key in tensor_keys:
        del tensors[f"shadows/{key}"]
    torch.save(tensors, old / "twin.pt")
    return old
