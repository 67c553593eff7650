"""The whole-reconstruction benchmarks refuse a training setting the command would refuse, before
they import, generate or train anything, and a twin reused from ``--work`` is refused when it was
made with other settings than asked."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_augment_cobot, bench_reconstruct_cobot, bench_reconstruct_fusion, bench_reconstruct_viewpoints
from benchmarks._harness import MissingBenchmarkData

#: (benchmark, its loss-weight flag) for every such flag a benchmark passes on to manisplat-reconstruct
WEIGHT_FLAGS = [(bench_reconstruct_cobot, "--lambda-pose"), (bench_reconstruct_viewpoints, "--lambda-pose"),
                (bench_reconstruct_cobot, "--lambda-mask"), (bench_augment_cobot, "--lambda-mask"),
                (bench_reconstruct_cobot, "--lambda-smooth"), (bench_augment_cobot, "--lambda-pose"),
                (bench_augment_cobot, "--lambda-smooth")]
#: (benchmark, flag) for the pose rate's final fraction, a number in (0, 1]
RATE_FLAGS = [(bench_reconstruct_cobot, "--pose-rate-final"), (bench_augment_cobot, "--pose-rate-final")]
#: (benchmark, flag, value) refused: a loss weight below 0 or unreadable, a pose rate fraction outside (0, 1]
REFUSED = ([(bench, flag, value) for bench, flag in WEIGHT_FLAGS for value in ("-0.01", "nan", "inf", "x")]
           + [(bench, flag, value) for bench, flag in RATE_FLAGS for value in ("0", "1.5", "nan", "x")]
           + [(bench, "--threads", value) for bench in (bench_reconstruct_viewpoints, bench_reconstruct_cobot)
              for value in ("0", "1.5")]
           + [(bench, "--light-response", "sometimes")
              for bench in (bench_reconstruct_cobot, bench_augment_cobot, bench_reconstruct_fusion)]
           + [(bench, "--fixed-camera-share", value) for bench in (bench_reconstruct_cobot, bench_augment_cobot)
              for value in ("0", "1", "nan", "x")])


@pytest.mark.parametrize(("bench", "flag", "value"), REFUSED,
                         ids=lambda x: x if isinstance(x, str) else x.__name__)
def test_an_out_of_range_or_unreadable_training_setting_is_refused_at_the_command_line(bench, flag, value, tmp_path,
                                                                                       capsys):
    with pytest.raises(SystemExit) as exit_:
        bench.main([flag, value, "--out", str(tmp_path / "result.json")])
    assert exit_.value.code == 2
    assert f"argument {flag}:" in capsys.readouterr().err  # the flag's own error, not the usage that names it
    assert not (tmp_path / "result.json").exists()


DEFAULTS = {"lambda_mask": None, "lambda_pose": None, "lambda_smooth": None, "pose_rate_final": None,
            "light_response": None, "fixed_camera_share": None}


def _twin(tmp_path, **recorded):
    (tmp_path / "metrics.json").write_text(json.dumps(recorded))
    return tmp_path


def test_a_reused_twin_made_with_the_asked_settings_is_taken_with_them(tmp_path):
    twin = _twin(tmp_path, lambda_mask=0.0, lambda_pose=0.01, lambda_smooth=1.0, pose_rate_final=0.1,
                 light_response=True)
    assert bench_augment_cobot.training_settings(twin, DEFAULTS, 3000) == {"lambda_mask": 0.0, "lambda_pose": 0.01,
                                                                      "lambda_smooth": 1.0, "pose_rate_final": 0.1,
                                                                      "light_response": True,
                                                                      "fixed_camera_share": None}
    asked = {"lambda_mask": None, "lambda_pose": 1.0, "lambda_smooth": 0.0, "pose_rate_final": 1.0,
             "light_response": "off", "fixed_camera_share": 0.5}
    made = bench_augment_cobot.training_settings(_twin(tmp_path, lambda_mask=0.0, lambda_pose=1.0, lambda_smooth=0.0,
                                                       fixed_camera_share=0.5),
                                                 asked, 3000)  # before the schedule was recorded: constant
    assert (made["lambda_pose"], made["pose_rate_final"]) == (1.0, 1.0)


@pytest.mark.parametrize(("recorded", "named"), [
    ({"lambda_mask": 0.0, "lambda_pose": 1.0, "lambda_smooth": 1.0, "pose_rate_final": 0.1, "light_response": True},
     "--lambda-pose 1, not 0.01"),
    ({"lambda_mask": 0.0, "lambda_pose": 0.01, "lambda_smooth": 0.0, "pose_rate_final": 0.1, "light_response": True},
     "--lambda-smooth 0, not 1"),
    ({"lambda_mask": 0.0, "lambda_pose": 0.01, "lambda_smooth": 1.0, "pose_rate_final": 0.01, "light_response": True},
     "--pose-rate-final 0.01, not 0.1"),
    ({"lambda_mask": 0.0, "lambda_pose": 0.01, "lambda_smooth": 1.0, "light_response": True},
     "--pose-rate-final 1, not 0.1"),  # constant then
    ({"lambda_mask": 0.0, "lambda_pose": 0.01, "lambda_smooth": 1.0, "pose_rate_final": 0.1},
     "--light-response off, not on"),  # made before the light response
    ({"lambda_mask": 0.0, "lambda_pose": 0.01, "lambda_smooth": 1.0, "pose_rate_final": 0.1, "light_response": True,
      "fixed_camera_share": 0.5}, "--fixed-camera-share 0.5, not alike"),
    ({"lambda_mask": 0.0}, "--lambda-pose 1, not 0.01"),  # made before metrics.json recorded the weight
])
def test_a_reused_twin_made_with_other_settings_is_refused_by_name(tmp_path, recorded, named):
    with pytest.raises(RuntimeError, match=named):
        bench_augment_cobot.training_settings(_twin(tmp_path, **recorded), DEFAULTS, 3000)


def test_a_reused_twin_is_refused_unless_made_with_the_share_the_budget_gives(tmp_path):
    """The command's default share (auto) is the head camera's half from 10 000 iterations on:
    a twin made alike is the default's at 3000 iterations, not at 10 000."""
    made_alike = {"lambda_mask": 0.0, "lambda_pose": 0.01, "lambda_smooth": 1.0, "pose_rate_final": 0.1,
                  "light_response": True}
    assert bench_augment_cobot.training_settings(_twin(tmp_path, **made_alike), DEFAULTS, 3000)["fixed_camera_share"] \
        is None
    with pytest.raises(RuntimeError, match="--fixed-camera-share alike, not 0.5"):
        bench_augment_cobot.training_settings(_twin(tmp_path, **made_alike), DEFAULTS, 10_000)
    asked_alike = {**DEFAULTS, "fixed_camera_share": "alike"}
    assert bench_augment_cobot.training_settings(_twin(tmp_path, **made_alike), asked_alike, 10_000)[
        "fixed_camera_share"] is None


def test_the_cobot_benchmark_refuses_a_share_with_the_head_camera_alone(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench_reconstruct_cobot.main(["--settings", "all,head", "--fixed-camera-share", "0.5",
                                      "--out", str(tmp_path / "result.json")])
    assert exit_.value.code == 2 and "the head camera alone has no riding camera" in capsys.readouterr().err
    assert not (tmp_path / "result.json").exists()


#: the fusion benchmark's settings of every twin, as its command line gives them by default
FUSION_OPTIONS = {"shadow_receivers": "all", "shadow_casters": "gaussians", "rasterize_mode": "classic",
                  "object_position_rate": "1", "lambda_pose": "1", "pose_rate_final": "1", "light_response": "off"}


def _fusion_twin(tmp_path, **recorded):
    """A twin folder whose metrics.json records :data:`FUSION_OPTIONS`' other settings and ``recorded``."""
    return _twin(tmp_path, light={"receivers": "all", "casters": "gaussians"}, rasterize_mode="classic",
                 object_position_rate=1.0, lambda_pose=1.0, pose_rate_final=1.0, **recorded)


@pytest.mark.parametrize(("recorded", "asked"), [(True, "off"), (False, "on"), (None, "on")])
def test_the_fusion_benchmark_refuses_a_reused_twin_of_another_light_response(tmp_path, recorded, asked):
    twin = _fusion_twin(tmp_path, **({} if recorded is None else {"light_response": recorded}))  # None: made before it
    with pytest.raises(MissingBenchmarkData, match=f"'light_response': '{asked}'"):
        bench_reconstruct_fusion._twin([], twin, 10, {**FUSION_OPTIONS, "light_response": asked})


def test_the_fusion_benchmark_takes_a_reused_twin_of_the_asked_light_response(tmp_path):
    twin = _fusion_twin(tmp_path, light_response=True, psnr={"full": 30.0})
    (twin / "bench_run.json").write_text(json.dumps({"wall_s": 12.0, "peak_rss_kb": 2048}))
    taken = bench_reconstruct_fusion._twin([], twin, 10, {**FUSION_OPTIONS, "light_response": "on"})
    assert (taken["wall_s"], taken["peak_rss_mb"], taken["psnr"]) == (12.0, 2, {"full": 30.0})


def test_reconstruct_cobot_keeps_its_twins_only_in_an_empty_work_folder(tmp_path, capsys):
    work = tmp_path / "work"
    work.mkdir()
    (work / "earlier_twin").mkdir()
    with pytest.raises(SystemExit) as exit_:
        bench_reconstruct_cobot.main(["--work", str(work), "--out", str(tmp_path / "result.json")])
    assert exit_.value.code == 2
    assert f"--work: {work} is not empty" in capsys.readouterr().err
    assert [p.name for p in work.iterdir()] == ["earlier_twin"] and not (tmp_path / "result.json").exists()


def test_reconstruct_viewpoints_declares_the_copies_colour_on_a_copy(tmp_path):
    from manisplat.episode import Episode
    from manisplat.episode.images import StoredChroma
    from tests.episode.episode_factory import write_episode

    degraded = write_episode(tmp_path / "right_oak1", 2)
    before = (degraded / "episode.json").read_text()
    declared = bench_reconstruct_viewpoints.declared_copy(degraded, tmp_path / "declared")
    assert declared == tmp_path / "declared" / "right_oak1"
    assert Episode.open(declared).chroma_subsampling() == StoredChroma("4:2:0", False)
    assert (degraded / "episode.json").read_text() == before  # the cached copy is left as the degrade tool wrote it
