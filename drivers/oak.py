"""Luxonis OAK cameras through depthai v3: a live :class:`OakCamera` and a
:class:`DepthaiReplayCamera` for depthai's own recordings, both :class:`~.base.Camera`\\ s.

    >>> with OakCamera(OakConfig(width=640, height=400, fps=30, depth=True)) as cam:
    ...     frame = cam.read()            # .rgb (H, W, 3) RGB, .depth (H, W) m, .t, .seq, .dropped
    ...     K = cam.K                     # (3, 3) at 640 x 400, from the device calibration

Timestamps: depthai stamps a frame on the host's steady clock (``time.monotonic()`` on Linux)
at the end of its exposure; when the frame carries its exposure time, ``CameraFrame.t`` is the
middle of the exposure (``getTimestamp(CameraExposureOffset.MIDDLE)``), else the stamp as is.
Sequence numbers give drop detection (:class:`~.base.SequenceTracker`).

Intrinsics: the device calibration (``readCalibration()``) rescaled to the output size the way
the Camera node resizes: ``"crop"`` (depthai's default, keep the aspect ratio and crop) or
``"stretch"``. Depth (``depth=True``): StereoDepth aligned to the RGB socket, at the RGB size,
paired with the RGB frame by a Sync node; depthai's uint16 millimetres become float32 metres.

Recordings: depthai's host nodes ``RecordVideo`` (RGB, ``.mkv``/``.avi`` + ``.mcap`` metadata
with the original timestamps, sequence numbers and exposure) and ``RecordMessage`` (any message,
e.g. RAW16 depth, ``.mcap``) write files that ``ReplayVideo`` / ``ReplayMessage`` play back in a
pipeline with no device (``dai.Pipeline(False)``), paced at the recorded rate. Note that
``RecordVideo`` loses the last frame when its pipeline stops, and without ``setFps`` it uses the
first 10 frames to estimate the rate and drops 9 of them.

Episodes are replayed by :class:`~manisplat.drivers.replay.EpisodeCamera`.
"""

from __future__ import annotations

import collections
import datetime as _dt
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import depthai as dai
import numpy as np

from manisplat.drivers.base import CameraFrame, DriverError, SequenceTracker
from manisplat.episode.chroma import video_chroma
from manisplat.episode.images import StoredChroma

log = logging.getLogger(__name__)

RESIZE_MODES = {"crop": dai.ImgResizeMode.CROP, "stretch": dai.ImgResizeMode.STRETCH}
DEPTH_UNIT_M = 1e-3  # depthai's default depth unit: millimetres


@dataclass
class OakConfig:
    """Settings of an :class:`OakCamera`.

    Attributes:
        width, height: output size, pixels (depth aligned at the same size; the width should be
            a multiple of 16 for StereoDepth).
        fps: frame rate.
        depth: also stream stereo depth aligned to the RGB camera.
        socket: the RGB camera's board socket name (``CAM_A`` on OAK-D).
        resize: ``"crop"`` or ``"stretch"`` (how the sensor image is resized to the output).
        stereo_preset: a ``dai.node.StereoDepth.PresetMode`` name.
        device: a device id / IP to open (None: the first one found).
        queue_size: host queue length; older frames are dropped (and counted) when full.
    """

    width: int = 640
    height: int = 400
    fps: float = 30.0
    depth: bool = False
    socket: str = "CAM_A"
    resize: str = "crop"
    stereo_preset: str = "DEFAULT"
    device: str | None = None
    queue_size: int = 4

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or not self.fps > 0:
            raise ValueError(f"OakConfig: size {self.width}x{self.height} and fps {self.fps} must be positive")
        if self.resize not in RESIZE_MODES:
            raise ValueError(f"OakConfig.resize: {self.resize!r} not in {sorted(RESIZE_MODES)}")
        if not hasattr(dai.CameraBoardSocket, self.socket):
            raise ValueError(f"OakConfig.socket: {self.socket!r} is no dai.CameraBoardSocket")
        if self.stereo_preset not in dai.node.StereoDepth.PresetMode.__members__:
            raise ValueError(f"OakConfig.stereo_preset: {self.stereo_preset!r} not in "
                             f"{sorted(dai.node.StereoDepth.PresetMode.__members__)}")


def intrinsics_at(calib: dai.CalibrationHandler, socket: str, width: int, height: int,
                  resize: str = "crop") -> tuple[np.ndarray, np.ndarray]:
    """``(K (3, 3), dist (D,))`` float64 of camera ``socket`` at ``width`` x ``height``, from a
    depthai calibration (a device's ``readCalibration()`` or ``dai.CalibrationHandler(json)``)."""
    board = getattr(dai.CameraBoardSocket, socket)
    if resize not in RESIZE_MODES:
        raise ValueError(f"resize {resize!r} not in {sorted(RESIZE_MODES)}")
    try:
        K = np.asarray(calib.getCameraIntrinsics(board, width, height, keepAspectRatio=resize == "crop"),
                       dtype=np.float64)
        dist = np.asarray(calib.getDistortionCoefficients(board), dtype=np.float64)
    except RuntimeError as exc:
        raise DriverError(f"the calibration has no intrinsics for {socket}: {exc}") from exc
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DriverError(f"the calibration gives an unusable K for {socket}: {K.tolist()}")
    return K, _trim_dist(dist)


def _trim_dist(dist: np.ndarray) -> np.ndarray:
    """OpenCV-order coefficients without depthai's trailing zeros (keeps 4, 5, 8, 12 or 14)."""
    for n in (4, 5, 8, 12, 14):
        if len(dist) >= n and not np.any(dist[n:]):
            return dist[:n].copy()
    return dist.copy()


def frame_time(img: dai.ImgFrame) -> tuple[float, float | None]:
    """``(t, exposure)`` in s: the mid-exposure host timestamp when the exposure time is known,
    else depthai's stamp (end of exposure); ``exposure`` None when unknown."""
    exposure = img.getExposureTime().total_seconds()
    if exposure > 0:
        return img.getTimestamp(dai.CameraExposureOffset.MIDDLE).total_seconds(), exposure
    return img.getTimestamp().total_seconds(), None


def rgb_of(img: dai.ImgFrame) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a depthai colour frame."""
    kind = img.getType()
    if kind == dai.ImgFrame.Type.RGB888i:
        return np.ascontiguousarray(img.getFrame())
    if kind in (dai.ImgFrame.Type.BGR888i, dai.ImgFrame.Type.BGR888p, dai.ImgFrame.Type.NV12,
                dai.ImgFrame.Type.YUV420p, dai.ImgFrame.Type.RGB888p):
        return np.ascontiguousarray(img.getCvFrame()[..., ::-1])  # getCvFrame gives BGR
    raise DriverError(f"unsupported colour frame type {kind}")


def depth_of(img: dai.ImgFrame) -> np.ndarray:
    """(H, W) float32 metres of a depthai RAW16 depth frame (0 = no depth)."""
    if img.getType() != dai.ImgFrame.Type.RAW16:
        raise DriverError(f"depth frames must be RAW16 millimetres, got {img.getType()}")
    return img.getFrame().astype(np.float32) * np.float32(DEPTH_UNIT_M)


def camera_frame(img: dai.ImgFrame, depth: dai.ImgFrame | None, tracker: SequenceTracker) -> CameraFrame:
    """A :class:`~.base.CameraFrame` of a depthai colour frame (and its depth frame)."""
    seq = int(img.getSequenceNum())
    t, exposure = frame_time(img)
    return CameraFrame(seq=seq, t=t, rgb=rgb_of(img), depth=None if depth is None else depth_of(depth),
                       exposure_s=exposure, dropped=tracker.update(seq), t_host=time.monotonic())


def _timeout(seconds: float | None) -> _dt.timedelta | None:
    return None if seconds is None else _dt.timedelta(seconds=max(0.0, seconds))


class OakCamera:
    """A live OAK camera (see the module docstring). Raises :class:`~.base.DriverError` when no
    device can be opened."""

    def __init__(self, config: OakConfig | None = None) -> None:
        self.config = cfg = config if config is not None else OakConfig()
        if cfg.device is None and not dai.Device.getAllAvailableDevices():  # 0.5 s, not the 10 s boot timeout
            raise DriverError("no OAK device found (USB or network); check the cable, power and udev rules")
        try:
            self._device = dai.Device(dai.DeviceInfo(cfg.device)) if cfg.device else dai.Device()
        except RuntimeError as exc:
            found = [d.getDeviceId() for d in dai.Device.getAllAvailableDevices()]
            raise DriverError(f"cannot open an OAK device{f' {cfg.device!r}' if cfg.device else ''}: {exc} "
                              f"(devices found: {found or 'none'})") from exc
        socket = getattr(dai.CameraBoardSocket, cfg.socket)
        self.width, self.height = cfg.width, cfg.height
        self.K, self.dist = intrinsics_at(self._device.readCalibration(), cfg.socket, cfg.width, cfg.height, cfg.resize)
        # the ISP's frames are YUV 4:2:0 before they are resized to the output and converted; how
        # that colour grid maps onto the output's pixels is not known here
        self.chroma_subsampling: StoredChroma | None = None
        self.tracker = SequenceTracker()
        self._pipeline = dai.Pipeline(self._device)
        cam = self._pipeline.create(dai.node.Camera).build(socket)
        rgb = cam.requestOutput((cfg.width, cfg.height), type=dai.ImgFrame.Type.BGR888i,
                                resizeMode=RESIZE_MODES[cfg.resize], fps=cfg.fps)
        if cfg.depth:
            preset = dai.node.StereoDepth.PresetMode.__members__[cfg.stereo_preset]
            stereo = self._pipeline.create(dai.node.StereoDepth).build(autoCreateCameras=True, presetMode=preset,
                                                                       fps=cfg.fps)
            stereo.setDepthAlign(socket)
            stereo.setOutputSize(cfg.width, cfg.height)
            sync = self._pipeline.create(dai.node.Sync)
            sync.setSyncThreshold(_dt.timedelta(seconds=0.5 / cfg.fps))
            rgb.link(sync.inputs["rgb"])
            stereo.depth.link(sync.inputs["depth"])
            self._queue = sync.out.createOutputQueue(maxSize=cfg.queue_size, blocking=False)
        else:
            self._queue = rgb.createOutputQueue(maxSize=cfg.queue_size, blocking=False)
        self._pipeline.start()
        log.info("OakCamera: %s %dx%d @ %g fps%s", self._device.getDeviceId(), cfg.width, cfg.height, cfg.fps,
                 " with aligned depth" if cfg.depth else "")

    def read(self, timeout: float | None = 1.0) -> CameraFrame | None:
        """The next frame (TimeoutError when none comes within ``timeout`` s)."""
        try:
            msg = self._queue.get() if timeout is None else self._queue.get(_timeout(timeout))
        except dai.MessageQueue.QueueException as exc:
            raise DriverError(f"OAK pipeline stopped: {exc}") from exc
        if msg is None:
            raise TimeoutError(f"no OAK frame within {timeout} s")
        if isinstance(msg, dai.MessageGroup):
            return camera_frame(msg["rgb"], msg["depth"], self.tracker)
        return camera_frame(msg, None, self.tracker)

    def close(self) -> None:
        if self._pipeline.isRunning():
            self._pipeline.stop()
        self._device.close()

    def __enter__(self) -> OakCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Drain:
    """Every message a depthai output sends, kept in order. A replay node that reaches its end
    stops its pipeline, and a stopped pipeline's queue refuses the messages still in it, so they
    are taken by a callback as they are sent."""

    def __init__(self, pipeline: dai.Pipeline, output: dai.Node.Output) -> None:
        self._pipeline = pipeline
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._queue = output.createOutputQueue(maxSize=1, blocking=False)
        self._queue.addCallback(self._add)

    def _add(self, msg: dai.ADatatype) -> None:
        with self._cond:
            self._items.append(msg)
            self._cond.notify_all()

    def head(self, timeout: float | None) -> dai.ADatatype | None:
        """The next message, left in place; None once the pipeline has stopped and every message
        was taken; TimeoutError when none comes within ``timeout`` s."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._items:
                if not self._pipeline.isRunning():
                    return None
                remaining = 0.05 if deadline is None else deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no replayed message within {timeout} s")
                self._cond.wait(min(0.05, remaining))
            return self._items[0]

    def get(self, timeout: float | None) -> dai.ADatatype | None:
        """The next message, taken (see :meth:`head`)."""
        msg = self.head(timeout)
        if msg is not None:
            with self._cond:
                self._items.popleft()
        return msg


class DepthaiReplayCamera:
    """Plays depthai's own recordings with their original timestamps and sequence numbers, with
    no device: ``video`` (RecordVideo's ``.mkv``/``.avi``/``.mp4``) and its ``.mcap`` metadata
    (default: beside the video), optionally ``depth`` (a RecordMessage ``.mcap`` of RAW16 depth).
    depthai's replay nodes send frames at the recorded rate; frames not read yet are buffered.

    Intrinsics come from ``calibration`` (a depthai calibration JSON, e.g. written by
    ``eepromToJsonFile``, or a ``dai.CalibrationHandler``) at the recording's size, or from an
    explicit ``K`` (and ``dist``).
    """

    def __init__(self, video: str | Path, metadata: str | Path | None = None, *, depth: str | Path | None = None,
                 calibration: str | Path | dai.CalibrationHandler | None = None, K: np.ndarray | None = None,
                 dist: np.ndarray | None = None, socket: str = "CAM_A", resize: str = "crop",
                 first_frame_timeout: float = 10.0) -> None:
        self.video = Path(video)
        self.metadata = Path(metadata) if metadata is not None else self.video.with_suffix(".mcap")
        for path, what in ((self.video, "video"), (self.metadata, "metadata (original timestamps)")):
            if not path.is_file():
                raise DriverError(f"depthai recording {what} {path} not found")
        if depth is not None and not Path(depth).is_file():
            raise DriverError(f"depthai depth recording {depth} not found")
        if (calibration is None) == (K is None):
            raise DriverError("DepthaiReplayCamera needs exactly one of calibration= or K=")
        self.tracker = SequenceTracker()
        self.frames_without_depth = 0
        # One pipeline per file: a replay node that reaches its end stops its whole pipeline.
        self._pipelines: list[dai.Pipeline] = [dai.Pipeline(False)]
        replay = self._pipelines[0].create(dai.node.ReplayVideo)
        replay.setReplayVideoFile(self.video)
        replay.setReplayMetadataFile(self.metadata)
        replay.setOutFrameType(dai.ImgFrame.Type.BGR888i)
        replay.setLoop(False)
        self._frames = _Drain(self._pipelines[0], replay.out)
        self._depth: _Drain | None = None
        if depth is not None:
            self._pipelines.append(dai.Pipeline(False))
            replay_depth = self._pipelines[1].create(dai.node.ReplayMessage)
            replay_depth.setReplayFile(Path(depth))
            replay_depth.setLoop(False)
            self._depth = _Drain(self._pipelines[1], replay_depth.out)
        for pipeline in self._pipelines:
            pipeline.start()
        self._first = self._frames.get(first_frame_timeout)
        if self._first is None:
            self.close()
            raise DriverError(f"{self.video}: the recording holds no frames")
        self.width, self.height = self._first.getWidth(), self._first.getHeight()
        self.chroma_subsampling = video_chroma(self.video)
        if K is not None:
            self.K = np.asarray(K, dtype=np.float64)
            if self.K.shape != (3, 3):
                raise DriverError(f"K must be (3, 3), got {self.K.shape}")
            self.dist = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
        else:
            handler = calibration if isinstance(calibration, dai.CalibrationHandler) else \
                dai.CalibrationHandler(str(calibration))
            self.K, self.dist = intrinsics_at(handler, socket, self.width, self.height, resize)

    def _depth_for(self, img: dai.ImgFrame, timeout: float | None) -> dai.ImgFrame | None:
        """The depth frame stamped like ``img``, skipping older ones; None (counted in
        ``frames_without_depth``) when there is none."""
        if self._depth is None:
            return None
        t = img.getTimestamp()
        while (head := self._depth.head(timeout)) is not None:
            if head.getTimestamp() < t:
                self._depth.get(0)  # an older depth frame whose colour frame was not recorded
                continue
            if head.getTimestamp() == t:
                return self._depth.get(0)
            break  # the next depth frame belongs to a later colour frame
        self.frames_without_depth += 1
        if self.frames_without_depth == 1:
            log.warning("DepthaiReplayCamera: frame %d (t=%s) has no depth frame", img.getSequenceNum(), t)
        return None

    def read(self, timeout: float | None = 5.0) -> CameraFrame | None:
        """The next frame, None after the last one."""
        if self._first is not None:
            img, self._first = self._first, None
        else:
            img = self._frames.get(timeout)
        if img is None:
            return None
        return camera_frame(img, self._depth_for(img, timeout), self.tracker)

    def close(self) -> None:
        for pipeline in self._pipelines:
            if pipeline.isRunning():
                pipeline.stop()

    def __enter__(self) -> DepthaiReplayCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
