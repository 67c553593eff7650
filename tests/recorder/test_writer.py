"""The writer thread: frames through a bounded queue, joint rows and CAN frames beside them,
complete only at the end; a full queue drops and counts."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from manisplat.episode import CameraInfo, Episode, EpisodeWriter, RobotInfo, validate
from manisplat.recorder.canlog import CanLogSink
from manisplat.recorder.writer import EpisodeSink, FrameItem, StorageError
from tests.recorder.helpers import K


def writer(path: Path, w: int = 64, h: int = 48) -> EpisodeWriter:
    Kw = K.copy()
    Kw[0, 2], Kw[1, 2] = (w - 1) / 2, (h - 1) / 2
    return EpisodeWriter(path, CameraInfo("c", w, h, Kw), RobotInfo(), 30.0, extra_frame_columns=("seq",))


@pytest.mark.parametrize("encode_threads", [0, 3])
def test_frames_and_joints_are_written_and_the_episode_completes_last(tmp_path: Path, encode_threads: int) -> None:
    w = writer(tmp_path / "ep2")
    can_log = CanLogSink()
    can_log.open(tmp_path / "ep2" / "can.asc", 100.0)
    for k in range(7):
        can_log.on_message_received(can.Message(arbitration_id=0x2A5, data=bytes(8), timestamp=100.0 + k * 0.01))
    sink = EpisodeSink(w, [can_log], queue_frames=4, encode_threads=encode_threads)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(9)]
    for i, rgb in enumerate(images):
        for k in range(4):
            sink.put_joint(i / 30 + k * 0.005, np.full(6, 0.1 * i), 0.03)
        while not sink.put_frame(FrameItem(i / 30, np.full(6, 0.1 * i), 0.03, rgb, extra={"seq": float(i)})):
            pass
    assert not Episode.open(tmp_path / "ep2").meta.complete
    sink.finish({"stats": {"note": "test"}})
    ep = Episode.open(tmp_path / "ep2")
    assert ep.meta.complete and ep.meta.frame_count == 9 and ep.meta.extra["stats"] == {"note": "test"}
    assert len(ep.joints()) == 36 and sink.frames_written == 9 and sink.joints_written == 36
    for i, rgb in enumerate(images):
        np.testing.assert_array_equal(ep.rgb(i), rgb)
    assert validate(tmp_path / "ep2").ok
    assert len(list(can.LogReader(tmp_path / "ep2" / "can.asc"))) == 7


def test_a_full_queue_drops_frames_and_counts_them(tmp_path: Path) -> None:
    sink = EpisodeSink(writer(tmp_path / "ep", 640, 480), queue_frames=1)
    rgb = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    accepted = sum(sink.put_frame(FrameItem(i / 30, np.zeros(6), 0.0, rgb, extra={"seq": float(i)}))
                   for i in range(40))
    sink.finish()
    assert sink.frames_dropped > 0 and accepted + sink.frames_dropped == 40
    assert sink.frames_written == accepted == Episode.open(tmp_path / "ep").meta.frame_count


def test_a_frame_that_cannot_be_encoded_stops_the_episode_keeping_the_earlier_ones(tmp_path: Path) -> None:
    sink = EpisodeSink(writer(tmp_path / "ep"), queue_frames=8, encode_threads=2)
    good = np.zeros((48, 64, 3), np.uint8)
    for i in range(3):
        assert sink.put_frame(FrameItem(i / 30, np.zeros(6), 0.0, good, extra={"seq": float(i)}))
    sink.put_frame(FrameItem(3 / 30, np.zeros(6), 0.0, np.zeros((48, 64), np.uint8), extra={"seq": 3.0}))
    with pytest.raises(StorageError, match=r"rgb must be \(48, 64, 3\) uint8.*Kept 3 frames") as exc:
        sink.finish()
    assert "not a storage problem" in str(exc.value)
    assert "free space" not in str(exc.value) and "--recover" not in str(exc.value)  # advice for storage errors only
    ep = Episode.open(tmp_path / "ep")
    assert not ep.meta.complete and len(ep) == 3


class FullDiskWriter(EpisodeWriter):
    """An episode writer on a disk that fills up after two frames."""

    def add_frame(self, *args: Any, **kwargs: Any) -> None:
        if self.frame_count == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path / "rgb" / "000002.png"))
        super().add_frame(*args, **kwargs)


def test_a_full_disk_stops_the_episode_with_advice_to_free_space_and_recover(tmp_path: Path) -> None:
    w = FullDiskWriter(tmp_path / "ep", CameraInfo("c", 64, 48, K), RobotInfo(), 30.0, extra_frame_columns=("seq",))
    sink = EpisodeSink(w, queue_frames=8)
    for i in range(4):
        sink.put_frame(FrameItem(i / 30, np.zeros(6), 0.0, np.zeros((48, 64, 3), np.uint8), extra={"seq": float(i)}))
    with pytest.raises(StorageError, match=r"the disk is full \(.*000002.png\).*Kept 2 frames") as exc:
        sink.finish()
    assert f"free space, then run `manisplat-record --recover {tmp_path / 'ep'}`" in str(exc.value)
    assert len(Episode.open(tmp_path / "ep")) == 2
