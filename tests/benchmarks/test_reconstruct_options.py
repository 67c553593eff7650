"""The whole-reconstruction benchmarks refuse a loss weight the command would refuse, before they
import, generate or train anything."""

from __future__ import annotations

import pytest

from benchmarks import bench_augment_cobot, bench_reconstruct_cobot, bench_reconstruct_viewpoints


@pytest.mark.parametrize("bench", [bench_reconstruct_cobot, bench_reconstruct_viewpoints])
@pytest.mark.parametrize("weight", ["-0.01", "nan", "x"])
def test_a_negative_or_unreadable_pose_prior_weight_is_refused_at_the_command_line(bench, weight, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--lambda-pose", weight, "--out", str(tmp_path / "result.json")])
    assert exit_.value.code == 2
    assert "--lambda-pose" in capsys.readouterr().err
    assert not (tmp_path / "result.json").exists()


@pytest.mark.parametrize("bench", [bench_reconstruct_cobot, bench_augment_cobot])
@pytest.mark.parametrize("weight", ["-1", "inf", "x"])
def test_a_negative_or_unreadable_mask_loss_weight_is_refused_at_the_command_line(bench, weight, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--lambda-mask", weight, "--out", str(tmp_path / "result.json")])
    assert exit_.value.code == 2
    assert "--lambda-mask" in capsys.readouterr().err
    assert not (tmp_path / "result.json").exists()
