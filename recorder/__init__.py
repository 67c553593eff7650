"""manisplat-record: synchronised, crash-safe recording of camera frames and joint states.

    >>> from manisplat.recorder import Recorder, RecorderConfig, SystemClock
    >>> rec = Recorder(arm, camera, SystemClock(), RecorderConfig(latency_s=0.012))
    >>> rec.wait_for_arm(); rec.record_episode(Path("episodes/episode_0000"), duration=30)

Modules, one job each: :mod:`.clock` (one monotonic timeline, measured wall offset),
:mod:`.sync` (joint state at frame times), :mod:`.actions` (leader-arm commands),
:mod:`.canlog` (the raw CAN log), :mod:`.writer` (the writer thread), :mod:`.session` (an
episode), :mod:`.recovery`, :mod:`.replaycam` and :mod:`.simrig` (replayed camera, simulated
arm), :mod:`.cli` (``manisplat-record``).
"""

from manisplat.recorder.clock import ClockMap, ManualClock, ScaledClock, SystemClock, measure_offset
from manisplat.recorder.recovery import recover_all, recover_episode
from manisplat.recorder.session import EpisodeResult, EpisodeStats, Recorder, RecorderConfig
from manisplat.recorder.sync import (FLAG_ACTION_STALE, FLAG_BEFORE, FLAG_GAP, FLAG_HELD, JointHistory,
                                     latest_at_arrival, nearest_sample, sync_joints)
from manisplat.recorder.writer import StorageError

__all__ = [
    "FLAG_ACTION_STALE", "FLAG_BEFORE", "FLAG_GAP", "FLAG_HELD", "ClockMap", "EpisodeResult", "EpisodeStats",
    "JointHistory", "ManualClock", "Recorder", "RecorderConfig", "ScaledClock", "StorageError", "SystemClock",
    "latest_at_arrival", "measure_offset", "nearest_sample", "recover_all", "recover_episode", "sync_joints",
]
