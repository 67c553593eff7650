import numpy as np
import pytest

from manisplat.calib.cli import main
from manisplat.calib.errors import NotEnoughDataError
from manisplat.calib.latency import RobotMotion, fit_latency
from manisplat.calib.synth import default_truth, write_latency_episode
from manisplat.calib.latency import estimate_latency


@pytest.mark.parametrize("latency, calibrated, seed", [(0.047, False, 3), (-0.012, True, 6)])
def test_latency_recovered_within_2ms(tmp_path, spec, latency, calibrated, seed):
    """15 s of bursty motion at 30 fps, rendered at the true exposure times, stamped late."""
    truth = default_truth(spec, width=320, height=240, f=260.0, latency_s=latency)
    write_latency_episode(tmp_path / "ep", spec, truth, rng=np.random.default_rng(seed), duration_s=15.0,
                          calibrated=calibrated)
    est = estimate_latency(tmp_path / "ep", bootstrap=40)
    assert est.signal == ("pixels" if calibrated else "metres")
    assert abs(est.latency_s - latency) < 0.002
    assert 0 < est.std_s < 0.004 and est.correlation > 0.9


def test_no_motion_is_refused():
    robot = RobotMotion(np.linspace(0, 5, 1001), np.zeros((1001, 3, 3)))
    with pytest.raises(NotEnoughDataError, match="no motion"):
        fit_latency(np.arange(0.5, 4.5, 0.1), np.zeros(39), robot)
    with pytest.raises(NotEnoughDataError, match="does not move"):
        fit_latency(np.arange(0.5, 4.5, 0.1), np.random.default_rng(0).random(39), robot)
    with pytest.raises(NotEnoughDataError, match="at least 9"):
        fit_latency(np.arange(5) * 0.1, np.ones(4), robot)


def test_latency_command(tmp_path, spec, capsys):
    truth = default_truth(spec, width=320, height=240, f=260.0, latency_s=0.04)
    write_latency_episode(tmp_path / "ep", spec, truth, rng=np.random.default_rng(2), duration_s=5.0)
    assert main(["latency", str(tmp_path / "ep"), "--json", str(tmp_path / "l.json")]) == 0
    assert "latency " in capsys.readouterr().out
    import json
    est = json.loads((tmp_path / "l.json").read_text())
    assert abs(est["latency_s"] - 0.04) < max(0.01, 3 * est["latency_std_s"])
