"""Per-frame image files (``rgb/``, ``depth/``, ``masks/``): naming, full decoding with checks,
encoding, depth unit conversion, and the chroma subsampling a JPEG stream was stored with.
Arrays in memory are RGB; files hold BGR (OpenCV)."""

from __future__ import annotations

import contextlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, NamedTuple

import cv2
import numpy as np

from manisplat.episode.format import CHROMA_SUBSAMPLING, DEPTH_DIR, MASKS_DIR, RGB_DIR, EpisodeFormatError, image_name

_IMAGE_RE = re.compile(r"^(\d{6})(\.png|\.jpg)$")
_DEPTH_MAX = np.iinfo(np.uint16).max


class StoredChroma(NamedTuple):
    """How a camera's images kept their colour when they were encoded.

    Attributes:
        scheme: a key of :data:`CHROMA_SUBSAMPLING` (``"4:2:0"``: one colour sample per 2 x 2 pixels).
        red_blue_swapped: the encoder took the images' red for blue (``cv2.imencode`` of an RGB
            array, as ACT and Cobot Magic recorders store their frames), so its brightness, kept
            at every pixel, weighed the channels the other way round.
    """

    scheme: str
    red_blue_swapped: bool = False

    @property
    def block(self) -> tuple[int, int]:
        """The pixels (horizontal, vertical) one colour sample covers."""
        return CHROMA_SUBSAMPLING[self.scheme]


def describe_chroma(stored: StoredChroma | None) -> str:
    """``stored`` in words for logs: ``"4:2:0"``, ``"4:2:0 (red and blue swapped)"``, ``"not known"``."""
    if stored is None:
        return "not known"
    return stored.scheme + (" (red and blue swapped)" if stored.red_blue_swapped else "")


CHROMA_KEYS = ("chroma_subsampling", "chroma_red_blue_swapped")
"""A camera's keys in ``episode.json`` saying how its images kept their colour."""


def chroma_keys(stored: StoredChroma | None) -> dict[str, Any]:
    """``stored`` as a camera's ``episode.json`` keys (none where it is not known)."""
    return {} if stored is None else dict(zip(CHROMA_KEYS, (stored.scheme, stored.red_blue_swapped)))


#: JPEG start-of-frame markers (every coding process: baseline, progressive, lossless, arithmetic)
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


@dataclass(frozen=True)
class ImageKind:
    """What the files of one image folder must be.

    Attributes:
        folder: folder name inside the episode.
        channels: 3 (colour) or 1.
        dtype: pixel type in the file.
        suffixes: allowed file suffixes.
    """

    folder: str
    channels: int
    dtype: np.dtype
    suffixes: tuple[str, ...]

    def describe(self) -> str:
        return f"{self.channels}-channel {8 * np.dtype(self.dtype).itemsize}-bit"


RGB = ImageKind(RGB_DIR, 3, np.dtype(np.uint8), (".png", ".jpg"))
DEPTH = ImageKind(DEPTH_DIR, 1, np.dtype(np.uint16), (".png",))
MASK = ImageKind(MASKS_DIR, 1, np.dtype(np.uint8), (".png",))
KINDS = (RGB, DEPTH, MASK)


def list_images(folder: Path) -> tuple[dict[int, list[str]], list[str]]:
    """``(index -> file names, other file names)`` of ``folder`` (empty when it does not exist)."""
    by_index: dict[int, list[str]] = {}
    others: list[str] = []
    if not folder.is_dir():
        return by_index, others
    for name in sorted(p.name for p in folder.iterdir()):
        m = _IMAGE_RE.match(name)
        if m:
            by_index.setdefault(int(m.group(1)), []).append(name)
        else:
            others.append(name)
    return by_index, others


def has_images(folder: Path) -> bool:
    """Whether ``folder`` holds at least one frame image (an episode "has depth" when ``depth/`` does)."""
    return bool(list_images(folder)[0])


def find_image(folder: Path, index: int) -> Path | None:
    """The file of frame ``index`` in ``folder`` (``.png`` first, then ``.jpg``), or None."""
    for suffix in RGB.suffixes:
        path = folder / image_name(index, suffix)
        if path.is_file():
            return path
    return None


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's own warnings (a truncated file is reported by us, once)."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def decode_image(path: Path) -> np.ndarray | None:
    """Fully decode an image file as stored (BGR for colour), or None when it is unreadable,
    truncated or corrupt. OpenCV's PNG and JPEG decoders reject a file cut anywhere short."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError:
        return None
    if data.size == 0:
        return None
    with _quiet_opencv():
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)


def image_problem(image: np.ndarray, kind: ImageKind, width: int | None, height: int | None) -> str | None:
    """Why a decoded image does not fit ``kind`` and the camera size, or None."""
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels != kind.channels or image.dtype != kind.dtype:
        got = f"{channels}-channel {8 * image.dtype.itemsize}-bit"
        return f"must be {kind.describe()} ({kind.folder}); got {got}"
    if width is not None and height is not None and image.shape[:2] != (height, width):
        return f"size {image.shape[1]}x{image.shape[0]} does not match the camera's {width}x{height}"
    return None


def load_image(path: Path, kind: ImageKind, width: int, height: int) -> np.ndarray:
    """Decode and check one frame image; colour images come back RGB.

    Returns (H, W, 3) uint8 for ``RGB``, (H, W) uint16 for ``DEPTH``, (H, W) uint8 for ``MASK``.
    Raises :class:`EpisodeFormatError` naming the file when it is missing, undecodable or wrong.
    """
    if not path.is_file():
        raise EpisodeFormatError(f"{path}: missing")
    image = decode_image(path)
    if image is None:
        raise EpisodeFormatError(f"{path}: cannot decode (truncated or corrupt)")
    problem = image_problem(image, kind, width, height)
    if problem:
        raise EpisodeFormatError(f"{path}: {problem}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if kind.channels == 3 else image


def encode_image(suffix: str, image: np.ndarray, *, rgb: bool) -> bytes:
    """``image`` encoded as ``suffix`` (".png", ".jpg"). ``rgb`` marks a (H, W, 3) RGB array,
    stored BGR as OpenCV expects. OpenCV releases the GIL while encoding: threads run in parallel."""
    if rgb:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode(suffix, image)
    if not ok:
        raise OSError(f"OpenCV could not encode a {image.shape} {image.dtype} image as {suffix}")
    return data.tobytes()


def jpeg_chroma_subsampling(data: bytes) -> str | None:
    """The chroma subsampling (a key of :data:`CHROMA_SUBSAMPLING`) a JPEG stream ``data`` was
    encoded with, read from its frame header; None for a one-channel (grey) image.

    Raises:
        ValueError: ``data`` is not a JPEG stream, has no frame header before its scan, or
            subsamples its chroma in a way :data:`CHROMA_SUBSAMPLING` does not name.
    """
    data = bytes(data)
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG stream (no start-of-image marker)")
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            raise ValueError(f"corrupt JPEG header: no marker at byte {at}")
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            at += 2
            continue
        length = int.from_bytes(data[at + 2:at + 4], "big")
        if marker in _SOF_MARKERS:
            return _subsampling_of(data[at + 4:at + 2 + length])
        if marker == 0xDA:
            break
        at += 2 + length
    raise ValueError("no JPEG frame header before the image data")


def _subsampling_of(header: bytes) -> str | None:
    """The scheme of a JPEG frame header's body (precision, height, width, then per component
    its id, sampling factors H << 4 | V and quantisation table)."""
    n = header[5] if len(header) > 5 else 0
    if n == 1:
        return None
    if n != 3 or len(header) < 6 + 3 * n:
        raise ValueError(f"a JPEG with {n} components; expected 3 (YCbCr) or 1 (grey)")
    factors = [(header[7 + 3 * k] >> 4, header[7 + 3 * k] & 0x0F) for k in range(3)]
    (hy, vy), chroma = factors[0], factors[1:]
    if chroma[0] != chroma[1] or 0 in (hy, vy, *chroma[0]) or hy % chroma[0][0] or vy % chroma[0][1]:
        raise ValueError(f"JPEG sampling factors {factors} (Y, Cb, Cr) are not a chroma subsampling this reads")
    block = (hy // chroma[0][0], vy // chroma[0][1])
    for scheme, b in CHROMA_SUBSAMPLING.items():
        if b == block:
            return scheme
    raise ValueError(f"JPEG chroma blocks of {block[0]}x{block[1]} pixels are not one of {', '.join(CHROMA_SUBSAMPLING)}")


def depth_to_raw(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metric depth (H, W) float -> stored (H, W) uint16: ``round(depth / depth_scale)``.

    Non-finite and non-positive values become 0 (invalid); values beyond the range clip to 65535.
    """
    depth_m = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(depth_m) & (depth_m > 0)
    raw = np.zeros(depth_m.shape, dtype=np.float64)
    raw[valid] = np.rint(depth_m[valid] / depth_scale)
    return np.clip(raw, 0, _DEPTH_MAX).astype(np.uint16)


def raw_to_depth(raw: np.ndarray, depth_scale: float) -> np.ndarray:
    """Stored (H, W) uint16 -> (H, W) float32 metres (0 stays 0 = invalid)."""
    return (raw.astype(np.float64) * depth_scale).astype(np.float32)
