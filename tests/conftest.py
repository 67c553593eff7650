"""Shared test settings: deterministic hypothesis runs, so CI failures reproduce; one torch thread
per xdist worker."""

import os

import pytest
from hypothesis import HealthCheck, settings

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `-n auto` runs a worker per core: a torch (OpenMP) pool per worker as wide as the machine
    # oversubscribes it, and the pools' spinning threads take the time (tests/reconstruct on 2 cores:
    # 186 s with the default threads, 69 s with one each). Subprocesses the tests start inherit it.
    import torch

    torch.set_num_threads(int(os.environ.setdefault("OMP_NUM_THREADS", "1")))

settings.register_profile(
    "manisplat",
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("manisplat")


# Tests that run real-time machinery (replayed cameras and CAN buses, recorders, the replay
# streamer, depthai's own pipelines) or load every core on purpose (a local Ray cluster, a browser
# drawing WebGL in software) share one xdist group, so they run one after another on one worker
# (`--dist loadgroup` in pyproject): on a 2-core runner, those loads beside a depthai recording
# made it drop frames.
REALTIME = ("tests/recorder/", "tests/replay/", "tests/drivers/test_oak.py", "tests/drivers/test_simulated.py",
            "tests/batch/", "tests/view/",
            "tests/augment/test_cli.py::test_an_augmented_episode_replays_on_the_simulated_arm")


LAST = ("tests/batch/",)
"""Run last in the session (and so last in the realtime group's worker): after the local Ray cluster
had run in a worker process, the simulated PiPER on the virtual CAN bus there once went silent for
30 s in a later recorder test."""


def _uses_a_module_fixture(item) -> bool:
    """Whether ``item`` uses a fixture of module scope (a twin trained once for a module's tests)."""
    return any(defs[-1].scope == "module" for defs in item._fixtureinfo.name2fixturedefs.values())


@pytest.hookimpl(tryfirst=True)  # before xdist's own, which names each test by the groups marked so far
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.startswith(REALTIME):
            item.add_marker(pytest.mark.xdist_group("realtime"))
        elif _uses_a_module_fixture(item):
            # xdist builds a module's fixture in every worker that runs one of its tests: the tests
            # that share one run on one worker, which builds it once
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))
    items[:] = [i for i in items if not i.nodeid.startswith(LAST)] + [i for i in items if i.nodeid.startswith(LAST)]
