"""manisplat-reconstruct's output folder: earlier results are never overwritten silently, a bad
ground truth is refused before training, an evaluation failure keeps the trained twin, and the
summary, sheets, plot and progress bar say what they show."""

from __future__ import annotations

import json
import logging
import math
import shutil

import numpy as np
import pytest

from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct import outputs
from manisplat.reconstruct.cli import main
from manisplat.reconstruct.outputs import SHEET_COLUMNS, pose_figure
from manisplat.render.sheets import labelled_sheet
from manisplat.reconstruct.trainer import _progress_fields


@pytest.fixture(scope="module")
def pick(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("pick") / "ep", frames=16, width=64, height=48)


@pytest.fixture(scope="module")
def finished(pick, tmp_path_factory):
    """One short run's output folder and its printed summary (shared, read only)."""
    out = tmp_path_factory.mktemp("finished") / "twin"
    import contextlib
    import io

    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert main([str(pick), "--out", str(out), "--iters", "6", "-q"]) == 0
    return out, text.getvalue()


def test_a_folder_with_results_is_refused_without_overwrite(pick, finished, tmp_path, capsys):
    out, _ = finished
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    with pytest.raises(SystemExit) as exc:
        main([str(pick), "--out", str(out), "--iters", "6", "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "not empty" in err and "--overwrite" in err and "--resume" in err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before


def test_metrics_list_each_held_out_frames_psnr_and_their_mean_is_the_summary(finished):
    metrics = json.loads((finished[0] / "metrics.json").read_text())
    per_frame = metrics["psnr_per_frame"]
    assert per_frame["frames"] == metrics["plan"]["test_frames"] and per_frame["frames"]
    for region, mean in metrics["psnr"].items():
        scores = [x for x in per_frame[region] if x is not None]
        assert len(per_frame[region]) == len(per_frame["frames"]) and scores
        assert np.mean(scores) == pytest.approx(mean, abs=0.01), region


def test_overwrite_replaces_what_the_run_owns_and_keeps_the_rest(pick, tmp_path):
    out = tmp_path / "twin"
    stale = out / "renders" / "test" / "999999.png"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"an earlier run's render")
    (out / "metrics.json").write_text('{"psnr": "stale"}')
    (out / "notes.txt").write_text("mine")
    assert main([str(pick), "--out", str(out), "--iters", "6", "-q", "--overwrite"]) == 0
    assert not stale.exists(), "a stale render of an earlier run was left among the new ones"
    assert json.loads((out / "metrics.json").read_text())["iters"] == 6
    assert (out / "notes.txt").read_text() == "mine"


def test_resume_needs_a_checkpoint_in_a_used_folder(pick, tmp_path, capsys):
    out = tmp_path / "twin"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    with pytest.raises(SystemExit) as exc:
        main([str(pick), "--out", str(out), "--resume", "-q"])
    assert exc.value.code == 2 and "checkpoint.pt" in capsys.readouterr().err


def test_ground_truth_of_another_length_is_refused_before_training(pick, tmp_path, capsys):
    import shutil

    copy = tmp_path / "recovered"
    shutil.copytree(pick, copy)
    with np.load(copy / "gt.npz") as gt:
        arrays = {k: gt[k] for k in gt.files}
    arrays["T_base_box"] = np.concatenate([arrays["T_base_box"], arrays["T_base_box"][-1:]])
    np.savez(copy / "gt.npz", **arrays)
    out = tmp_path / "twin"
    assert main([str(copy), "--out", str(out), "--iters", "6", "-q"]) == 2
    err = capsys.readouterr().err
    assert "gt.npz" in err and "T_base_box" in err and "17" in err and "16" in err
    assert not out.exists(), "nothing should be trained or written for an episode refused at loading"


def test_a_failed_evaluation_keeps_the_trained_twin(pick, tmp_path, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise OSError("simulated failure while rendering the held-out frames")

    monkeypatch.setattr(outputs, "write_evaluation", broken)
    out = tmp_path / "twin"
    assert main([str(pick), "--out", str(out), "--iters", "6", "-q"]) == 1
    err = capsys.readouterr().err
    assert "twin is trained" in err and "simulated failure" in err
    for name in ("checkpoint.pt", "background.ply", "object_box.ply", "object_poses.csv", "phases.csv"):
        assert (out / name).is_file(), name


def test_summary_has_units_and_names_the_files_to_look_at(finished):
    out, text = finished
    assert "held-out PSNR: full" in text and " dB" in text and "held-out SSIM" in text
    assert "pose error box:" in text and " cm, " in text and " deg" in text
    assert str(out / "pose_plot.png") in text and f"{out / 'renders' / 'sheets'}/" in text
    assert "nan" not in text


def test_one_camera_is_drawn_classic_by_default(finished):
    """--rasterize-mode auto: classic with one camera (several: antialiased, test_two_arms)."""
    out, _ = finished
    assert json.loads((out / "metrics.json").read_text())["rasterize_mode"] == "classic"
    assert json.loads((out / "metrics.json").read_text())["eps2d"] == 0.3
    assert json.loads((out / "twin.json").read_text())["rasterize_mode"] == "classic"


def test_one_camera_learns_two_bands_of_view_dependent_colour_by_default(finished):
    """--sh-degree auto: 2 with one camera (several: 3, test_two_arms)."""
    out, _ = finished
    assert json.loads((out / "metrics.json").read_text())["sh_degree"] == 2


def test_fixed_cameras_alone_leave_the_parts_response_to_the_light_off_by_default(finished):
    """--light-response auto: off with fixed cameras only (on with a riding one: test_two_arms)."""
    out, _ = finished
    assert json.loads((out / "metrics.json").read_text())["light_response"] is False
    assert not [n["name"] for n in json.loads((out / "twin.json").read_text())["nodes"] if "light_gain" in n["params"]]


def test_the_episode_masks_keep_the_mask_loss(finished):
    """--lambda-mask unset: 1 with the episode's masks (0 with drawn ones: test_without_masks_or_depth)."""
    out, _ = finished
    assert json.loads((out / "metrics.json").read_text())["lambda_mask"] == 1.0


def test_the_mask_loss_weight_resolves_by_the_masks_source():
    from manisplat.reconstruct.config import resolve_lambda_mask

    assert resolve_lambda_mask(None, masks_drawn=False) == 1.0
    assert resolve_lambda_mask(None, masks_drawn=True) == 0.0
    assert resolve_lambda_mask(0.25, masks_drawn=True) == 0.25 and resolve_lambda_mask(0.0, masks_drawn=False) == 0.0


def test_the_rasterize_mode_resolves_by_the_number_of_cameras():
    from manisplat.reconstruct.config import RASTERIZE_MODES, resolve_rasterize_mode
    from manisplat.splat import RASTERIZE_MODES as RASTERIZER_MODES

    assert RASTERIZE_MODES == RASTERIZER_MODES  # the command line's torch-free copy

    assert [resolve_rasterize_mode("auto", n) for n in (1, 2, 3)] == ["classic", "antialiased", "antialiased"]
    assert [resolve_rasterize_mode(m, 1) for m in ("classic", "antialiased")] == ["classic", "antialiased"]
    assert resolve_rasterize_mode("classic", 3) == "classic"
    with pytest.raises(ValueError, match="unknown rasterize mode 'mip'"):
        resolve_rasterize_mode("mip", 1)


def test_the_sh_degree_resolves_by_the_number_of_cameras():
    from manisplat.reconstruct.config import resolve_sh_degree

    assert [resolve_sh_degree("auto", n) for n in (1, 2, 3)] == [2, 3, 3]
    assert [resolve_sh_degree(d, 3) for d in ("0", "1", "2", "3")] == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="unknown SH degree '4'; choose one of auto, 0, 1, 2, 3"):
        resolve_sh_degree("4", 1)


def test_a_fixed_cameras_weight_on_the_objects_resolves_by_the_cameras_trained(tmp_path, capsys):
    from manisplat.reconstruct.cli import main
    from manisplat.reconstruct.config import resolve_fixed_camera_weight

    assert [resolve_fixed_camera_weight(None, riding) for riding in (False, True)] == [1.0, 30.0]
    assert [resolve_fixed_camera_weight(2.5, riding) for riding in (False, True)] == [2.5, 2.5]
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path), "--out", str(tmp_path / "twin"), "--fixed-camera-weight", "0"])
    assert exit_.value.code == 2 and "argument --fixed-camera-weight:" in capsys.readouterr().err


def test_the_head_cameras_share_of_the_iterations_is_half_from_the_cuda_budget_on_with_a_riding_camera(caplog):
    from manisplat.reconstruct.cli import _config, build_parser
    from manisplat.reconstruct.config import resolve_fixed_camera_share

    assert [resolve_fixed_camera_share("auto", True, iters) for iters in (3000, 9999, 10_000, 30_000)] == \
        [None, None, 0.5, 0.5]
    assert resolve_fixed_camera_share("auto", False, 10_000) is None  # fixed cameras only: nothing to share
    assert [resolve_fixed_camera_share("alike", True, iters) for iters in (3000, 10_000)] == [None, None]
    assert [resolve_fixed_camera_share(0.7, True, iters) for iters in (3000, 10_000)] == [0.7, 0.7]
    with pytest.raises(ValueError, match="no camera riding on an arm is trained"):
        resolve_fixed_camera_share(0.7, False, 3000)
    with pytest.raises(ValueError, match="between 0 and 1"):
        resolve_fixed_camera_share(1.0, True, 3000)

    def share(flags, iters):  # the configuration the command trains a wrist camera's run with
        args = build_parser().parse_args(["ep", "--out", "twin", *flags])
        return _config(args, "cpu", iters, None, cameras=3, masks_drawn=True, riding=True).fixed_camera_share

    with caplog.at_level(logging.INFO, logger="manisplat.reconstruct"):
        assert [share([], 3000), share([], 10_000)] == [None, 0.5]
    assert "a fixed camera's frames drawn in 0.5 of the iterations (--fixed-camera-share auto, 10000 iterations)" \
        in caplog.text
    assert [share(["--fixed-camera-share", "alike"], 10_000), share(["--fixed-camera-share", "0.25"], 3000)] == \
        [None, 0.25]


def test_sheets_are_labelled_with_columns_and_frame(finished):
    import cv2

    out, _ = finished
    sheet = cv2.imread(str(out / "renders" / "sheets" / "000012.png"))
    height, width = sheet.shape[:2]
    assert width == 3 * 64 and height > 48, "no header strip above the panels"
    header = sheet[: height - 48]
    for k in range(len(SHEET_COLUMNS)):
        assert (header[:, k * 64:(k + 1) * 64] < 128).any(), f"column {k} has no label"
    blank = labelled_sheet(np.zeros((48, 192, 3), np.uint8), SHEET_COLUMNS, "frame 8")
    plain = labelled_sheet(np.zeros((48, 192, 3), np.uint8), SHEET_COLUMNS, "frame 16")
    assert not np.array_equal(blank, plain), "the frame number is not drawn"


def test_pose_plot_legend_names_every_axis_and_source_with_ground_truth_visible():
    t = np.linspace(0, 1, 10)
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = t * 0.1
    fig = pose_figure(t, {"box": (poses, poses.copy(), poses.copy())})
    labels = [text.get_text() for text in fig.axes[0].get_legend().get_texts()]
    assert {"x", "y", "z", "ours", "per-frame baseline", "ground truth"} <= set(labels)
    lines = {line.get_label(): line for line in fig.axes[0].get_legend().get_lines()}
    assert lines["ground truth"].get_linewidth() > 2 * lines["ours"].get_linewidth(), \
        "ground truth must stay visible under an estimate that agrees with it"


def test_progress_bar_shows_no_psnr_before_it_is_measured():
    assert "held-out PSNR" not in _progress_fields(0.1, math.nan, 100)
    fields = _progress_fields(0.1, 31.234, 100)
    assert fields["held-out PSNR"] == "31.23 dB"


def test_the_help_names_every_output_and_overwrite_removes_them(finished, tmp_path):
    import fnmatch
    import re

    from manisplat.reconstruct.cli import EPILOG

    out, _ = finished
    outputs_text = EPILOG[EPILOG.index("outputs:"):EPILOG.index("Exit status")]
    named = [re.sub(r"<\w+>", "*", t) for t in re.findall(r"[\w<>.]+\.(?:json|pt|ply|csv|png)|\w+/", outputs_text)]
    written = [p.name + ("/" if p.is_dir() else "") for p in out.iterdir()]
    assert not [w for w in written if not any(fnmatch.fnmatch(w, n) for n in named)], named
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "notes.txt").write_text("mine")
    outputs.remove_outputs(copy)
    assert [p.name for p in copy.iterdir()] == ["notes.txt"]


def test_bad_input_is_refused_before_training_is_announced(tmp_path, capsys, caplog):
    import logging

    caplog.set_level(logging.INFO, logger="manisplat.reconstruct")
    (tmp_path / "not_an_episode").mkdir()
    assert main([str(tmp_path / "not_an_episode"), "--out", str(tmp_path / "twin"), "--iters", "6"]) == 2
    assert "episode.json" in capsys.readouterr().err
    assert not [r for r in caplog.records if "training on" in r.getMessage()]


def _camera_check(applied: bool) -> dict:
    return {"applied": applied, "rotation_deg": 4.019, "sigma_rotation_deg": 0.292, "translation_mm": 79.94,
            "sigma_translation_mm": 4.16, "time_offset_ms": None,
            "reason": "" if applied else "the robot's depth does not fit its model (residual RMS 9.07 -> 8.84 mm)"}


def test_the_summary_gives_the_calibration_advice_only_when_the_camera_was_corrected(tmp_path):
    from manisplat.reconstruct.cli import _summary

    base = {"wall_s": 1.0, "iters": 6}
    kept = _summary({**base, "camera": _camera_check(False)}, tmp_path)
    assert "manisplat-calibrate apply" not in kept, "advice that would write the unchanged camera"
    assert "kept as recorded: the robot's depth does not fit" in kept and "4.019" not in kept
    corrected = _summary({**base, "camera": _camera_check(True)}, tmp_path)
    assert "corrected by 4.019 +- 0.292 deg" in corrected
    assert f"manisplat-calibrate apply {tmp_path / 'camera_refined.json'} EPISODE" in corrected


def test_the_built_in_samples_depth_fits_the_robot_model(tmp_path):
    """The sample a newcomer reconstructs first must pass the camera check, not end with a depth that
    "does not fit its model" (one depth per triangle left 9 mm RMS and a proposed 4 deg / 80 mm)."""
    from manisplat.reconstruct.data import load_episode_data
    from manisplat.reconstruct.extrinsic import MAX_RESIDUAL_MM, refine_extrinsic

    episode = write_sample_episode(tmp_path / "sample", frames=24)
    check = refine_extrinsic(load_episode_data(episode, progress=False), list(range(0, 24, 2)))
    assert check is not None and "does not fit" not in check.reason, check and check.reason
    assert check.rms_before_mm < MAX_RESIDUAL_MM / 5
