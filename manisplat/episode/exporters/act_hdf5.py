"""Export episodes as ACT / ALOHA / AgileX Cobot Magic HDF5 files (``episode_<N>.hdf5``).

Layout written (``shared/reference/augmentation.md`` section 5.3), 7 columns per arm, the arms in the
episode's order (a Cobot Magic import: left, right, so 14 columns as Cobot Magic stores them)::

    attrs: sim (bool), compress (bool), fps (float64), qpos_names (str, JSON list of the column names:
           q1..gripper in version 1, left.q1..left.gripper, right.q1.. in version 2),
           manisplat_source, manisplat_episode (str), manisplat_parent (str, augmented episodes only)
    /observations/qpos          (T, 7 A) float32, each arm's [q1..q6 rad, gripper m] (float64 with dtype="float64")
    /observations/qvel          (T, 7 A) same dtype: backward differences over frames.csv t, row 0 zero
    /observations/images/<key>  one per camera (key: the camera name, e.g. cam_high, cam_left_wrist):
                                (T, H, W, 3) uint8 RGB, chunks (1, H, W, 3); with compress: (T, L) uint8,
                                chunks (1, L), each row the cv2.imencode JPEG bytes of the RGB array padded
                                with zeros to the longest frame L of all cameras (as ALOHA pads)
    /compress_len               (cameras, T) float32 JPEG byte count of each frame (compress only)
    /action                     (T, 7 A) same dtype, each arm's [a1..a6, a_gripper]; attr ``source``: "actions"
                                when every arm has them, else "next_qpos" (qpos of frame i+1, the last row repeats)

``import-act --arm single`` reads one-arm files back, ``import-act --calib FILE.calib.json`` two-arm
ones (``docs/cobot-magic.md``): a version 2 episode's file gets its ``episode_<N>.calib.json`` beside
it (:mod:`~manisplat.episode.exporters.act_calibration`). ``augmentation.json`` beside them records where
every file came from. The export is written into a hidden folder beside ``OUT`` and moved there only
when complete: a failed export leaves nothing in ``OUT``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import cv2
import h5py
import numpy as np
from tqdm import tqdm

from manisplat.episode.exporters.act_calibration import act_calibration, calibration_path
from manisplat.episode.exporters.sources import (PROVENANCE_FILE, ExportDestinationError, ExportSource,
                                                 export_cameras, export_frames, frame_times, open_sources, state_and_action,
                                                 state_names)
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
_OUTPUT_RE = re.compile(r"^episode_\d+(\.hdf5|\.calib\.json)(\.tmp)?$")


def check_destination(out_dir: str | Path, overwrite: bool) -> None:
    """Refuse an ``out_dir`` that is a file, or a folder holding anything without ``overwrite``."""
    check_output_folder(Path(out_dir), allowed=overwrite, error=ExportDestinationError,
                        refusal=f"; pass --overwrite to replace its episode_*.hdf5 files and {PROVENANCE_FILE}, "
                                "or choose another folder")


def _clear_previous(out_dir: Path) -> None:
    """Remove what an earlier export wrote (``episode_<N>.hdf5``, their calibration sidecars,
    their ``.tmp``, the side file)."""
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


def _write_file(src: ExportSource, frames: np.ndarray, fps: float, path: Path, keys: dict[str, str], *,
                compress: bool, jpeg_quality: int, dtype: np.dtype, on_frame: Callable[[], None]) -> dict[str, Any]:
    """Write frames ``frames`` of one episode to ``path`` (in the staging folder), the images of each
    camera of ``keys`` (camera -> dataset name); returns its provenance entry."""
    ep = src.episode
    qpos, actions, recorded = state_and_action(ep, frames)
    action_source = "actions" if recorded else "next_qpos"
    qvel = velocities(frame_times(ep)[frames], qpos)
    with h5py.File(path, "w") as f:
        f.attrs["sim"] = src.sim
        f.attrs["compress"] = compress
        f.attrs["fps"] = float(fps)
        f.attrs["qpos_names"] = json.dumps(state_names(ep))
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
            _write_jpeg(f, images, keys, ep, frames, jpeg_quality, path.parent, on_frame)
        else:
            for camera, key in keys.items():
                info = ep.cameras[camera]
                shape = (len(frames), info.height, info.width, 3)
                ds = images.create_dataset(key, shape, dtype=np.uint8, chunks=(1, *shape[1:]))
                for row, i in enumerate(frames):
                    ds[row] = ep.rgb(int(i), camera)
                    on_frame()
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())
    if ep.meta.version != 1:  # a version 2 episode's calibration, for import-act --calib
        sidecar = json.dumps(act_calibration(ep, keys, fps), indent=1) + "\n"
        atomic_write_bytes(calibration_path(path), sidecar.encode())
    return {"file": path.name, **src.provenance(), "frames": len(frames),
            "recorded_frames": [int(frames[0]), int(frames[-1])], "action": action_source}


def _write_jpeg(f: h5py.File, images: h5py.Group, keys: dict[str, str], ep: Episode, frames: np.ndarray,
                quality: int, scratch_dir: Path, on_frame: Callable[[], None]) -> None:
    """JPEG rows of every camera padded to the longest frame of all, as ALOHA writes them. The padded
    length is known only after every frame is encoded, so the bytes wait in anonymous scratch
    files (one per camera), never in memory."""
    T = len(frames)
    lengths = np.zeros((len(keys), T), dtype=np.int64)
    with contextlib.ExitStack() as stack:
        scratches = []
        for c, camera in enumerate(keys):
            scratch = stack.enter_context(tempfile.TemporaryFile(dir=scratch_dir))
            for row, i in enumerate(frames):
                ok, data = cv2.imencode(".jpg", ep.rgb(int(i), camera), [int(cv2.IMWRITE_JPEG_QUALITY), quality])
                if not ok:
                    raise OSError(f"{ep.path}: camera {camera} frame {i}: OpenCV could not encode the image as JPEG")
                lengths[c, row] = data.size
                scratch.write(data.tobytes())
                on_frame()
            scratches.append(scratch)
        padded = int(lengths.max())
        row = np.zeros(padded, dtype=np.uint8)
        for c, (scratch, key) in enumerate(zip(scratches, keys.values())):
            ds = images.create_dataset(key, (T, padded), dtype=np.uint8, chunks=(1, padded))
            scratch.seek(0)
            for i in range(T):
                row[:] = 0
                row[:lengths[c, i]] = np.frombuffer(scratch.read(int(lengths[c, i])), dtype=np.uint8)
                ds[i] = row
    f.create_dataset("compress_len", data=lengths.astype(np.float32))


def _write_provenance(out_dir: Path, entries: list[dict[str, Any]], *, fps: float, keys: dict[str, str],
                      compress: bool, dtype: str) -> None:
    record = {"format": PROVENANCE_FORMAT, "version": 1, "complete": True, "layout": "act_hdf5",
              "fps": fps, "cameras": list(keys), "image_keys": keys, "compress": compress, "dtype": dtype,
              "files": entries}
    atomic_write_bytes(out_dir / PROVENANCE_FILE, (json.dumps(record, indent=2) + "\n").encode())


def image_keys(cameras: Sequence[str], image_key: str | Mapping[str, str] | None) -> dict[str, str]:
    """Camera -> dataset name under ``/observations/images``: the camera's name, or as ``image_key``
    renames them (one name when one camera is exported, else a mapping camera -> name)."""
    if isinstance(image_key, str):
        if len(cameras) != 1:
            raise ValueError(f"one image key {image_key!r} for {len(cameras)} cameras ({', '.join(cameras)}); "
                             "give one per camera as CAMERA=KEY")
        image_key = {cameras[0]: image_key}
    renamed = dict(image_key or {})
    unknown = [c for c in renamed if c not in cameras]
    if unknown:
        raise ValueError(f"image keys for {', '.join(unknown)}, which are not exported (cameras: {', '.join(cameras)})")
    keys = {c: renamed.get(c, c) for c in cameras}
    bad = [k for k in keys.values() if "/" in k or not k]
    if bad or len(set(keys.values())) != len(keys):
        raise ValueError(f"image keys must be distinct plain names; got {list(keys.values())}")
    return keys


def export_act_hdf5(episodes: Sequence[str | Path], out_dir: str | Path, *,
                    camera: str | Sequence[str] | None = None, image_key: str | Mapping[str, str] | None = None,
                    compress: bool = False,
                    jpeg_quality: int = DEFAULT_JPEG_QUALITY, dtype: str = "float32", fps: float | None = None,
                    overwrite: bool = False, progress: bool = False) -> list[dict[str, Any]]:
    """Write ``episodes`` as ``out_dir/episode_0.hdf5``, ``episode_1.hdf5``, ... in the order given.

    Everything is checked before anything is written: every episode complete and with an image
    for each frame of each exported camera, the same arms and cameras, one fps (or ``fps`` given)
    and one image size per camera for all. Images stream one frame at a
    time into pre-sized datasets, in a hidden folder beside ``out_dir`` (``.OUT.partial-*``) whose
    files move into ``out_dir`` when the last one is written: a failed export leaves nothing there,
    and the same command can simply run again.

    Args:
        episodes: episode folders.
        out_dir: export folder, created; must be new or empty unless ``overwrite`` (which removes an
            earlier export's ``episode_*.hdf5`` and ``augmentation.json``, nothing else).
        camera: the camera or cameras to export, which every episode must have (default: every
            camera of the first episode).
        image_key: dataset name under ``/observations/images`` (default: the camera's name), e.g.
            ``cam_high`` to match an ACT task config: one name when one camera is exported, or a
            mapping camera -> name.
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
    sources = open_sources(episodes, "ACT", same_fps=fps is None)
    keys = image_keys([c.name for c in export_cameras(sources, camera, "ACT")], image_key)
    rate = sources[0].episode.meta.fps if fps is None else float(fps)
    frames = [export_frames(src.episode, rate) for src in sources]
    in_use = out_dir.is_dir() and any(out_dir.iterdir())  # allowed by check_destination: --overwrite
    settings = dict(fps=rate, keys=keys, compress=compress, dtype=dtype)
    entries: list[dict[str, Any]] = []
    total = sum(len(f) for f in frames) * len(keys)
    staging = staging_folder(out_dir)
    try:
        with tqdm(total=total, desc="export act-hdf5", unit="image", disable=not progress) as bar:
            for n, src in enumerate(sources):
                entries.append(_write_file(src, frames[n], rate, staging / f"episode_{n}.hdf5", keys, compress=compress,
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
    log.info("exported %d episodes (%d frames of %d cameras) to %s", len(sources), total // len(keys), len(keys),
             out_dir)
    return entries
