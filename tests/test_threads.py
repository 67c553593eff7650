"""CPU threads: importing manisplat makes OpenMP's idle workers sleep (unless the user chose), a
job takes the cores other work leaves free, --threads overrides, and the log says which and why."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import pytest

from manisplat import threads


#: what each new process starts without unless a test sets it (xdist's workers set OMP_NUM_THREADS)
WAIT_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")


def _wait_after(script: str, **chosen: str) -> list[str]:
    """[OMP_WAIT_POLICY, GOMP_SPINCOUNT, torch imported] after ``script`` ran in a new process, the
    user having set ``chosen``."""
    env = {k: v for k, v in os.environ.items() if k not in WAIT_VARIABLES} | chosen
    report = "; import os, sys; print(*(os.environ.get(k) for k in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')), 'torch' in sys.modules)"
    return subprocess.run([sys.executable, "-c", script + report], env=env, capture_output=True, text=True,
                          check=True).stdout.split()


def test_importing_manisplat_makes_idle_openmp_workers_sleep_unless_the_user_chose():
    assert _wait_after("import manisplat") == ["PASSIVE", "None", "False"]
    assert _wait_after("import manisplat", OMP_WAIT_POLICY="active") == ["active", "None", "False"]


def test_a_new_process_sets_how_its_idle_workers_wait_before_torch_loads_openmp():
    """What a command line tool does: manisplat first, then torch, whose OpenMP reads the policy."""
    assert _wait_after("import manisplat.reconstruct.cli, torch") == ["PASSIVE", "None", "True"]


def test_a_command_on_an_idle_machine_lets_its_workers_spin_briefly_before_torch_loads():
    pin = "import manisplat.threads as t; t.free_cores = lambda: (2, 2, 0.0); "
    spins = str(threads.SPIN_COUNT)
    assert _wait_after(pin + "t.use_threads()") == ["PASSIVE", spins, "True"]
    assert _wait_after(pin + "t.use_threads(2)") == ["PASSIVE", spins, "True"]
    # other work beside it, more threads than free cores, one thread, the user's own choices,
    # torch already loaded: no spin of ours
    busy = "import manisplat.threads as t; t.free_cores = lambda: (2, 2, 0.8); "
    assert _wait_after(busy + "t.use_threads()") == ["PASSIVE", "None", "True"]
    assert _wait_after(pin + "t.use_threads(3)") == ["PASSIVE", "None", "True"]
    assert _wait_after(pin + "t.use_threads(1)") == ["PASSIVE", "None", "True"]
    assert _wait_after(pin + "t.use_threads()", OMP_WAIT_POLICY="PASSIVE") == ["PASSIVE", "None", "True"]
    assert _wait_after(pin + "t.use_threads()", GOMP_SPINCOUNT="500") == ["PASSIVE", "500", "True"]
    assert _wait_after(pin + "import torch; t.use_threads()") == ["PASSIVE", "None", "True"]


@pytest.mark.parametrize(("cores", "busy", "free"), [(2, 0.0, 2), (2, 0.6, 2), (2, 1.2, 1), (2, 5.0, 1),
                                                       (16, 3.7, 13), (16, 40.0, 1), (1, 0.0, 1)])
def test_a_job_takes_the_cores_other_work_leaves_free(monkeypatch, cores, busy, free):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
    monkeypatch.setattr(threads, "_busy_cores", lambda sample_s: busy)
    assert threads.free_cores() == (free, cores, busy)


def test_without_cpu_counters_the_load_average_stands_in(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    monkeypatch.setattr(threads, "_busy_cores", lambda sample_s: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (2.5, 1.0, 1.0))
    assert threads.free_cores() == (2, 4, 2.5)


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="reads Linux's /proc/stat")
def test_a_spinning_process_counts_as_a_busy_core():
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        assert threads._busy_cores(0.5) >= 0.8
    finally:
        hog.kill()
        hog.wait()


@pytest.fixture
def restore_threads():
    import cv2
    import torch

    before = torch.get_num_threads(), cv2.getNumThreads()
    yield
    torch.set_num_threads(before[0])
    cv2.setNumThreads(before[1])


def test_use_threads_sets_torch_and_opencv_and_says_why(monkeypatch, caplog, restore_threads):
    import cv2
    import torch

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    caplog.set_level(logging.INFO, logger="manisplat.threads")
    assert threads.use_threads(3) == 3
    assert torch.get_num_threads() == 3 and cv2.getNumThreads() == 3
    assert "using 3 CPU threads (--threads" in caplog.text
    monkeypatch.setattr(threads, "free_cores", lambda: (1, 2, 1.4))
    assert threads.use_threads() == 1 and torch.get_num_threads() == 1
    assert "using 1 CPU thread (the free cores: 2, 1.4 busy with other work" in caplog.text
    with pytest.raises(ValueError, match="at least 1"):
        threads.use_threads(0)


def test_omp_num_threads_is_kept_as_a_schedulers_or_users_choice(monkeypatch, caplog, restore_threads):
    """Ray sets OMP_NUM_THREADS to a task's num_cpus: a job started while the node's other tasks are
    still starting must not take their cores. --threads overrides it; a value OpenMP would not take
    is named and ignored."""
    import torch

    caplog.set_level(logging.INFO, logger="manisplat.threads")
    monkeypatch.setattr(threads, "free_cores", lambda: (2, 2, 0.0))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads.use_threads() == 1 and torch.get_num_threads() == 1
    assert "using 1 CPU thread (OMP_NUM_THREADS" in caplog.text
    monkeypatch.setenv("OMP_NUM_THREADS", "3,1")  # nested levels: the first is this process's
    assert threads.use_threads() == 3 and threads.use_threads(2) == 2
    for value in ("0", "x", "-2"):
        monkeypatch.setenv("OMP_NUM_THREADS", value)
        caplog.clear()
        assert threads.use_threads() == 2
        assert f"OMP_NUM_THREADS={value!r} is no thread count" in caplog.text and "the free cores: 2" in caplog.text


def test_reconstruct_says_how_many_threads_it_uses(tmp_path, caplog, restore_threads):
    from manisplat.episode.synthetic import write_sample_episode
    from manisplat.reconstruct.cli import main

    episode = write_sample_episode(tmp_path / "ep", frames=16, width=40, height=30)
    caplog.set_level(logging.INFO)
    assert main([str(episode), "--out", str(tmp_path / "out"), "--plan", "--threads", "1"]) == 0
    assert "using 1 CPU thread (--threads" in caplog.text


@pytest.mark.parametrize(("module", "argv"), [
    ("manisplat.reconstruct.cli", ["ep", "--out", "o"]),
    ("manisplat.augment.cli", ["recon", "--out", "o"]),
    ("manisplat.view.cli", ["twin"]),
])
def test_every_heavy_command_takes_threads(module, argv):
    import importlib

    parser = importlib.import_module(module).build_parser()
    assert parser.parse_args([*argv, "--threads", "2"]).threads == 2
    assert parser.parse_args(argv).threads is None


def test_batch_run_takes_threads():
    from manisplat.batch.cli import build_parser

    assert build_parser().parse_args(["run", "p.toml", "--threads", "2"]).threads == 2
