"""manisplat-calibrate: camera-to-base / camera-to-flange (hand-eye), intrinsics and camera latency.

    >>> from manisplat.calib import BoardSpec, solve_episode, build_calibration, save_calibration
    >>> spec = BoardSpec()                                   # 7x5 ChArUco, 30 mm squares, DICT_5X5_100
    >>> solved = solve_episode("calib_ep", spec)             # eye-to-hand; mount="link6" for eye-in-hand
    >>> solved.result.T_mount_cam, solved.result.uncertainty()
    >>> save_calibration("calibration.json", build_calibration(solved, spec.to_dict()))

Modules (one job each): :mod:`.board` (board file, printables), :mod:`.camera` (pinhole model),
:mod:`.render` (our own board-view renderer), :mod:`.detect` (ChArUco detection, corner-offset
convention, PnP), :mod:`.handeye` (closed forms, motion diversity), :mod:`.refine` (joint
reprojection least squares), :mod:`.solve` (views -> result), :mod:`.episode_solve` (episode ->
result), :mod:`.intrinsics`, :mod:`.latency`, :mod:`.capture`, :mod:`.report`, :mod:`.result`
(calibration.json, apply), :mod:`.rig` (two arms and several cameras from one episode),
:mod:`.rig_file` (rig.json, apply to version 2), :mod:`.synth` and :mod:`.synth_rig` (synthetic
scenes and episodes), :mod:`.cli`. The names
below load on first use (PEP 562): OpenCV, torch and scipy only when a name that needs them is
used, so ``manisplat-calibrate --help`` answers at once.
"""

from __future__ import annotations

from manisplat._lazy import lazy_exports

_EXPORTS = {
    "board": ("BoardSpec", "load_board", "save_board", "write_printables"),
    "camera": ("CameraModel",),
    "detect": ("BoardDetector", "BoardView", "Detection", "detector_corner_offset"),
    "episode_solve": ("EpisodeSolve", "solve_episode"),
    "errors": ("CalibrationError", "DegenerateMotionError", "InputError", "NotEnoughDataError"),
    "handeye": ("check_motion", "closed_form", "motion_diversity", "opencv_closed_forms"),
    "intrinsics": ("intrinsics_from_images", "intrinsics_from_oak", "solve_intrinsics"),
    "latency": ("LatencyEstimate", "estimate_latency"),
    "render": ("render_board",),
    "result": ("apply_calibration", "build_calibration", "load_calibration", "save_calibration"),
    "rig": ("RigSolve", "solve_rig"),
    "rig_file": ("apply_rig", "build_rig", "load_rig", "save_rig"),
    "solve": ("HandEyeResult", "solve_hand_eye"),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
