"""Import one ACT / ALOHA / AgileX Cobot Magic HDF5 episode (``episode_<i>.hdf5``).

Layout (``shared/reference/augmentation.md`` section 5.3)::

    attrs: sim (bool), compress (bool)
    /observations/qpos          (T, 14) [left 6 joints, left gripper, right 6, right gripper]; (T, 7) single arm
    /observations/qvel          (T, 14)  (not imported)
    /observations/effort        (T, 14) or (T, 7): the grippers' columns imported (``gripper_effort``)
    /observations/images/<cam>  (T, H, W, 3) uint8, or with compress: (T, L) uint8 JPEG bytes padded
                                with zeros (+ /compress_len (n_cams, T))
    /observations/images_depth/<cam>  (T, H, W) uint16 millimetres (optional)
    /action                     (T, 14) leader-arm positions, same layout (optional)
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any, Iterator

import cv2
import h5py
import numpy as np

from manisplat.episode.format import ACTION_COLUMNS, GRIPPER_EFFORT_COLUMN, EpisodeFormatError
from manisplat.episode.images import StoredChroma, chroma_keys, jpeg_chroma_subsampling
from manisplat.episode.meta import CameraInfo, RobotInfo
from manisplat.episode.reader import Episode
from manisplat.episode.writer import EpisodeWriter

log = logging.getLogger(__name__)

SOURCE = "import:act_hdf5"
DEPTH_SCALE_MM = 0.001
ARM_COLUMNS = {"left": slice(0, 7), "right": slice(7, 14), "single": slice(0, 7)}
"""Columns of qpos/action holding one arm's 6 joints and gripper, by ``arm``."""


def _contents(f: h5py.File) -> str:
    """Every dataset of ``f`` with its shape and type, for error messages."""
    found: list[str] = []
    f.visititems(lambda name, obj: found.append(f"{name} {obj.shape} {obj.dtype}")
                 if isinstance(obj, h5py.Dataset) else None)
    return ", ".join(found) or "no datasets"


def _dataset(f: h5py.File, name: str, where: Path) -> h5py.Dataset:
    obj = f.get(name)
    if not isinstance(obj, h5py.Dataset):
        raise EpisodeFormatError(f"{where}: no dataset /{name}; the file has: {_contents(f)}")
    return obj


def _arm(ds: h5py.Dataset, arm: str, length: int, where: Path) -> np.ndarray:
    """(T, 7) joints + gripper of ``arm`` from a qpos/action dataset."""
    width = {"single": 7}.get(arm, 14)
    if ds.shape != (length, width):
        layout = ("(T, 7) for arm='single'" if arm == "single" else
                  "(T, 14) [left 6 joints, left gripper, right 6, right gripper] for arm='left'/'right'")
        raise EpisodeFormatError(f"{where}: /{ds.name.lstrip('/')} has shape {ds.shape}; expected {layout} "
                                 f"with T={length}")
    return np.asarray(ds[:, ARM_COLUMNS[arm]], dtype=np.float64)


def _images(ds: h5py.Dataset, compressed: bool, bgr: bool, where: Path) -> Iterator[np.ndarray]:
    """(H, W, 3) uint8 RGB frames of a camera dataset, read and decoded one at a time."""
    for i in range(ds.shape[0]):
        image = ds[i]
        if compressed:
            image = cv2.imdecode(image, cv2.IMREAD_COLOR)
            if image is None:
                raise EpisodeFormatError(f"{where}: {ds.name} frame {i}: cannot decode the JPEG bytes")
        yield cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if bgr else image


def _chroma_subsampling(ds: h5py.Dataset, compressed: bool, bgr: bool, where: Path) -> dict[str, Any]:
    """The episode.json keys saying how a camera's JPEG frames kept their colour (read from its
    first frame's header; the encoder took the stored arrays for BGR, which RGB arrays are not),
    or ``{}`` for raw frames."""
    if not compressed:
        return {}
    try:
        scheme = jpeg_chroma_subsampling(ds[0].tobytes())
    except ValueError as exc:
        raise EpisodeFormatError(f"{where}: {ds.name} frame 0: {exc}") from None
    return {} if scheme is None else chroma_keys(StoredChroma(scheme, red_blue_swapped=not bgr))


def _camera_dataset(f: h5py.File, camera: str, length: int, where: Path) -> tuple[h5py.Dataset, bool]:
    """The colour dataset of ``camera`` and whether it holds JPEG bytes."""
    group = f.get("observations/images")
    if not isinstance(group, h5py.Group):
        raise EpisodeFormatError(f"{where}: no group /observations/images; the file has: {_contents(f)}")
    if camera not in group:
        raise EpisodeFormatError(f"{where}: no camera {camera!r}; cameras in the file: {', '.join(group)}")
    ds = group[camera]
    compressed = ds.ndim == 2
    if ds.dtype != np.uint8 or ds.shape[0] != length or not (compressed or (ds.ndim == 4 and ds.shape[3] == 3)):
        raise EpisodeFormatError(f"{where}: {ds.name} has shape {ds.shape} {ds.dtype}; expected (T, H, W, 3) uint8 "
                                 f"or (T, L) uint8 JPEG bytes, with T={length} like /observations/qpos")
    if "compress" in f.attrs and bool(f.attrs["compress"]) != compressed:
        raise EpisodeFormatError(f"{where}: attribute compress={bool(f.attrs['compress'])} but {ds.name} has shape "
                                 f"{ds.shape}")
    return ds, compressed


def import_act_hdf5(h5_path: str | Path, out_dir: str | Path, *, K: Any = None, arm: str = "left",
                    camera: str = "cam_high", fps: float = 30.0, gripper_scale: float = 1.0,
                    dist: Any = (), mount: str = "base", bgr: bool = False,
                    robot_description: str = "builtin:agilex_piper", task: str | None = None,
                    image_format: str = "png", overwrite: bool = False) -> Episode:
    """Convert one ACT-style HDF5 episode into an episode folder, streaming frame by frame.

    Frame ``i`` gets ``t = i / fps``, ``q1..q6`` and ``gripper`` from ``qpos`` (the chosen arm),
    the image of ``camera``, its depth (``images_depth/<camera>``, millimetres, so
    ``depth_scale`` 0.001) when present, ``a1..a6, a_gripper`` from ``/action`` and the gripper's
    effort (``gripper_effort``) from ``/observations/effort`` when present.

    Colour order: Cobot Magic stores the arrays it got from ROS ``cv_bridge`` with
    ``passthrough`` encoding from ``rgb8`` cameras, i.e. RGB; compressed files hold those arrays
    JPEG-encoded by ``cv2.imencode``, so decoding gives the same RGB arrays back. Images are
    therefore taken as RGB; pass ``bgr=True`` for files whose arrays are BGR.

    Args:
        h5_path: the ``.hdf5`` file.
        out_dir: episode folder to create.
        K: (3, 3) intrinsics in pixels, required: these files store no calibration. A
            :class:`CameraInfo` (from calibration) may be given instead; its size must match.
        arm: ``"left"`` or ``"right"`` half of a (T, 14) dual-arm file, or ``"single"`` for (T, 7).
        camera: image dataset name (``cam_high``, ``cam_left_wrist``, ``cam_right_wrist``, ``top``).
        fps: recording rate in Hz (Cobot Magic default 30).
        gripper_scale: factor from the file's gripper value to the finger-pad gap in metres.
        dist: OpenCV distortion coefficients (when K is an array).
        mount: ``"base"`` or the link a wrist camera is fixed to (when K is an array).
        bgr: the stored arrays are BGR, not RGB.
        robot_description: ``episode.json`` ``robot.description`` (how the joint angles read).
        task: task description, stored as ``episode.json`` ``task``.
        image_format: ``"png"`` or ``"jpg"`` for the rgb files.
        overwrite: replace an existing episode at ``out_dir``.

    Returns:
        the new episode, opened for reading.
    """
    h5_path, out_dir = Path(h5_path), Path(out_dir)
    if K is None:
        raise EpisodeFormatError(
            f"{h5_path}: ACT/Cobot Magic HDF5 files store no camera intrinsics; pass K=[[fx, 0, cx], "
            "[0, fy, cy], [0, 0, 1]] (pixels, from your calibration or the camera's factory values) "
            "or a CameraInfo, e.g. `manisplat-episode import-act FILE --K fx,fy,cx,cy`")
    if arm not in ARM_COLUMNS:
        raise ValueError(f"arm must be one of {sorted(ARM_COLUMNS)}; got {arm!r}")
    if not h5_path.is_file():
        raise FileNotFoundError(f"{h5_path}: no such file")
    with h5py.File(h5_path, "r") as f:
        qpos_ds = _dataset(f, "observations/qpos", h5_path)
        length = qpos_ds.shape[0]
        scale = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, gripper_scale])  # gripper value -> metres
        qpos = _arm(qpos_ds, arm, length, h5_path) * scale
        action = _arm(_dataset(f, "action", h5_path), arm, length, h5_path) * scale if "action" in f else None
        effort = (_arm(_dataset(f, "observations/effort", h5_path), arm, length, h5_path)[:, 6]
                  if "observations/effort" in f else None)
        columns = ((*ACTION_COLUMNS,) if action is not None else ()) + ((GRIPPER_EFFORT_COLUMN,) if effort is not None else ())
        color, compressed = _camera_dataset(f, camera, length, h5_path)
        depth = f.get(f"observations/images_depth/{camera}")
        frames = _images(color, compressed, bgr, h5_path)
        first = next(frames, None)
        if first is None:
            raise EpisodeFormatError(f"{h5_path}: {color.name} holds no frames")
        height, width = first.shape[:2]
        if depth is not None and (depth.shape != (length, height, width) or depth.dtype != np.uint16):
            raise EpisodeFormatError(f"{h5_path}: {depth.name} has shape {depth.shape} {depth.dtype}; expected "
                                     f"({length}, {height}, {width}) uint16 millimetres")
        cam = K if isinstance(K, CameraInfo) else CameraInfo(name=camera, width=width, height=height, K=K,
                                                              dist=dist, mount=mount)
        cam = replace(cam, extra={**cam.extra, **_chroma_subsampling(color, compressed, bgr, h5_path)})
        if (cam.width, cam.height) != (width, height):
            raise EpisodeFormatError(f"{h5_path}: images are {width}x{height} but the camera is "
                                     f"{cam.width}x{cam.height}")
        robot = RobotInfo(description=robot_description)
        source_info = {"file": h5_path.name, "arm": arm, "camera": camera, "sim": bool(f.attrs.get("sim", False)),
                       "compress": compressed, "gripper_scale": gripper_scale}
        extra_meta = {"import": source_info, **({"task": task} if task is not None else {})}
        with EpisodeWriter(out_dir, cam, robot, fps, source=SOURCE,
                           depth_scale=DEPTH_SCALE_MM if depth is not None else None,
                           image_format=image_format, extra_frame_columns=columns,
                           extra_meta=extra_meta, overwrite=overwrite) as writer:
            for i, rgb in enumerate(itertools.chain([first], frames)):
                extra = {} if action is None else dict(zip(ACTION_COLUMNS, action[i].tolist()))
                if effort is not None:
                    extra[GRIPPER_EFFORT_COLUMN] = float(effort[i])
                try:
                    writer.add_frame(i / fps, qpos[i, :6], qpos[i, 6], rgb,
                                     depth=None if depth is None else depth[i], extra=extra or None)
                except ValueError as exc:
                    raise EpisodeFormatError(f"{h5_path}: frame {i}: {exc}") from exc
    log.info("%s: imported %d frames into %s", h5_path, length, out_dir)
    return Episode.open(out_dir)

