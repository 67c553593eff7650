"""A dataset's video file gets every frame, in frame order, even when SVT-AV1 hands a key frame's
packet over ahead of its predecessors (as SVT-AV1 4.1 was seen to do, rarely: frame 148 came right
after 122 and the MP4 muxer refused it); a frame whose packet never comes is an error naming the
file, not a shorter video."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest

from manisplat.episode.exporters import lerobot_files
from manisplat.episode.exporters.lerobot_files import VideoSeries

FRAMES, WIDTH, HEIGHT = 40, 64, 48


class ReorderingStream:
    """The encoder's stream, handing the packets of frames ``first``..``ahead - 1`` over only after
    frame ``ahead``'s (the order SVT-AV1 4.1 was seen to produce); ``drop`` frames are never handed over."""

    def __init__(self, stream: Any, first: int, ahead: int, drop: tuple[int, ...] = ()) -> None:
        self.stream, self.first, self.ahead, self.drop = stream, first, ahead, drop
        self.held: list[Any] = []
        self.order: list[int] = []

    def encode(self, frame: Any = None) -> list[Any]:
        out = []
        for packet in self.stream.encode(frame):
            if packet.pts in self.drop:
                continue
            if self.first <= packet.pts < self.ahead:
                self.held.append(packet)
            elif packet.pts == self.ahead:
                out += [packet, *self.held]
                self.held = []
            else:
                out.append(packet)
        self.order += [int(p.pts) for p in out]
        return out


def gray(k: int) -> np.ndarray:
    """Frame ``k``: a uniform gray level that tells the frames apart after encoding."""
    return np.full((HEIGHT, WIDTH, 3), 40 + 4 * k, dtype=np.uint8)


def write_file(root: Path, monkeypatch, **reorder: Any) -> tuple[Path, list[int]]:
    streams: list[ReorderingStream] = []
    original_open = VideoSeries._open

    def open_reordering(self: VideoSeries) -> None:
        original_open(self)
        self._stream = ReorderingStream(self._stream, **reorder)
        streams.append(self._stream)

    monkeypatch.setattr(lerobot_files.VideoSeries, "_open", open_reordering)
    series = VideoSeries(root, "observation.images.ego", "libsvtav1", 30, WIDTH, HEIGHT, 30, 2, 200e6)
    series.begin_episode(FRAMES)
    for k in range(FRAMES):
        series.write(gray(k))
    series.close()
    return root / "videos/observation.images.ego/chunk-000/file-000.mp4", streams[0].order


def test_a_key_frame_handed_over_early_waits_for_its_turn(tmp_path, monkeypatch):
    path, order = write_file(tmp_path, monkeypatch, first=11, ahead=20)
    assert order.index(20) < order.index(11)  # the encoder's order really was out of frame order
    with av.open(str(path)) as container:
        levels = [frame.to_ndarray(format="rgb24").mean() for frame in container.decode(video=0)]
    assert len(levels) == FRAMES
    # every frame decodes to its own gray level (AV1 at crf 30 keeps a flat gray within ~2 levels)
    np.testing.assert_allclose(levels, [gray(k).mean() for k in range(FRAMES)], atol=2.0)


def test_a_frame_whose_packet_never_comes_is_an_error_naming_the_file(tmp_path, monkeypatch):
    with pytest.raises(RuntimeError, match=r"libsvtav1 returned 10 packets for the 40 frames of .*file-000\.mp4"):
        write_file(tmp_path, monkeypatch, first=0, ahead=0, drop=(10,))
