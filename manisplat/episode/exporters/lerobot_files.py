"""The files of a LeRobot v3.0 dataset as they grow: one continuous video stream per camera file and
parquet row groups per data file, each series moving to the next ``chunk-CCC/file-FFF`` when the
next episode would push the open file past its size limit (as LeRobot's writer decides)."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

log = logging.getLogger(__name__)

CHUNKS_SIZE = 1000
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"


@dataclass
class FileIndex:
    """``chunk-CCC/file-FFF`` of a file series; ``advance`` moves to the next (1000 files per chunk)."""

    chunk: int = 0
    file: int = 0

    def advance(self) -> None:
        self.file += 1
        if self.file == CHUNKS_SIZE:
            self.chunk, self.file = self.chunk + 1, 0


def _codec_options(codec: str, crf: int, gop: int) -> dict[str, str]:
    options = {"g": str(gop), "crf": str(crf)}
    if codec == "libsvtav1":
        options["preset"] = "12"  # LeRobot's choice: its fastest SVT-AV1 preset
    if codec == "hevc":
        options["x265-params"] = "log-level=error"
    return options


class VideoSeries:
    """One camera's video files: a continuous stream per file, frame n at pts n (time base 1/fps).

    Packets reach the file in frame order. AV1 from SVT-AV1 has one packet (a temporal unit) per
    frame with dts = pts = the frame's index, but SVT-AV1 4.1 rarely hands a key frame's packet
    over ahead of its predecessors (seen: frame 148 right after 122), which the MP4 muxer refuses
    ("non monotonically increasing dts"); such a packet waits here for its turn. Other encoders'
    packets go to the file as they come. Closing a file checks that every frame's packet reached it."""

    def __init__(self, root: Path, key: str, codec: str, fps: int, width: int, height: int, crf: int, gop: int,
                 limit_bytes: float) -> None:
        self.root, self.key, self.codec, self.fps = root, key, codec, fps
        self.width, self.height, self.crf, self.gop, self.limit = width, height, crf, gop, limit_bytes
        self.index = FileIndex()
        self.files = 0
        self._container: Any = None
        self._stream: Any = None
        self._in_frame_order = codec == "libsvtav1"
        self._waiting: dict[int, Any] = {}  # frame index -> packet handed over ahead of its turn
        self.frames = 0  # frames in the open file
        self.packets = 0  # packets muxed into the open file
        self.bytes = 0  # bytes muxed into the open file

    def _path(self) -> Path:
        return self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.index.chunk,
                                             file_index=self.index.file)

    def _open(self) -> None:
        path = self._path()
        path.parent.mkdir(parents=True, exist_ok=True)
        os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its configuration to stderr otherwise
        self._container = av.open(str(path), "w")
        stream = self._container.add_stream(self.codec, rate=self.fps,
                                            options=_codec_options(self.codec, self.crf, self.gop))
        stream.width, stream.height, stream.pix_fmt = self.width, self.height, "yuv420p"
        stream.time_base = Fraction(1, self.fps)
        self._stream = stream
        self.frames = self.packets = self.bytes = 0
        self._waiting = {}
        self.files += 1

    def _mux(self, packets: list[Any]) -> None:
        for packet in packets:
            if not self._in_frame_order:
                self._write(packet)
                continue
            if packet.dts != packet.pts or not self.packets <= packet.dts < self.frames \
                    or packet.dts in self._waiting:
                raise RuntimeError(f"{self.codec} returned a packet with pts {packet.pts}, dts {packet.dts} while "
                                   f"frame {self.packets} of {self.frames} was next: not one packet per frame in "
                                   "frame order (an encoder this exporter does not know)")
            if packet.dts > self.packets and not self._waiting:
                log.debug("%s handed frame %d over ahead of frame %d: packets wait for their turn",
                          self.codec, packet.dts, self.packets)
            self._waiting[packet.dts] = packet
            while (ready := self._waiting.pop(self.packets, None)) is not None:
                self._write(ready)

    def _write(self, packet: Any) -> None:
        self.bytes += packet.size
        self.packets += 1
        self._container.mux(packet)

    def begin_episode(self, length: int) -> tuple[int, int, float]:
        """Start an episode of ``length`` frames; returns its (chunk, file, from_timestamp)."""
        if self._container is not None and self.frames:
            per_frame = self.bytes / self.frames
            if self.bytes + per_frame * length >= self.limit:
                self.close()
                self.index.advance()
        if self._container is None:
            self._open()
        return self.index.chunk, self.index.file, self.frames / self.fps

    def write(self, rgb: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 RGB frame."""
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts, frame.time_base = self.frames, Fraction(1, self.fps)
        self.frames += 1
        self._mux(self._stream.encode(frame))

    def end_timestamp(self) -> float:
        return self.frames / self.fps

    def close(self) -> None:
        """Flush the encoder and finish the open file (RuntimeError if a frame's packet is missing)."""
        if self._container is not None:
            self._mux(self._stream.encode())
            self._container.close()
            self._container = self._stream = None
            if self.packets != self.frames:
                raise RuntimeError(f"{self.codec} returned {self.packets} packets for the {self.frames} frames "
                                   f"of {self._path()}")


class DataSeries:
    """The data parquet files: rows appended in row groups, a new file when the size limit would pass."""

    def __init__(self, root: Path, schema: pa.Schema, limit_bytes: float) -> None:
        self.root, self.schema, self.limit = root, schema, limit_bytes
        self.index = FileIndex()
        self.files = 0
        self._writer: pq.ParquetWriter | None = None
        self.rows = 0
        self.bytes = 0  # uncompressed Arrow bytes written to the open file (LeRobot's limit is on size)

    def begin_episode(self, length: int) -> tuple[int, int]:
        """Start an episode of ``length`` rows; returns its (chunk, file)."""
        if self._writer is not None and self.rows:
            if self.bytes + self.bytes / self.rows * length >= self.limit:
                self.close()
                self.index.advance()
        if self._writer is None:
            path = self.root / DATA_PATH.format(chunk_index=self.index.chunk, file_index=self.index.file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(path, self.schema, compression="snappy", use_dictionary=True)
            self.rows = self.bytes = 0
            self.files += 1
        return self.index.chunk, self.index.file

    def write(self, table: pa.Table) -> None:
        assert self._writer is not None
        self._writer.write_table(table)
        self.rows += table.num_rows
        self.bytes += table.nbytes

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
