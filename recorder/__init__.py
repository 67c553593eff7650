"""manisplat-record: synchronised, crash-safe recording of camera frames and joint states.

    >>> from manisplat.recorder import Recorder, RecorderConfig, SystemClock
    >>> rec = Recorder(arm, camera, SystemClock(), RecorderConfig(latency_s=0.012))
    >>> rec.wait_for_arm(); rec.record_episode(Path("episodes/episode_0000"), duration=30)

Modules, one job each: :mod:`.clock` (one monotonic timeline, measured wall offset),
:mod:`.sync` (joint state at frame times), :mod:`.actions` (leader-arm commands),
:mod:`.canlog` (the raw CAN log), :mod:`.armfeed` (one arm's samples, sync and CAN log),
:mod:`.camfeed` (one camera read on its own thread, its drops), :mod:`.writer` (the writer
thread), :mod:`.config` (the settings), :mod:`.loop` (the frame loop of an episode),
:mod:`.layout` (what is written: version 1 or 2), :mod:`.stats` and :mod:`.result` (what an
episode gives back), :mod:`.rig` (the recorder of named arms and cameras) and :mod:`.rigcli`
(its options and devices), :mod:`.session` (its special case: one arm and camera, version 1),
:mod:`.recovery`,
:mod:`.replaycam` and :mod:`.simrig` (replayed camera, simulated
arm), :mod:`.cli` (``manisplat-record``). The names below load on first use (PEP 562), so
``manisplat-record --help`` imports none of them.
"""

from __future__ import annotations

from manisplat._lazy import lazy_exports

_EXPORTS = {
    "clock": ("ClockMap", "ManualClock", "ScaledClock", "SystemClock", "measure_offset"),
    "recovery": ("recover_all", "recover_episode"),
    "config": ("RecorderConfig",),
    "result": ("EpisodeResult", "Status"),
    "rig": ("RigArm", "RigCamera", "RigRecorder"),
    "session": ("Recorder",),
    "stats": ("ArmStats", "EpisodeStats", "RigStats"),
    "sync": ("FLAG_ACTION_STALE", "FLAG_BEFORE", "FLAG_GAP", "FLAG_HELD", "JointHistory", "latest_at_arrival",
             "nearest_sample", "sync_joints"),
    "camfeed": ("CameraStats",),
    "writer": ("StorageError",),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
