"""manisplat-reconstruct end to end on tiny samples the test writes itself."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from manisplat.episode import load_meta, save_meta
from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.cli import main
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.outputs import write_evaluation
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainConfig
from manisplat.splat import load_ply
from manisplat.twin import Twin


@pytest.fixture(scope="module")
def pick(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("pick") / "ep", frames=24, width=80, height=60)


@pytest.fixture(scope="module")
def reach(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("reach") / "ep", frames=16, width=80, height=60, task="reach")


def test_cli_writes_every_output(pick, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(pick), "--out", str(out), "--iters", "40", "-q"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["psnr"]) == {"full", "robot", "object"} and set(metrics["ssim"]) == set(metrics["psnr"])
    assert metrics["iters"] == 40 and metrics["wall_s"] > 0 and metrics["plan"]["frames"] == 24
    assert set(metrics["pose"]["box"]) == {"et_cm", "er_deg"} and "box" in metrics["pose_baseline"]
    assert metrics["psnr"]["full"] > 15.0
    assert (metrics["lambda_pose"], metrics["lambda_smooth"]) == (0.01, 0.0), "a fixed camera: no smoothness"
    # the box's pose after it first moves and where it is left, with the offset fixed before it
    # moves (measured 0.21 cm / 0.08 deg, left 0.18 cm; a box left 2.3 cm off failed this)
    anchored = metrics["pose_anchored"]["box"]
    assert anchored["et_cm"] < 0.5 and anchored["er_deg"] < 1.0 and anchored["final"]["et_cm"] < 0.5
    assert set(metrics["pose_pseudo"]["box"]) == {"fitted", "anchored"}
    renders = sorted(p.name for p in (out / "renders" / "test").iterdir())
    assert renders == ["000004.png", "000012.png", "000020.png"]  # every 8th frame from the 4th, by frame index
    assert len(list((out / "renders" / "sheets").iterdir())) == 3 and (out / "pose_plot.png").stat().st_size > 0
    rows = list(csv.DictReader(open(out / "object_poses.csv")))
    assert len(rows) == 24 and {"frame", "t", "source", "T00", "T33"} <= set(rows[0])
    phases = [r["phase"] for r in csv.DictReader(open(out / "phases.csv"))]
    order = list(dict.fromkeys(phases))  # in order of appearance
    assert order[:4] == ["M_approach", "S_pick", "M_transfer", "S_place"]
    assert len(load_ply(out / "object_box.ply")["means"]) > 0 and (out / "background.ply").exists()
    assert "done in" in capsys.readouterr().out


def test_plan_prints_and_exits(pick, capsys, tmp_path):
    assert main([str(pick), "--out", str(tmp_path / "x"), "--plan"]) == 0
    text = capsys.readouterr().out
    assert "held out" in text and "box: tracked" in text and not (tmp_path / "x").exists()
    # the training the device's defaults choose (no GPU here: the CPU's budget, eager)
    assert "training      on cpu" in text and "3000 iterations (the CPU default" in text and "eager" in text
    assert "densification every 100 iterations from 300 to 2100" in text


def test_plan_prints_the_training_asked_for(pick, capsys, tmp_path):
    assert main([str(pick), "--out", str(tmp_path / "x"), "--plan", "--iters", "500", "--no-densify",
                 "--compile", "on"]) == 0
    text = capsys.readouterr().out
    assert "500 iterations (--iters)" in text and "compiled by torch.compile" in text and "densification off" in text


def test_resume_continues_from_the_checkpoint(pick, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(pick), "--out", str(out), "--iters", "20", "-q"]) == 0
    # mark the checkpoint: a background colour no training would reach; resuming at its own
    # step trains nothing more, so the twin must carry the mark (it does not if the checkpoint is ignored)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    state["background"] = torch.full_like(state["background"], 4.0)
    torch.save(state, out / "checkpoint.pt")
    assert main([str(pick), "--out", str(out), "--iters", "20", "--resume", "-q"]) == 0
    twin = Twin.load(out)
    assert torch.allclose(twin.background_rgb, torch.sigmoid(torch.tensor(4.0)))
    assert main([str(pick), "--out", str(out), "--iters", "30", "--resume", "-q"]) == 0
    assert json.loads((out / "metrics.json").read_text())["iters"] == 30
    (out / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert main([str(pick), "--out", str(out), "--iters", "40", "--resume", "-q"]) == 2
    assert "checkpoint.pt" in capsys.readouterr().err


def test_an_object_that_never_moves_gets_one_pose_and_no_tracking(reach):
    data = load_episode_data(reach)
    plan = make_plan(data)
    (obj,) = plan.objects
    assert not obj.moves
    rec, alignments = build(data, plan, TrainConfig(iters=1))
    assert rec.trajectories["box"].n_params == 1 and alignments["box"].baseline is None


def test_a_moving_frames_loss_holds_its_correction_to_its_trained_neighbours(pick):
    """The training loss of a carried frame grows by lambda_smooth times the squared distance (in
    sigma units) of its correction from its trained neighbours' mean; a frame at rest adds none."""
    data = load_episode_data(pick)
    rec, _ = build(data, make_plan(data), TrainConfig(iters=1, lambda_pose=0.0))
    traj, neighbours = rec.trajectories["box"], rec._neighbours["box"]
    frame = next(f for f in sorted(neighbours) if len(neighbours[f]) == 2)
    at_rest = next(f for f in rec.plan.train_frames if f not in neighbours)
    with torch.no_grad():
        traj.twist(frame)[0] = 0.002  # 2 mm off its neighbours (which stay at 0): 0.04 in sigma units

    def loss(f: int, weight: float) -> float:
        rec.config.lambda_smooth = weight
        with torch.no_grad():
            return rec.losses(f)[0].item()

    assert loss(frame, 1.0) - loss(frame, 0.0) == pytest.approx(0.04, rel=1e-4)
    assert loss(at_rest, 1.0) == loss(at_rest, 0.0)


def test_shadows_are_searched_and_learned(pick, tmp_path):
    data = load_episode_data(pick)
    rec, alignments = build(data, make_plan(data), TrainConfig(iters=12, shadow_start=6, eval_every=100))
    found = {}

    def snapshot(r):  # the light as the search left it, before any training step moved it
        if r.graph.shadows is not None and not found:
            found.update({k: v.detach().clone() for k, v in r.graph.shadows.named_parameters()})

    rec.train(progress=False, callback=snapshot)
    assert rec.graph.shadows is not None and found
    assert abs(float(rec.graph.shadows.direction.detach().norm()) - 1.0) < 0.1
    learned = dict(rec.graph.shadows.named_parameters())
    assert any(not torch.equal(found[k], learned[k].detach()) for k in found), "the light was never trained"
    metrics = write_evaluation(rec, alignments, tmp_path, wall_s=1.0)
    light = metrics["light"]
    assert abs(sum(x * x for x in light["direction"]) - 1.0) < 1e-4 and 0 < light["elevation_deg"] <= 90
    # the shadow map matched to the camera: this 80x60 camera resolves fewer texels than the smallest map
    assert light["shadow_map_px"] == rec.graph.shadows.resolution == 64
    # the shadowed pixels are scored with and without the shadows: two renders that differ there
    shadow = metrics["shadow"]
    assert shadow["pixels"] > 0 and shadow["psnr"] != shadow["psnr_without_shadows"]


def test_uncalibrated_camera_is_a_clear_error(pick, tmp_path, capsys):
    import shutil

    copy = tmp_path / "uncalibrated"
    shutil.copytree(pick, copy)
    meta = load_meta(copy / "episode.json")
    meta.camera.T_mount_cam = None
    save_meta(copy / "episode.json", meta)
    assert main([str(copy), "--out", str(tmp_path / "o"), "--iters", "5"]) == 2
    assert "T_mount_cam" in capsys.readouterr().err


def test_densification_follows_the_optimizer_step(pick):
    """gsplat's order: backward, one optimizer step over everything, then each node's
    densification, so a node that grows or is pruned still takes that iteration's update."""
    data = load_episode_data(pick)
    config = TrainConfig(iters=3, shadows=False, eval_every=100, refine_stop_fraction=1.0)  # densifying throughout
    rec, _ = build(data, make_plan(data), config)
    events = []
    step = rec.optimizer.step
    rec.optimizer.step = lambda *a, **k: (events.append("step"), step(*a, **k))[1]
    for name, strategy in rec.strategies.items():
        post = strategy.step_post_backward
        strategy.step_post_backward = (lambda post: lambda *a, **k: (events.append("densify"), post(*a, **k))[1])(post)
    rec.train(progress=False)
    nodes = len(rec.strategies)
    assert events == (["step"] + ["densify"] * nodes) * 3
