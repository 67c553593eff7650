"""Write a version 2 episode (named arms and cameras) crash-safely, frame by frame.

The same order of writes and the same fsync policy as the version 1
:class:`~manisplat.episode.writer.EpisodeWriter` (it shares its :class:`WriterBase`):
``episode.json`` with ``complete: false`` first, then per frame every camera's images (each
through a temporary name and a rename), then the frame's ``frames.csv`` row in one write, flushed;
joint samples go to ``joints_<arm>.csv``. ``close`` writes ``complete: true`` and ``frame_count``.
A killed writer therefore leaves what ``recover`` clears away: temporary files, a torn last row,
images of some cameras whose row was never written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from manisplat.episode.format import JOINT_COLUMNS, VERSION_2, image_name
from manisplat.episode.images import DEPTH, MASK, RGB, ImageKind, depth_to_raw, encode_image
from manisplat.episode.meta import ArmInfo, CameraInfo, EpisodeMeta
from manisplat.episode.writer import (IMAGE_FORMATS, WriterBase, _check_columns, _extra_values, _finite,
                                      _joint_vector)


def _state(name: str, value: Any) -> np.ndarray:
    """(7,) float64: six joint angles (rad) and the gripper (m), each checked as the v1 writer checks them."""
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (7,):
        raise ValueError(f"{name} must hold 6 joint angles (rad) and the gripper (m); got shape {v.shape}")
    return np.append(_joint_vector(name, v[:6]), _finite(f"{name} gripper", v[6]))


def _exactly(name: str, given: Iterable[str], expected: Iterable[str]) -> None:
    given, expected = list(given), list(expected)
    if set(given) != set(expected):
        missing = [n for n in expected if n not in given]
        unknown = [n for n in given if n not in expected]
        raise ValueError(f"{name} must give exactly {expected}; missing {missing}, unknown {unknown}")


class EpisodeWriterV2(WriterBase):
    """Writes one version 2 episode folder; use it as a context manager.

    Args:
        path: episode folder to create (an existing episode only with ``overwrite``).
        arms: the arms, in the order of their ``frames.csv`` columns (:class:`ArmInfo` with ``name``).
        cameras: the cameras (:class:`CameraInfo`, mounts ``"world"`` or ``"<arm>/<link>"``).
        fps: declared frame rate in Hz.
        source, depth_scale, labels, objects, image_format, extra_meta, fsync_every, overwrite:
            as for :class:`~manisplat.episode.writer.EpisodeWriter`.
        actions: every frame gives each arm's action (``<arm>.a1..a6,<arm>.a_gripper`` columns).
        camera_times: cameras whose own frame time every frame gives (``<camera>.t`` columns),
            for cameras not triggered with the frame.
        extra_frame_columns: names of further ``frames.csv`` columns every frame gives.
        joint_columns: names of optional columns of every ``joints_<arm>.csv``.

    Every frame carries the same images as frame 0 (for each camera: rgb, and depth or masks
    either always or never). If the ``with`` block raises, ``complete`` stays false.
    """

    def __init__(self, path: str | Path, arms: Sequence[ArmInfo], cameras: Sequence[CameraInfo], fps: float, *,
                 source: str = "recorder", depth_scale: float | None = None,
                 labels: Mapping[int, str] | None = None, objects: Sequence[str] | None = None,
                 image_format: str = "png", actions: bool = False, camera_times: Sequence[str] = (),
                 extra_frame_columns: Sequence[str] = (), joint_columns: Sequence[str] = (),
                 extra_meta: Mapping[str, Any] | None = None, fsync_every: int = 30, overwrite: bool = False) -> None:
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format must be one of {sorted(IMAGE_FORMATS)}; got {image_format!r}")
        meta = EpisodeMeta(version=VERSION_2, complete=False, source=source, arms=list(arms), cameras=list(cameras),
                           fps=fps, depth_scale=depth_scale, labels=dict(labels or {}), objects=list(objects or []),
                           extra=dict(extra_meta or {}))
        layout = meta.layout
        unknown = [c for c in camera_times if c not in meta.cameras]
        if unknown:
            raise ValueError(f"camera_times: no camera {unknown}; cameras: {list(meta.cameras)}")
        self._actions = actions
        self._camera_times = tuple(c for c in meta.cameras if c in camera_times)
        declared = [c for a in layout.arms for c in (a.actions if actions else ())]
        declared += [layout.camera(c).time_column for c in self._camera_times]
        self._extra_columns = _check_columns("extra_frame_columns", extra_frame_columns,
                                             (*layout.frame_columns, *declared))
        self._joint_columns = _check_columns("joint_columns", joint_columns, JOINT_COLUMNS)
        self._suffixes = {RGB.folder: IMAGE_FORMATS[image_format], DEPTH.folder: DEPTH.suffixes[0],
                          MASK.folder: MASK.suffixes[0]}
        super().__init__(path, meta, (*layout.frame_columns, *declared, *self._extra_columns),
                         fsync_every=fsync_every, overwrite=overwrite)
        self.layout = layout
        self._last_t: float | None = None
        self._last_joint_t: dict[str, float] = {}
        self._layers: frozenset[str] | None = None  # the image folders of frame 0

    def _check_image(self, camera: str, kind: ImageKind, image: Any) -> np.ndarray:
        cam = self.meta.cameras[camera]
        image = np.asarray(image)
        dtypes = {RGB.folder: (np.uint8,), DEPTH.folder: (np.float32, np.float64, np.uint16),
                  MASK.folder: (np.uint8,)}[kind.folder]
        shape = (cam.height, cam.width) + ((3,) if kind is RGB else ())
        if image.shape != shape or not any(image.dtype == d for d in dtypes):
            want = " or ".join(np.dtype(d).name for d in dtypes)
            raise ValueError(f"add_frame: {kind.folder} of camera {camera!r} must be {shape} {want} "
                             f"({cam.width}x{cam.height}); got {image.shape} {image.dtype}")
        return image

    def encode_frame(self, rgb: Mapping[str, np.ndarray], depth: Mapping[str, np.ndarray] | None = None,
                     masks: Mapping[str, np.ndarray] | None = None) -> dict[str, bytes]:
        """Check and encode one frame's images (arguments as in :meth:`add_frame`), keyed by
        folder (``rgb/cam_high``); touches no file, so other threads may encode in parallel."""
        _exactly("add_frame: rgb", rgb, self.meta.cameras)
        encoded: dict[str, bytes] = {}
        for kind, given in ((RGB, rgb), (DEPTH, depth or {}), (MASK, masks or {})):
            for camera, image in given.items():
                if camera not in self.meta.cameras:
                    raise ValueError(f"add_frame: {kind.folder}: no camera {camera!r}; cameras: {list(self.meta.cameras)}")
                image = self._check_image(camera, kind, image)
                if kind is DEPTH:
                    if self.meta.depth_scale is None:
                        raise ValueError("add_frame: depth given but the writer has no depth_scale (metres per unit)")
                    if image.dtype != np.uint16:
                        image = depth_to_raw(image, self.meta.depth_scale)
                folder = self.layout.camera(camera).folder(kind)
                encoded[folder] = encode_image(self._suffixes[kind.folder], image, rgb=kind is RGB)
        return encoded

    def add_frame(self, t: float, arms: Mapping[str, Any], rgb: Mapping[str, np.ndarray], *,
                  depth: Mapping[str, np.ndarray] | None = None, masks: Mapping[str, np.ndarray] | None = None,
                  actions: Mapping[str, Any] | None = None, camera_t: Mapping[str, float] | None = None,
                  extra: Mapping[str, float] | None = None, encoded: Mapping[str, bytes] | None = None) -> int:
        """Write one frame: every camera's images first, then its ``frames.csv`` row. Returns its index.

        Args:
            t: seconds on the episode clock, strictly after the previous frame's.
            arms: arm name -> (7,) ``q1..q6`` (rad) and gripper (m), for every arm.
            rgb: camera name -> (H, W, 3) uint8 RGB, for every camera.
            depth: camera name -> (H, W) float metres or uint16 raw units, for the cameras with depth.
            masks: camera name -> (H, W) uint8 labels, for the cameras with masks.
            actions: arm name -> (7,) ``a1..a6, a_gripper``, for every arm (with ``actions=True``).
            camera_t: camera name -> its own frame time (s), for the declared ``camera_times``.
            extra: values of the declared ``extra_frame_columns``.
            encoded: what :meth:`encode_frame` returned for these images (written as given), or None.
        """
        self._check_open("add_frame")
        t = _finite("add_frame: t", t)
        if self._last_t is not None and not t > self._last_t:
            raise ValueError(f"add_frame: t={t!r} must be after the previous frame's t={self._last_t!r}")
        _exactly("add_frame: arms", arms, self.meta.arms)
        values: list[float | int] = [self._frame_count, t]
        for arm in self.meta.arms:
            values += _state(f"add_frame: arms[{arm!r}]", arms[arm]).tolist()
        if self._actions:
            _exactly("add_frame: actions", actions or {}, self.meta.arms)
            for arm in self.meta.arms:
                values += _state(f"add_frame: actions[{arm!r}]", actions[arm]).tolist()
        elif actions:
            raise ValueError("add_frame: actions given but the writer was made without actions=True")
        _exactly("add_frame: camera_t", camera_t or {}, self._camera_times)
        values += [_finite(f"add_frame: camera_t[{c!r}]", camera_t[c]) for c in self._camera_times]
        values += _extra_values("add_frame", extra, self._extra_columns)
        if encoded is None:
            encoded = self.encode_frame(rgb, depth, masks)
        layers = frozenset(encoded)
        if self._layers is not None and layers != self._layers:
            raise ValueError(f"add_frame: frame 0 had the images {sorted(self._layers)}, this frame has "
                             f"{sorted(layers)}; every frame must carry the same images")
        index = self._frame_count
        for folder, data in encoded.items():
            self._write_bytes(folder, image_name(index, self._suffixes[folder.split("/")[0]]), data)
        self._write_frame_row(values)
        self._layers = layers
        self._last_t = t
        return index

    def add_joint_sample(self, arm: str, t: float, q: Any, gripper: float,
                         extra: Mapping[str, float] | None = None) -> None:
        """Append one feedback sample of ``arm`` to ``joints_<arm>.csv`` (created by its first sample).

        Args:
            arm: the arm's name.
            t: seconds on the episode clock, strictly increasing per arm.
            q: (6,) joint angles in radians.
            gripper: finger-pad gap in metres.
            extra: values of the declared ``joint_columns``.
        """
        self._check_open("add_joint_sample")
        if arm not in self.meta.arms:
            raise ValueError(f"add_joint_sample: no arm {arm!r}; arms: {list(self.meta.arms)}")
        t = _finite("add_joint_sample: t", t)
        last = self._last_joint_t.get(arm)
        if last is not None and not t > last:
            raise ValueError(f"add_joint_sample: {arm}: t={t!r} must be after the previous sample's t={last!r}")
        state = _state("add_joint_sample: q, gripper", [*np.asarray(q, dtype=np.float64).reshape(-1), gripper])
        extras = _extra_values("add_joint_sample", extra, self._joint_columns)
        self._write_joint_row(self.layout.arm(arm).joints_file, JOINT_COLUMNS + self._joint_columns,
                              [t, *state.tolist(), *extras])
        self._last_joint_t[arm] = t

