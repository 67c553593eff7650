"""The whole-reconstruction benchmarks refuse a loss weight the command would refuse, before they
import, generate or train anything."""

from __future__ import annotations

import pytest

from benchmarks import bench_augment_cobot, bench_reconstruct_cobot, bench_reconstruct_viewpoints

#: (benchmark, its loss-weight flag) for every such flag a benchmark passes on to manisplat-reconstruct
WEIGHT_FLAGS = [(bench_reconstruct_cobot, "--lambda-pose"), (bench_reconstruct_viewpoints, "--lambda-pose"),
                (bench_reconstruct_cobot, "--lambda-mask"), (bench_augment_cobot, "--lambda-mask"),
                (bench_reconstruct_cobot, "--lambda-smooth")]


@pytest.mark.parametrize(("bench", "flag"), WEIGHT_FLAGS, ids=lambda x: x if isinstance(x, str) else x.__name__)
@pytest.mark.parametrize("weight", ["-0.01", "nan", "inf", "x"])
def test_a_negative_or_unreadable_loss_weight_is_refused_at_the_command_line(bench, flag, weight, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench.main([flag, weight, "--out", str(tmp_path / "result.json")])
    assert exit_.value.code == 2
    assert flag in capsys.readouterr().err
    assert not (tmp_path / "result.json").exists()
