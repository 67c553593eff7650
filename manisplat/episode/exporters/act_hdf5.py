"""Export episodes as ACT / ALOHA / AgileX Cobot Magic HDF5 files (``episode_<N>.hdf5``).

Layout written (``shared/reference/augmentation.md`` section 5.3, single arm, so 7 columns)::

    attrs: sim (bool), compress (bool), fps (float64),
           manisplat_source, manisplat_episode (str), manisplat_parent (str, augmented episodes only)
    /observations/qpos          (T, 7) float32 [q1..q6 rad, gripper m] (float64 with dtype="float64")
    /observations/qvel          (T, 7) same dtype: backward differences over frames.csv t, row 0 zero
    /observations/images/<key>  (T, H, W, 3) uint8 RGB, chunks (1, H, W, 3); with compress: (T, L) uint8,
                                chunks (1, L), each row the cv2.imencode JPEG bytes of the RGB array padded
                                with zeros to the longest frame L
    /compress_len               (1, T) float32 JPEG byte count of each frame (compress only)
    /action                     (T, 7) same dtype [a1..a6, a_gripper]; attr ``source``: "actions" when the
                                episode has them, else "next_qpos" (qpos of frame i+1, the last row repeats)

``import-act --arm single`` reads these files back. ``augmentation.json`` beside them records where
every file came from. The export is written into a hidden folder beside ``OUT`` and moved there only
when complete: a failed export leaves nothing in ``OUT``.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import h5py
import numpy as np
from tqdm import tqdm

from manisplat.episode.exporters.sources import (PROVENANCE_FILE, ExportDestinationError, ExportSource,
                                                 export_frames, open_sources, state_and_action)
from manisplat.episode.exporters.staging import merge_files, replace_folder, staging_folder
from manisplat.episode.fsio import atomic_write_bytes, temp_path
from manisplat.episode.reader import Episode
from manisplat.output_folder import check_output_folder

log = logging.getLogger(__name__)

PROVENANCE_FORMAT = "manisplat-act-export"
DEFAULT_JPEG_QUALITY = 90
"""JPEG quality with ``compress``. ALOHA's ``record_episodes.py`` uses 50, which on the 64x48 sample
episode gives 27.6 dB PSNR (90: 33.8 dB, 1.6x the bytes); pass 50 to match its file sizes."""
DTYPES = ("float32", "float64")
_OUTPUT_RE = re.compile(r"^episode_\d+\.hdf5(\.tmp)?$")


def check_destination(out_dir: str | Path, overwrite: bool) -> None:
    """Refuse an ``out_dir`` that is a file, or a folder holding anything without ``overwrite``."""
    check_output_folder(Path(out_dir), allowed=overwrite, error=ExportDestinationError,
                        refusal=f"; pass --overwrite to replace its episode_*.hdf5 files and {PROVENANCE_FILE}, "
                                "or choose another folder")


def _clear_previous(out_dir: Path) -> None:
    """Remove what an earlier export wrote (``episode_<N>.hdf5``, their ``.tmp``, the side file)."""
    removed = 0
    for path in out_dir.iterdir():
        if path.is_file() and (_OUTPUT_RE.match(path.name) or path.name in (PROVENANCE_FILE,
                                                                            temp_path(Path(PROVENANCE_FILE)).name)):
            path.unlink()
            removed += 1
    if removed:
        log.info("--overwrite: removed %d files of an earlier export from %s", removed, out_dir)


def velocities(t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(T, D) backward differences ``(v[i] - v[i-1]) / (t[i] - t[i-1])``; row 0 is zero."""
    out = np.zeros_like(values, dtype=np.float64)
    if len(t) > 1:
        out[1:] = np.diff(values, axis=0) / np.diff(t)[:, None]
    return out


def _write_file(src: ExportSource, frames: np.ndarray, fps: float, path: Path, key: str, *, compress: bool,
                jpeg_quality: int, dtype: np.dtype, on_frame: Callable[[], None]) -> dict[str, Any]:
    """Write frames ``frames`` of one episode to ``path`` (in the staging folder); returns its provenance entry."""
    ep = src.episode
    T, width, height = len(frames), ep.camera.width, ep.camera.height
    qpos, actions, recorded = state_and_action(ep, frames)
    action_source = "actions" if recorded else "next_qpos"
    qvel = velocities(ep.frames.t[frames], qpos)
    with h5py.File(path, "w") as f:
        f.attrs["sim"] = src.sim
        f.attrs["compress"] = compress
        f.attrs["fps"] = float(fps)
        f.attrs["manisplat_source"] = ep.meta.source
        f.attrs["manisplat_episode"] = ep.path.name
        if src.parent is not None:
            f.attrs["manisplat_parent"] = src.parent
        obs = f.create_group("observations")
        obs.create_dataset("qpos", data=qpos.astype(dtype))
        obs.create_dataset("qvel", data=qvel.astype(dtype))
        f.create_dataset("action", data=actions.astype(dtype)).attrs["source"] = action_source
        images = obs.create_group("images")
        if compress:
            _write_jpeg(f, images, key, ep, frames, jpeg_quality, path.parent, on_frame)
        else:
            ds = images.create_dataset(key, (T, height, width, 3), dtype=np.uint8, chunks=(1, height, width, 3))
            for row, i in enumerate(frames):
                ds[row] = ep.rgb(int(i))
                on_frame()
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())
    return {"file": path.name, **src.provenance(), "frames": T, "recorded_frames": [int(frames[0]), int(frames[-1])],
            "action": action_source}


def _write_jpeg(f: h5py.File, images: h5py.Group, key: str, ep: Episode, frames: np.ndarray, quality: int,
                scratch_dir: Path, on_frame: Callable[[], None]) -> None:
    """JPEG rows padded to the longest frame, as ALOHA writes them. The padded length is known only after
    every frame is encoded, so the bytes wait in an anonymous scratch file, never in memory."""
    T = len(frames)
    lengths = np.zeros(T, dtype=np.int64)
    with tempfile.TemporaryFile(dir=scratch_dir) as scratch:
        for row, i in enumerate(frames):
            ok, data = cv2.imencode(".jpg", ep.rgb(int(i)), [int(cv2.IMWRITE_JPEG_QUALITY), quality])
            if not ok:
                raise OSError(f"{ep.path}: frame {i}: OpenCV could not encode the image as JPEG")
            lengths[row] = data.size
            scratch.write(data.tobytes())
            on_frame()
        padded = int(lengths.max())
        ds = images.create_dataset(key, (T, padded), dtype=np.uint8, chunks=(1, padded))
        scratch.seek(0)
        row = np.zeros(padded, dtype=np.uint8)
        for i in range(T):
            row[:] = 0
            row[:lengths[i]] = np.frombuffer(scratch.read(int(lengths[i])), dtype=np.uint8)
            ds[i] = row
    f.create_dataset("compress_len", data=lengths[None].astype(np.float32))


def _write_provenance(out_dir: Path, entries: list[dict[str, Any]], *, fps: float, camera: str,
                      key: str, compress: bool, dtype: str) -> None:
    record = {"format": PROVENANCE_FORMAT, "version": 1, "complete": True, "layout": "act_hdf5",
              "fps": fps, "camera": camera, "image_key": key, "compress": compress, "dtype": dtype,
              "files": entries}
    atomic_write_bytes(out_dir / PROVENANCE_FILE, (json.dumps(record, indent=2) + "\n").encode())


def export_act_hdf5(episodes: Sequence[str | Path], out_dir: str | Path, *, camera: str | None = None,
                    image_key: str | None = None, compress: bool = False,
                    jpeg_quality: int = DEFAULT_JPEG_QUALITY, dtype: str = "float32", fps: float | None = None,
                    overwrite: bool = False, progress: bool = False) -> list[dict[str, Any]]:
    """Write ``episodes`` as ``out_dir/episode_0.hdf5``, ``episode_1.hdf5``, ... in the order given.

    Everything is checked before anything is written: every episode complete and with an image
    for each frame, one camera, one fps (or ``fps`` given) and one image size for all. Images stream one frame at a
    time into pre-sized datasets, in a hidden folder beside ``out_dir`` (``.OUT.partial-*``) whose
    files move into ``out_dir`` when the last one is written: a failed export leaves nothing there,
    and the same command can simply run again.

    Args:
        episodes: episode folders.
        out_dir: export folder, created; must be new or empty unless ``overwrite`` (which removes an
            earlier export's ``episode_*.hdf5`` and ``augmentation.json``, nothing else).
        camera: the camera every episode must have (default: the first episode's).
        image_key: dataset name under ``/observations/images`` (default: the camera name), e.g.
            ``cam_high`` to match an ACT task config.
        compress: JPEG-encode the images (ALOHA's compressed variant) instead of raw arrays.
        jpeg_quality: JPEG quality 0..100 with ``compress``.
        dtype: ``float32`` (what ACT and Cobot Magic record; ACT's loader computes its normalisation
            statistics in the file's dtype and feeds them to a float32 model, so float64 files make it
            fail with "mat1 and mat2 must have the same dtype") or ``float64`` (joints round-trip
            bit-exact through ``import-act``).
        fps: export rate in Hz (default: the episodes' common rate); episodes recorded faster are
            resampled to the frame nearest each ``1/fps`` step (qvel over those frames' own times).
        overwrite: allow a non-empty ``out_dir``.
        progress: show a tqdm progress bar over all frames.

    Returns:
        the provenance entries written to ``augmentation.json``, one per file.
    """
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {DTYPES}; got {dtype!r}")
    if not 0 <= jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be in 0..100; got {jpeg_quality}")
    out_dir = Path(out_dir)
    check_destination(out_dir, overwrite)
    sources = open_sources(episodes, camera, "ACT", same_fps=fps is None)
    first = sources[0].episode
    rate = first.meta.fps if fps is None else float(fps)
    frames = [export_frames(src.episode, rate) for src in sources]
    camera = first.camera.name
    key = image_key or camera
    if "/" in key or not key:
        raise ValueError(f"image key must be a plain name; got {key!r}")
    in_use = out_dir.is_dir() and any(out_dir.iterdir())  # allowed by check_destination: --overwrite
    settings = dict(fps=rate, camera=camera, key=key, compress=compress, dtype=dtype)
    entries: list[dict[str, Any]] = []
    total = sum(len(f) for f in frames)
    staging = staging_folder(out_dir)
    try:
        with tqdm(total=total, desc="export act-hdf5", unit="frame", disable=not progress) as bar:
            for n, src in enumerate(sources):
                entries.append(_write_file(src, frames[n], rate, staging / f"episode_{n}.hdf5", key, compress=compress,
                                           jpeg_quality=jpeg_quality, dtype=np.dtype(dtype),
                                           on_frame=lambda: bar.update(1)))
        _write_provenance(staging, entries, **settings)
        if in_use:  # an earlier export's files go; anything else in the folder stays
            _clear_previous(out_dir)
            merge_files(staging, out_dir, last=PROVENANCE_FILE)
        else:
            replace_folder(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    log.info("exported %d episodes (%d frames) to %s", len(sources), total, out_dir)
    return entries
