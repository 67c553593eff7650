"""``manisplat-view PATH --video OUT.mp4``: the demonstrations replayed as an H.264 video (PyAV), no
browser needed. With a twin: its render from the episode's camera (or an orbit around the scene)
beside the recorded image where there is one; for an episode alone: its recorded images (every
camera's side by side under their names when it has several)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterator

import av
import cv2
import numpy as np
from tqdm import tqdm

from manisplat.render.sheets import labelled_sheet
from manisplat.view.content import Demo, ViewContent

log = logging.getLogger(__name__)
SIDE_BY_SIDE = ("recorded", "twin")


@dataclass(frozen=True)
class VideoResult:
    """``frames`` written to ``path`` in ``seconds`` (``frames_per_s``), ``width`` x ``height``."""

    path: Path
    frames: int
    seconds: float
    width: int
    height: int

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")


def orbit_pose(T_base_cam: np.ndarray, target: np.ndarray, angle: float) -> np.ndarray:
    """[4, 4] the camera ``T_base_cam`` turned by ``angle`` rad about the vertical axis through ``target``."""
    c, s = np.cos(angle), np.sin(angle)
    turn = np.eye(4)
    turn[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    to_target, back = np.eye(4), np.eye(4)
    to_target[:3, 3], back[:3, 3] = -target, target
    return back @ turn @ to_target @ T_base_cam


def camera_sheet(demo: Demo, i: int, cameras: list[str]) -> np.ndarray:
    """[H', W', 3] uint8: frame ``i`` of every camera of ``demo``'s episode side by side, each scaled
    to the first one's height and padded white to the widest, under a header naming them and the frame."""
    images = [demo.episode.rgb(i, name) for name in cameras]
    height = images[0].shape[0]
    scaled = [image if image.shape[0] == height else
              cv2.resize(image, (round(image.shape[1] * height / image.shape[0]), height), interpolation=cv2.INTER_AREA)
              for image in images]
    width = max(image.shape[1] for image in scaled)
    panels = [np.pad(image, ((0, 0), (0, width - image.shape[1]), (0, 0)), constant_values=255) for image in scaled]
    return labelled_sheet(np.concatenate(panels, axis=1), tuple(cameras), f"frame {i}  t = {demo.t[i]:.2f} s")


def _frames(content: ViewContent, orbit_deg: float) -> Iterator[np.ndarray]:
    """Each video frame: an episode's recorded image (its cameras' side by side when it has several);
    a reconstruction's [recorded | twin] under a header naming the halves and the frame (the twin
    alone without its episode); an augmentation folder's twin view of every demonstration (augmented
    episodes hold the twin's renders already); with an orbit, the twin from the turning camera."""
    twin, cameras = content.twin, list(content.cameras)
    total = sum(len(d) for d in content.demos)
    shown = 0
    for demo in content.demos:
        target = np.concatenate(list(content.tcp_paths(demo).values())).mean(axis=0) if orbit_deg else None
        for i in range(len(demo)):
            if twin is None:
                image = demo.episode.rgb(i, cameras[0]) if len(cameras) == 1 else camera_sheet(demo, i, cameras)
            elif orbit_deg:
                T = orbit_pose(twin.T_base_cam, target, np.deg2rad(orbit_deg) * shown / max(1, total - 1))
                image = content.twin_render(demo, i, T_base_cam=T)
            elif demo.episode is not None and demo.episode.meta.source == "augmentation":  # twin renders already
                image = demo.episode.rgb(i)
            else:
                image = content.twin_render(demo, i)
                if content.kind == "reconstruction" and demo.episode is not None:
                    image = labelled_sheet(np.concatenate([demo.episode.rgb(i), image], axis=1), SIDE_BY_SIDE,
                                           f"frame {i}  t = {demo.t[i]:.2f} s")
            shown += 1
            yield image


def write_video(content: ViewContent, out: str | Path, *, orbit_deg: float = 0.0, crf: int = 20,
                progress: bool = False) -> VideoResult:
    """Write every demonstration of ``content``, one after another, to ``out`` (H.264, yuv420p, at the
    first demonstration's frame rate).

    Args:
        content: what :func:`manisplat.view.content.load_content` read.
        out: the .mp4 to write (through ``out.partial.mp4``, renamed when complete).
        orbit_deg: with a twin, turn the camera this many degrees about the scene over the video
            (0: the episode's own camera, with the recorded image beside the render).
        crf: H.264 quality (lower is better).
        progress: show a tqdm progress bar.
    """
    out = Path(out)
    if orbit_deg and content.twin is None:
        raise ValueError("--orbit needs a twin to render from new viewpoints; PATH is an episode alone")
    rate = Fraction(content.demos[0].fps).limit_denominator(1001)
    partial = out.with_name(out.stem + ".partial.mp4")
    total = sum(len(d) for d in content.demos)
    start = time.perf_counter()
    frames, size = 0, (0, 0)
    try:
        with av.open(str(partial), "w") as container, \
                tqdm(total=total, desc="video", unit="frame", disable=not progress) as bar:
            stream = None
            for image in _frames(content, orbit_deg):
                height, width = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2  # yuv420p: even sizes
                if stream is None:
                    stream = container.add_stream("h264", rate=rate, options={"crf": str(crf)})
                    stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
                    size = (width, height)
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image[:height, :width]), format="rgb24")
                for packet in stream.encode(frame):
                    container.mux(packet)
                frames += 1
                bar.update(1)
            if stream is not None:
                for packet in stream.encode():
                    container.mux(packet)
        partial.replace(out)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return VideoResult(out, frames, time.perf_counter() - start, *size)
