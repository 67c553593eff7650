"""CPU threads of a job: idle OpenMP workers that sleep, and as many threads as there are free cores.

PyTorch's CPU kernels and the C++ rasterizer run on one OpenMP pool per process (libgomp on
Linux), by default one thread per core, whose idle workers spin between parallel regions. On a
machine whose cores other jobs use, those spinning workers take turns with the other jobs' work
and with each other: on a 2-core machine at load 2.3-6, ``manisplat-view --video`` rendered 2.0
frames/s with the defaults and 58 with one thread. So here:

- idle workers sleep (``OMP_WAIT_POLICY=PASSIVE``), set when manisplat is imported, which must
  come before torch's first import to take effect (every command line tool does); a user's own
  ``OMP_WAIT_POLICY`` is kept;
- a command that takes only free cores (below) on an otherwise idle machine (other work below
  half a core) lets them spin briefly before they sleep
  (``GOMP_SPINCOUNT`` of :data:`SPIN_COUNT`, about 0.2 ms), set before it imports torch: the
  spin bridges the gaps between one training iteration's parallel regions (tens of microseconds
  of Python each), where workers that slept at once had to be woken for every region and the
  sample's iteration took 1.6x as long on an idle 2-core machine
  (``benchmarks/results_contention/wait_policy/``). Where threads may outnumber the free cores
  (a library user's own thread count, a ``--threads`` above them), spinning workers would take
  turns with the other jobs, so they sleep at once there;
- a job takes the cores that are free when it starts: the cores this process may run on minus
  the whole cores other work keeps busy (measured over 0.2 s), at least one; ``--threads N`` on
  every heavy command sets it, and so does ``OMP_NUM_THREADS`` where it is set (by the user, or by
  a scheduler to what it gave the job: Ray sets it to a task's ``num_cpus``, so a reconstruction
  that took the cores free when it started would share them with the tasks started after it);
  torch's pool and OpenCV's follow it, and the log says how many and why.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time

log = logging.getLogger(__name__)


#: busy-wait iterations of an idle OpenMP worker before it sleeps: about 0.2 ms by libgomp's own
#: estimate of 100 000 a millisecond (its default is 3 ms, or none at all with PASSIVE alone)
SPIN_COUNT = 20_000


#: whether :func:`sleep_when_idle` chose the wait policy (the user did not)
_POLICY_OURS = False


def sleep_when_idle() -> None:
    """Make OpenMP's idle workers sleep instead of spin, unless ``OMP_WAIT_POLICY`` is set (only
    effective before torch's first import loads OpenMP)."""
    global _POLICY_OURS
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        _POLICY_OURS = True


#: other work (cores) under which the machine counts as idle enough for spinning workers
SPIN_IF_BUSY_BELOW = 0.5


def spin_briefly_when_idle(threads: int, free: int, busy: float) -> None:
    """Let idle workers spin :data:`SPIN_COUNT` before they sleep when each of ``threads`` has a
    free core (of ``free``), other work keeps less than :data:`SPIN_IF_BUSY_BELOW` of a core busy
    (``busy``: a process beside this one would take turns with the spinning workers), the wait
    policy is ours and ``GOMP_SPINCOUNT`` unset; only effective before torch's first import, so not
    done after it."""
    if (_POLICY_OURS and 1 < threads <= free and busy < SPIN_IF_BUSY_BELOW and "GOMP_SPINCOUNT" not in os.environ
            and "torch" not in sys.modules):
        os.environ["GOMP_SPINCOUNT"] = str(SPIN_COUNT)


def free_cores(sample_s: float = 0.2) -> tuple[int, int, float]:
    """(free cores, cores this process may use, cores busy with other work): the busy cores are
    measured over ``sample_s`` seconds from ``/proc/stat`` (Linux; elsewhere the 1-minute load
    average, which lags); free = cores minus the busy ones' whole part, within [1, cores] (a core
    less than fully busy counts as free: idle workers sleep, so a thread too many costs little, one
    too few halves a 2-core machine)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    busy = _busy_cores(sample_s)
    if busy is None:
        busy = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    return max(1, min(cores, cores - math.floor(busy))), cores, busy


def _busy_cores(sample_s: float) -> float | None:
    """Cores busy over the next ``sample_s`` seconds, from the kernel's CPU time counters (None
    where ``/proc/stat`` cannot be read)."""
    def totals() -> tuple[int, int, int]:
        with open("/proc/stat") as f:
            lines = f.read().splitlines()
        fields = [int(v) for v in lines[0].split()[1:]]  # user nice system idle iowait irq softirq steal ...
        n = sum(line.startswith("cpu") and line[3:4].isdigit() for line in lines)
        return sum(fields[:8]), fields[3] + fields[4], n

    try:
        total0, idle0, n = totals()
        time.sleep(sample_s)
        total1, idle1, _ = totals()
    except (OSError, ValueError, IndexError):
        return None
    spent = total1 - total0
    return 0.0 if spent <= 0 else n * (spent - (idle1 - idle0)) / spent


def environment_threads() -> int | None:
    """The threads ``OMP_NUM_THREADS`` asks for (its first level's: ``4,2`` is 4), or None where
    it is unset or no whole number above 0 (a warning names it; OpenMP ignores such a value too).
    A scheduler sets it to what it gave the job (Ray to a task's ``num_cpus``, many SLURM setups
    to ``--cpus-per-task``), a user to what they chose."""
    text = os.environ.get("OMP_NUM_THREADS", "").strip()
    if not text:
        return None
    first = text.split(",")[0].strip()
    if not first.isdigit() or int(first) < 1:
        log.warning("OMP_NUM_THREADS=%r is no thread count (a whole number above 0): ignored", text)
        return None
    return int(first)


def use_threads(requested: int | None = None) -> int:
    """Set this process's CPU threads (torch's pool, OpenCV's) to ``requested``, else to what
    ``OMP_NUM_THREADS`` asks for (:func:`environment_threads`), else to the free cores; log the
    choice and return it."""
    if requested is not None and requested < 1:
        raise ValueError(f"threads must be at least 1, got {requested}")
    free, cores, busy = free_cores()
    if requested is not None:
        threads, why = requested, "--threads"
    elif (asked := environment_threads()) is not None:
        threads, why = asked, "OMP_NUM_THREADS"
    else:
        threads, why = free, f"the free cores: {cores}, {busy:.1f} busy with other work"
    spin_briefly_when_idle(threads, free, busy)
    import cv2
    import torch

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    log.info("using %d CPU thread%s (%s; OpenMP wait policy %s)", threads, "" if threads == 1 else "s", why,
             _wait_policy())
    return threads


def _wait_policy() -> str:
    """How idle OpenMP workers wait, as the environment sets it, for the log."""
    policy = os.environ.get("OMP_WAIT_POLICY", "the default").lower()
    spins = os.environ.get("GOMP_SPINCOUNT")
    return policy if spins is None else f"{policy} after {spins} spins"


THREADS_HELP = "CPU threads (default: the cores free when it starts, measured over 0.2 s)"
