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
(calibration.json, apply), :mod:`.synth` (synthetic scenes and episodes), :mod:`.cli`.
"""

from manisplat.calib.board import BoardSpec, load_board, save_board, write_printables
from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardDetector, BoardView, Detection, detector_corner_offset
from manisplat.calib.episode_solve import EpisodeSolve, solve_episode
from manisplat.calib.errors import CalibrationError, DegenerateMotionError, InputError, NotEnoughDataError
from manisplat.calib.handeye import check_motion, closed_form, motion_diversity, opencv_closed_forms
from manisplat.calib.intrinsics import intrinsics_from_images, intrinsics_from_oak, solve_intrinsics
from manisplat.calib.latency import LatencyEstimate, estimate_latency
from manisplat.calib.render import render_board
from manisplat.calib.result import apply_calibration, build_calibration, load_calibration, save_calibration
from manisplat.calib.solve import HandEyeResult, solve_hand_eye

__all__ = [
    "BoardDetector", "BoardSpec", "BoardView", "CalibrationError", "CameraModel", "DegenerateMotionError",
    "Detection", "EpisodeSolve", "HandEyeResult", "InputError", "LatencyEstimate", "NotEnoughDataError",
    "apply_calibration", "build_calibration", "check_motion", "closed_form", "detector_corner_offset",
    "estimate_latency", "intrinsics_from_images", "intrinsics_from_oak", "load_board", "load_calibration",
    "motion_diversity", "opencv_closed_forms", "render_board", "save_board", "save_calibration", "solve_episode",
    "solve_hand_eye", "solve_intrinsics", "write_printables",
]
