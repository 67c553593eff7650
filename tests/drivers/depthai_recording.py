"""Writes depthai recordings with depthai's own RecordVideo / RecordMessage nodes in a host-only
pipeline (no device): the files a real OAK session records, produced from known frames."""

from __future__ import annotations

import datetime
import threading
import time
from pathlib import Path

import depthai as dai
import numpy as np


class _Source(dai.node.ThreadedHostNode):
    """Sends the given colour (and depth) frames with the given metadata, then signals."""

    def __init__(self) -> None:
        super().__init__()
        self.rgb = self.createOutput()
        self.depth = self.createOutput()
        self.frames: list[tuple[np.ndarray, np.ndarray | None, float, int, int]] = []
        self.done = threading.Event()

    def run(self) -> None:
        for rgb, depth, t, seq, exposure_us in self.frames:
            stamp = datetime.timedelta(seconds=t)
            img = dai.ImgFrame()
            img.setCvFrame(np.ascontiguousarray(rgb[..., ::-1]), dai.ImgFrame.Type.BGR888i)
            img.setSequenceNum(seq)
            img.setTimestamp(stamp)
            settings = img.cam
            settings.exposureTimeUs = exposure_us
            img.cam = settings
            self.rgb.send(img)
            if depth is not None:
                d = dai.ImgFrame()
                d.setFrame(depth)
                d.setType(dai.ImgFrame.Type.RAW16)
                d.setWidth(depth.shape[1])
                d.setHeight(depth.shape[0])
                d.setSequenceNum(seq)
                d.setTimestamp(stamp)
                self.depth.send(d)
            time.sleep(0.005)
        self.done.set()


def write_recording(folder: Path, rgb: np.ndarray, t: np.ndarray, seq: np.ndarray, exposure_us: int,
                    depth_mm: np.ndarray | None = None, fps: int = 30) -> tuple[Path, Path, Path | None]:
    """``(video.mkv, video.mcap, depth.mcap or None)`` holding N frames: ``rgb`` (N, H, W, 3)
    uint8 RGB, timestamps ``t`` (N,) s, sequence numbers ``seq`` (N,), ``depth_mm`` (N, H, W) uint16."""
    video, meta = folder / "rgb.mkv", folder / "rgb.mcap"
    depth_path = folder / "depth.mcap" if depth_mm is not None else None
    with dai.Pipeline(False) as pipeline:
        source = pipeline.create(_Source)
        source.frames = [(rgb[i], None if depth_mm is None else depth_mm[i], float(t[i]), int(seq[i]), exposure_us)
                         for i in range(len(t))]
        record = pipeline.create(dai.node.RecordVideo)
        record.setRecordVideoFile(video)
        record.setRecordMetadataFile(meta)
        record.setFps(fps)
        source.rgb.link(record.input)
        if depth_path is not None:
            record_depth = pipeline.create(dai.node.RecordMessage)
            record_depth.setRecordFile(depth_path)
            source.depth.link(record_depth.input)
        pipeline.start()
        assert source.done.wait(10.0), "the depthai source node did not finish"
        # RecordVideo writes its file only when the pipeline stops and drops what it has not encoded
        # by then, with nothing to wait on: 0.2 s lost all but one frame on a loaded 2-core runner
        time.sleep(2.0)
        pipeline.stop()
    return video, meta, depth_path
