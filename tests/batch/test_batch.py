"""manisplat-batch on a real local Ray cluster (2 worker CPUs, small generated episodes): the full
pipeline, a worker SIGKILLed mid-task, a corrupt episode among good ones, a second run doing only
what is missing; and the same pipeline without Ray."""

from __future__ import annotations

import json
import os
import shutil
import signal
import textwrap
import threading
import time
from pathlib import Path

import pytest

from manisplat.batch.cli import main
from manisplat.batch.config import BatchConfigError, load_config
from manisplat.batch.runner import LocalExecutor, RayExecutor, batch_status, run_batch, unfit_reconstruction
from manisplat.episode import validate
from manisplat.episode.synthetic import write_sample_episode
from manisplat.twin import Twin

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'manisplat[distributed]')")

PIPELINE = """
episodes = ["episodes/*"]
out = "out"
[reconstruct]
iters = 5
[augment]
n = 1
seed = 1
[export]
task = "pick the box and place it on the mat"
[retries]
max = 2
"""


@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster with 2 CPUs, shared by this module's tests."""
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 1024 ** 2, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> Path:
    """Two sample episodes (32 frames, 64x48) in SOURCES/episodes/."""
    root = tmp_path_factory.mktemp("batch_sources")
    for seed in (0, 1):
        write_sample_episode(root / "episodes" / f"ep{seed}", frames=32, width=64, height=48, seed=seed)
    return root


def _batch(sources: Path, tmp_path: Path, pipeline: str = PIPELINE) -> Path:
    shutil.copytree(sources / "episodes", tmp_path / "episodes")
    (tmp_path / "pipeline.toml").write_text(pipeline)
    return tmp_path / "pipeline.toml"


def _statuses(results) -> dict[tuple[str, str], str]:
    return {(r.episode, r.stage): r.status for r in results}


def _check_outputs(out: Path, episodes: list[str]) -> None:
    for name in episodes:
        assert Twin.load(out / "recon" / name).n_frames == 32
        augmented = sorted((out / "aug" / name).glob("episode_*"))
        assert augmented and all(validate(p).ok for p in augmented)
    info = json.loads((out / "dataset" / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 2 * len(episodes)
    assert not list(out.rglob(".partial-*"))  # nothing half-written left


def test_the_full_pipeline_on_ray_and_a_second_run_does_nothing_more(cluster, sources, tmp_path):
    config = load_config(_batch(sources, tmp_path))
    results = run_batch(config, RayExecutor(None, config.max_retries))
    assert set(_statuses(results).values()) == {"done"}, _statuses(results)
    _check_outputs(config.out, ["ep0", "ep1"])
    assert {r.status for r in batch_status(config.out)} == {"complete"}
    again = run_batch(config, RayExecutor(None, config.max_retries))
    assert set(_statuses(again).values()) == {"skipped"}
    summary = json.loads((config.out / "batch.json").read_text())
    assert summary["executor"].startswith("Ray (2 CPUs") and len(summary["results"]) == 7

    # an interruption that lost ep1's augmentation and the dataset: only those are redone
    shutil.rmtree(config.out / "aug" / "ep1")
    shutil.rmtree(config.out / "dataset")
    third = _statuses(run_batch(config, RayExecutor(None, config.max_retries)))
    assert third[("ep1", "augment")] == "done" and third[("(all)", "export")] == "done"
    assert [k for k, v in third.items() if v == "done"] == [("ep1", "augment"), ("(all)", "export")]
    _check_outputs(config.out, ["ep0", "ep1"])


def test_a_worker_killed_mid_task_is_retried_and_the_batch_completes(cluster, sources, tmp_path):
    config = load_config(_batch(sources, tmp_path))
    outcome: dict = {}
    runner = threading.Thread(target=lambda: outcome.update(results=run_batch(
        config, RayExecutor(None, config.max_retries))), daemon=True)
    runner.start()
    pid_file = config.out / "recon" / ".partial-ep0.pid"
    deadline = time.monotonic() + 300
    while not pid_file.is_file() and runner.is_alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert pid_file.is_file(), "the reconstruction of ep0 never started"
    victim = int(pid_file.read_text())
    assert victim != os.getpid()  # a Ray worker process, not this one
    os.kill(victim, signal.SIGKILL)
    runner.join(timeout=600)
    assert not runner.is_alive()
    statuses = _statuses(outcome["results"])
    assert set(statuses.values()) == {"done"}, statuses
    with pytest.raises(ProcessLookupError):
        os.kill(victim, 0)  # it really died
    _check_outputs(config.out, ["ep0", "ep1"])


def test_a_corrupt_episode_is_reported_and_the_others_complete(cluster, sources, tmp_path, capsys):
    pipeline = _batch(sources, tmp_path)
    frame = tmp_path / "episodes" / "ep1" / "rgb" / "000007.png"
    frame.write_bytes(frame.read_bytes()[:100])  # truncated
    assert main(["run", str(pipeline), "-q"]) == 1
    out = capsys.readouterr().out
    statuses = _statuses(run_batch(load_config(pipeline), LocalExecutor()))  # rerun: same verdicts, no Ray
    assert statuses[("ep1", "validate")] == "failed" and statuses[("ep1", "reconstruct")] == "blocked"
    assert statuses[("ep0", "augment")] == "skipped" and statuses[("(all)", "export")] == "skipped"
    assert "ep1                      validate     failed" in out and "invalid episode" in out
    error = (tmp_path / "out" / "errors" / "ep1.validate.txt").read_text()
    assert "000007.png" in error
    info = json.loads((tmp_path / "out" / "dataset" / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 2  # ep0 and its augmented demonstration
    rows = {(r.episode, r.stage): r.status for r in batch_status(tmp_path / "out")}
    assert rows[("ep1", "validate")] == "failed" and rows[("ep0", "augment")] == "complete"


def test_without_ray_the_same_pipeline_runs_in_process(sources, tmp_path, monkeypatch, capsys):
    import manisplat.batch.cli as cli

    pipeline = _batch(sources, tmp_path, PIPELINE.replace('"episodes/*"', '"episodes/ep0"'))
    real_find_spec = cli.importlib.util.find_spec
    monkeypatch.setattr(cli.importlib.util, "find_spec", lambda name: None if name == "ray" else real_find_spec(name))
    assert main(["run", str(pipeline), "-q"]) == 0
    err = capsys.readouterr().err
    assert "pip install 'manisplat[distributed]'" in err and "sequential (in-process)" in err
    _check_outputs(tmp_path / "out", ["ep0"])


def test_configuration_errors_name_the_key(tmp_path):
    (tmp_path / "a" / "ep").mkdir(parents=True)
    (tmp_path / "b" / "ep").mkdir(parents=True)
    cases = {'episodes = ["none/*"]\nout = "o"': "matches nothing",
             'episodes = ["a/*", "b/*"]\nout = "o"': "several folders named",
             'episodes = ["a/*"]': "out: the output folder is required",
             'episodes = ["a/*"]\nout = "o"\n[export]\nformat = "zarr"': "export.format must be one of",
             'episodes = ["a/*"]\nout = "o"\n[augment]\nn = "ten"': "augment.n: expected int",
             'episodes = "a"\nout = "o"': "episodes: expected a list",
             'episodes = ["a/*"]\nout = "o"\n[reconstruct]\ngpus = 1.5': "reconstruct.gpus a fraction"}
    for text, message in cases.items():
        (tmp_path / "p.toml").write_text(text)
        with pytest.raises(BatchConfigError, match=message):
            load_config(tmp_path / "p.toml")
    (tmp_path / "p.toml").write_text('episodes = ["a/*"]\nout = "o"\n[reconstruct]\ndevice = "cuda"\ngpus = 0.25')
    config = load_config(tmp_path / "p.toml")
    assert config.reconstruct_gpus == 0.25 and config.episodes == ((tmp_path / "a" / "ep").resolve(),)
    assert load_config(tmp_path / "p.toml").out == (tmp_path / "o").resolve()
    (tmp_path / "p.toml").write_text('episodes = ["none"]\nout = "o"')
    with pytest.raises(BatchConfigError, match="'none' matches nothing"):
        load_config(tmp_path / "p.toml")
    assert main(["run", str(tmp_path / "p.toml")]) == 2
    assert main(["status", str(tmp_path)]) == 2


def test_the_pipeline_example_in_the_help_is_a_working_pipeline(tmp_path, capsys):
    from manisplat.batch.config import load_config

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    shown = capsys.readouterr().out
    example = shown[shown.index("for example:") + len("for example:"):shown.index("Each stage of each episode")]
    (tmp_path / "recordings" / "ep0").mkdir(parents=True)
    (tmp_path / "PIPELINE.toml").write_text(textwrap.dedent(example))
    config = load_config(tmp_path / "PIPELINE.toml")
    assert [p.name for p in config.episodes] == ["ep0"] and config.iters == 3000 and config.n == 20


def test_reconstructions_no_node_of_the_local_cluster_can_hold_are_refused_not_left_waiting(cluster, sources, tmp_path,
                                                                                            capsys):
    """The module's cluster has 2 CPUs and no GPU: Ray would keep such tasks pending forever."""
    for section, message in (("cpus = 4", "reconstruct.cpus = 4, but the largest node of the Ray cluster has 2 CPUs"),
                             ('device = "cuda"\ngpus = 0.5', "reconstruct.gpus = 0.5 (device cuda), but the largest "
                                                            "node of the Ray cluster has 0 GPUs")):
        pipeline = _batch(sources, tmp_path / section[:4], PIPELINE.replace("iters = 5", f"iters = 5\n{section}"))
        assert main(["run", str(pipeline), "-q"]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / section[:4] / "out").exists()  # refused before anything ran
    assert ray.is_initialized()  # the module's cluster, not the command's, stays up


def test_a_reconstruction_fits_only_a_node_that_has_both_its_cpus_and_its_gpus(tmp_path):
    (tmp_path / "a" / "ep").mkdir(parents=True)
    (tmp_path / "p.toml").write_text('episodes = ["a/*"]\nout = "o"\n[reconstruct]\ndevice = "cuda"\ncpus = 4\ngpus = 1')
    config = load_config(tmp_path / "p.toml")
    assert unfit_reconstruction(config, [(8.0, 0.0), (2.0, 1.0)]) == ("reconstruct.cpus = 4 and reconstruct.gpus = 1: "
                                                                       "no node of the Ray cluster has both")
    assert unfit_reconstruction(config, [(8.0, 0.0), (4.0, 2.0)]) is None
    assert "has 0 CPUs" in unfit_reconstruction(config, [])
