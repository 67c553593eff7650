"""Make an episode whose writer was killed (or lost power) valid again without losing a complete frame.

A frame is complete when its ``frames.csv`` row is whole and the rgb image of every camera (and
its depth and mask, where that camera has them) decodes at the camera's size. Crash artefacts are what an
interrupted :class:`~manisplat.episode.writer.EpisodeWriter` leaves behind: temporary files, a
torn last CSV line, images whose row was never written, rows at the end whose images are
missing or truncated. ``recover`` moves them, and the original of every file it rewrites, into
``<episode>/.recovered/<UTC time>/`` (nothing is deleted), rewrites those files, and marks
the episode complete with a ``recovery`` entry in ``episode.json``. Damage that is not a crash
artefact (a broken frame followed by good ones, or any broken frame in an episode that was
closed as complete) is refused unless ``drop_damaged``. Every per-frame file follows the kept
frames: ``frames.csv`` (with its action columns), every camera's images, and the per-frame arrays
of ``gt.npz``; ``joints.csv`` (``joints_<arm>.csv`` per arm in version 2) is a stream of its own
and only loses damaged samples.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from manisplat.episode.format import (FRAMES_FILE, GT_FILE, JOINT_COLUMNS, META_FILE, RECOVERED_DIR,
                                      DamagedEpisodeError, EpisodeFormatError, image_name)
from manisplat.episode.fsio import TMP_SUFFIX, atomic_write_bytes, fsync_path
from manisplat.episode.groundtruth import is_compressed, per_frame_names, read_gt, write_gt
from manisplat.episode.images import KINDS, RGB, ImageKind, decode_image, find_image, has_images, image_problem, list_images
from manisplat.episode.layout import Layout
from manisplat.episode.meta import EpisodeMeta, load_meta, save_meta
from manisplat.episode.tables import CsvRow, CsvScan, scan_csv
from manisplat.episode.validation import ValidationReport, validate

log = logging.getLogger(__name__)

GT_TIME_TOL = 1e-6
"""Seconds within which a ``gt.npz`` ``t`` matches a ``frames.csv`` ``t`` (CSV files may round to 1 us)."""


@dataclass
class RecoveryReport:
    """What :func:`recover` did.

    Attributes:
        path: the episode folder.
        changed: False when the episode was already complete and valid.
        frames_kept: frames in the recovered episode.
        dropped: ``frames.csv`` lines (1-based, header = 1) of the rows moved aside.
        moved: files moved out of the episode, relative to it (they are now under ``backup_dir``).
        saved: files rewritten, whose original is kept under ``backup_dir``.
        renamed: ``(old, new)`` image paths when frames were renumbered (``drop_damaged``).
        gt_cut: the ``gt.npz`` arrays cut to the kept frames (its original is under ``backup_dir``).
        backup_dir: ``<episode>/.recovered/<time>``, or None when nothing was moved.
        validation: :func:`validate` of the result (None when nothing changed).
    """

    path: Path
    changed: bool
    frames_kept: int
    dropped: list[int] = field(default_factory=list)
    moved: list[str] = field(default_factory=list)
    saved: list[str] = field(default_factory=list)
    renamed: list[tuple[str, str]] = field(default_factory=list)
    gt_cut: list[str] = field(default_factory=list)
    backup_dir: Path | None = None
    validation: ValidationReport | None = None

    def __str__(self) -> str:
        if not self.changed:
            return f"{self.path}: already complete and valid ({self.frames_kept} frames); nothing to do"
        dropped = f"; dropped the {FRAMES_FILE} line(s) {self.dropped}" if self.dropped else ""
        if self.frames_kept:
            lines = [f"{self.path}: recovered {self.frames_kept} frames{dropped}"]
        else:
            lines = [f"{self.path}: nothing could be kept: no frame is complete (a whole {FRAMES_FILE} row whose "
                     f"images decode at the camera size){dropped}. The episode holds no frame and is not valid"]
        if self.backup_dir is not None:
            originals = ", ".join(self.saved) or "no rewritten file"
            lines.append(f"  moved {len(self.moved)} file(s) and the original of {originals} to {self.backup_dir}")
        if self.renamed:
            lines.append(f"  renumbered {len(self.renamed)} image(s)")
        if self.gt_cut:
            lines.append(f"  cut the per-frame arrays of {GT_FILE} ({', '.join(self.gt_cut)}) to the kept frames")
        if self.validation is not None and not self.validation.ok:
            lines.append(f"  still invalid:\n{self.validation}")
        return "\n".join(lines)


@dataclass(frozen=True)
class _Folder:
    """One image folder a frame needs an image in: ``rel`` (``rgb`` or ``rgb/cam_high``), its kind
    and its camera's size."""

    rel: str
    kind: ImageKind
    width: int
    height: int


def _frame_folders(path: Path, meta: EpisodeMeta) -> list[_Folder]:
    """Every image folder each frame needs an image in: every camera's rgb, and its depth and
    masks when that folder holds any image."""
    folders = []
    for files in meta.layout.cameras:
        camera = meta.cameras[files.name]
        for kind in KINDS:
            if kind is RGB or has_images(path / files.folder(kind)):
                folders.append(_Folder(files.folder(kind), kind, camera.width, camera.height))
    return folders


def _image_faults(path: Path, index: int, folders: list[_Folder]) -> list[str]:
    """Why the images of frame ``index`` are not complete (empty when they are)."""
    faults = []
    for folder in folders:
        file = find_image(path / folder.rel, index)
        if file is None:
            faults.append(f"{folder.rel}/{image_name(index)} missing")
            continue
        image = decode_image(file)
        if image is None:
            problem = "cannot decode (truncated or corrupt)"
        else:
            problem = image_problem(image, folder.kind, folder.width, folder.height)
        if problem:
            faults.append(f"{folder.rel}/{file.name} {problem}")
    return faults


def _row_faults(scan: CsvScan, path: Path, folders: list[_Folder]) -> list[list[str]]:
    """Per ``frames.csv`` row, why it is not a complete frame on its own (index and t order aside)."""
    faults = []
    for k, row in enumerate(scan.rows):
        if row.values is None:
            faults.append([f"line {row.line}: {row.problem}"])
            continue
        own = []
        if k == len(scan.rows) - 1 and not scan.ends_with_newline:
            own.append(f"line {row.line}: torn last line (no line break)")
        faults.append(own + _image_faults(path, int(row.values[0]), folders))
    return faults


def _select_frames(scan: CsvScan, faults: list[list[str]], *, drop_damaged: bool, complete: bool) -> list[int]:
    """Positions of the ``frames.csv`` rows to keep.

    Without ``drop_damaged`` the kept frames are the rows before the first damaged one, and the
    rest must be a crash tail: raises :class:`DamagedEpisodeError` when a good frame follows the
    damage, or when the episode was closed (``complete``), so that no crash can explain it. With
    ``drop_damaged`` every good row is kept whose index and t increase strictly (kept frames are
    then renumbered in order, which never overwrites an image).
    """
    kept: list[int] = []
    last_index, last_t = -1, float("-inf")
    for k, row in enumerate(scan.rows):
        fault = list(faults[k])
        if not fault:
            index, t = int(row.values[0]), row.values[1]
            if not drop_damaged and index != len(kept):
                fault.append(f"line {row.line}: index {index}, expected {len(kept)}")
            elif drop_damaged and index <= last_index:
                fault.append(f"line {row.line}: index {index} not after the previous frame's {last_index}")
            if t <= last_t:
                fault.append(f"line {row.line}: t={t!r} not after the previous frame's t={last_t!r}")
        if not fault:
            kept.append(k)
            last_index, last_t = index, t
            continue
        if drop_damaged:
            continue
        good_after = sum(1 for j in range(k + 1, len(scan.rows)) if not faults[j])
        if good_after or complete:
            why = (f"{good_after} good frame(s) follow it" if good_after
                   else "the episode was closed as complete, so no crash explains it")
            raise DamagedEpisodeError(
                f"{FRAMES_FILE}: frame at line {row.line} is damaged ({'; '.join(fault)}) and {why}: "
                "it is not a crash artefact. Repair it, or run `manisplat-episode recover --drop-damaged` "
                "to move the damaged frames aside and renumber the rest")
        break
    return kept


def _select_joints(scan: CsvScan, file: str, drop_damaged: bool) -> list[int]:
    """Positions of the ``joints.csv`` rows to keep: a torn last line is a crash artefact,
    other bad rows are damage (refused unless ``drop_damaged``)."""
    kept: list[int] = []
    last_t = float("-inf")
    for k, row in enumerate(scan.rows):
        is_last = k == len(scan.rows) - 1
        if is_last and scan.torn_tail:
            break
        if row.values is not None and row.values[0] > last_t:
            kept.append(k)
            last_t = row.values[0]
        elif not drop_damaged:
            why = row.problem or f"t={row.values[0]!r} not after {last_t!r}"
            raise DamagedEpisodeError(f"{file}: line {row.line}: {why}; this is not a crash artefact. "
                                      "Repair it, or run `manisplat-episode recover --drop-damaged`")
    return kept


def _csv_text(columns: tuple[str, ...], rows: list[str]) -> bytes:
    return ("".join(line + "\n" for line in [",".join(columns), *rows])).encode("utf-8")


def _backup_dir(path: Path) -> Path:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    candidate, n = path / RECOVERED_DIR / stamp, 1
    while candidate.exists():
        candidate, n = path / RECOVERED_DIR / f"{stamp}-{n}", n + 1
    return candidate


def _scan_frames(path: Path, required: tuple[str, ...]) -> tuple[CsvScan, bool]:
    """``(frames.csv, needs_rewrite)``: an empty table to rewrite when the file is missing, empty
    or holds only a torn header (the writer was stopped while creating it)."""
    file = path / FRAMES_FILE
    scan = scan_csv(file, required, ("index",)) if file.is_file() else None
    if scan is None or (not scan.rows and (not scan.columns or not scan.ends_with_newline)):
        return CsvScan(required, None, [], True), True
    if scan.header_problem:
        raise DamagedEpisodeError(f"{file}: line 1: {scan.header_problem}; repair the header by hand")
    return scan, False


def _stray_files(path: Path, keep: set[int], layout: Layout) -> list[str]:
    """Files to move aside: frame images not in ``keep`` and temporary files of every camera's
    folders, relative to ``path``."""
    stray = []
    for _, _, rel in layout.image_folders(KINDS):
        by_index, others = list_images(path / rel)
        stray += [f"{rel}/{n}" for i, names in sorted(by_index.items()) if i not in keep for n in names]
        stray += [f"{rel}/{n}" for n in others if n.endswith(TMP_SUFFIX)]
    return stray + [p.name for p in sorted(path.glob("*" + TMP_SUFFIX))]


def _renames(path: Path, old_indices: list[int], folders: list[_Folder]) -> list[tuple[str, str]]:
    """``(old, new)`` image paths that give kept frame ``old_indices[j]`` the index ``j``."""
    renamed = []
    for new, old in enumerate(old_indices):
        if new != old:
            for folder in folders:
                file = find_image(path / folder.rel, old)
                renamed.append((f"{folder.rel}/{file.name}", f"{folder.rel}/{image_name(new, file.suffix)}"))
    return renamed


@dataclass
class _GtCut:
    """``gt.npz`` with its per-frame arrays cut to the kept frames."""

    arrays: dict[str, np.ndarray]
    names: list[str]  # the per-frame arrays
    compressed: bool


def _rows_by_time(gt_t: np.ndarray, t: np.ndarray) -> list[int] | None:
    """For each time of ``t`` (increasing), the row of ``gt_t`` within :data:`GT_TIME_TOL` of it,
    or None when one has no such row or ``gt_t`` is not strictly increasing."""
    if gt_t.ndim != 1 or not len(gt_t) or np.any(np.diff(gt_t) <= 0):
        return None
    right = np.searchsorted(gt_t, t).clip(0, len(gt_t) - 1)
    left = (right - 1).clip(0)
    rows = np.where(np.abs(gt_t[left] - t) < np.abs(gt_t[right] - t), left, right)
    if np.any(np.abs(gt_t[rows] - t) > GT_TIME_TOL) or np.any(np.diff(rows) <= 0):
        return None
    return rows.tolist()


def _plan_gt(path: Path, objects: Sequence[str], *, complete: bool, rows_before: int, old_indices: list[int],
             kept_t: np.ndarray) -> _GtCut | None:
    """How ``gt.npz`` follows the kept frames; None without one, or when it already fits them.

    Row i of a per-frame array belongs to frame i. When a closed episode's ``gt.npz`` is not as
    long as its ``frames.csv`` (an older recovery cut only ``frames.csv``), its rows are matched to
    the frames by ``t`` instead. Raises :class:`DamagedEpisodeError` when it cannot be read or
    does not cover the kept frames.
    """
    file = path / GT_FILE
    if not file.is_file():
        return None
    advice = (f"{GT_FILE} (simulation ground truth) is optional: repair it, or move it out of the episode and run "
              "recover again")
    try:
        arrays = read_gt(file)
    except EpisodeFormatError as exc:
        raise DamagedEpisodeError(f"{exc}; {advice}") from None
    names = per_frame_names(arrays, objects)
    sizes = {name: len(arrays[name]) if arrays[name].ndim else 0 for name in names}
    if len(set(sizes.values())) > 1:
        raise DamagedEpisodeError(f"{file}: the per-frame arrays differ in length "
                                  f"({', '.join(f'{n}: {s}' for n, s in sizes.items())}); {advice}")
    if not names:
        return None
    length = next(iter(sizes.values()))
    if complete and length != rows_before:
        rows = _rows_by_time(arrays["t"], kept_t) if "t" in arrays else None
        if rows is None:
            raise DamagedEpisodeError(f"{file}: {length} rows but {FRAMES_FILE} has {rows_before}, and its t do not "
                                      f"match the frames' t; {advice}")
    else:
        rows = old_indices
        if rows and max(rows) >= length:
            raise DamagedEpisodeError(f"{file}: {length} rows, but {FRAMES_FILE} keeps frame {max(rows)}; {advice}")
    if rows == list(range(length)):
        return None
    take = np.asarray(rows, dtype=np.intp)
    cut = {name: a[take] if name in names else a for name, a in arrays.items()}
    return _GtCut(cut, names, is_compressed(file))


@dataclass
class _Plan:
    """What :func:`recover` will change, decided before anything is touched."""

    frames: CsvScan
    kept_rows: list[CsvRow]
    old_indices: list[int]  # original index of each kept frame; its position is its new index
    dropped: list[int]
    joints: dict[str, tuple[CsvScan, list[int]]]  # joint stream file -> (its scan, rows to keep), when rewritten
    gt: _GtCut | None
    moved: list[str]
    saved: list[str]
    renamed: list[tuple[str, str]]


def _plan_joints(path: Path, file: str, drop_damaged: bool) -> tuple[CsvScan | None, list[int], bool]:
    """``(scan, rows to keep, torn header)`` of one joint stream (scan None when it is absent)."""
    joints_file = path / file
    joints = scan_csv(joints_file, JOINT_COLUMNS) if joints_file.is_file() else None
    torn_header = joints is not None and not joints.rows and not joints.ends_with_newline
    if joints is not None and joints.header_problem and not torn_header:
        raise DamagedEpisodeError(f"{joints_file}: line 1: {joints.header_problem}; repair the header by hand")
    keep = _select_joints(joints, file, drop_damaged) if joints is not None and not torn_header else []
    return joints, keep, torn_header


def _plan(path: Path, meta: EpisodeMeta, *, drop_damaged: bool, complete: bool) -> _Plan:
    layout = meta.layout
    folders = _frame_folders(path, meta)
    frames, rewrite_frames = _scan_frames(path, layout.frame_columns)
    kept = _select_frames(frames, _row_faults(frames, path, folders), drop_damaged=drop_damaged,
                          complete=complete)
    kept_rows = [frames.rows[k] for k in kept]
    old_indices = [int(r.values[0]) for r in kept_rows]
    kept_set = set(kept)
    dropped = [r.line for k, r in enumerate(frames.rows) if k not in kept_set]

    joints: dict[str, tuple[CsvScan, list[int]]] = {}
    torn_joint_headers = []
    for arm in layout.arms:
        scan, keep, torn = _plan_joints(path, arm.joints_file, drop_damaged)
        if torn:
            torn_joint_headers.append(arm.joints_file)
        elif scan is not None and len(keep) != len(scan.rows):
            joints[arm.joints_file] = (scan, keep)
    gt = _plan_gt(path, meta.objects, complete=complete, rows_before=len(frames.rows), old_indices=old_indices,
                  kept_t=np.array([r.values[1] for r in kept_rows], dtype=np.float64))

    moved = _stray_files(path, set(old_indices), layout) + torn_joint_headers
    renamed = _renames(path, old_indices, folders)
    saved = [FRAMES_FILE] if rewrite_frames or dropped or renamed else []
    saved += list(joints)
    if gt is not None:
        saved.append(GT_FILE)
    return _Plan(frames, kept_rows, old_indices, dropped, joints, gt, moved, saved, renamed)


def _apply(path: Path, plan: _Plan, layout: Layout, backup: Path, entry: dict[str, Any]) -> None:
    """Move files aside into ``backup`` (with a copy of each rewritten file), rewrite, rename."""
    if plan.moved or plan.saved:
        backup.mkdir(parents=True)
        (backup / "recovery.json").write_text(json.dumps(entry, indent=1) + "\n")
    for name in plan.saved:
        if (path / name).is_file():
            shutil.copy2(path / name, backup / name)
    for rel in plan.moved:
        (backup / rel).parent.mkdir(parents=True, exist_ok=True)
        os.replace(path / rel, backup / rel)
    if FRAMES_FILE in plan.saved:
        lines = [r.text if new == old else str(new) + r.text[r.text.index(","):]
                 for new, (old, r) in enumerate(zip(plan.old_indices, plan.kept_rows))]
        atomic_write_bytes(path / FRAMES_FILE, _csv_text(plan.frames.columns, lines))
    for old, new in plan.renamed:
        os.replace(path / old, path / new)
    for file, (scan, keep) in plan.joints.items():
        atomic_write_bytes(path / file, _csv_text(scan.columns, [scan.rows[k].text for k in keep]))
    if plan.gt is not None:
        write_gt(path / GT_FILE, plan.gt.arrays, compressed=plan.gt.compressed)
    for folder in {path / rel for _, _, rel in layout.image_folders(KINDS) if (path / rel).is_dir()} | {path}:
        fsync_path(folder)


def recover(path: str | Path, *, drop_damaged: bool = False) -> RecoveryReport:
    """Make the episode at ``path`` complete and valid again, keeping every complete frame.

    Args:
        path: episode folder (its ``episode.json`` must be readable: the writer writes it first).
        drop_damaged: also move aside damaged frames that are followed by good ones (or that are
            in an episode closed as complete), and renumber the remaining frames 0..T-1 (rows
            and image files).

    Returns:
        a :class:`RecoveryReport`; ``changed`` is False for an already complete, valid episode.
        When no frame is complete, the debris is moved aside all the same and the report says
        that nothing could be kept (``frames_kept`` 0, ``validation`` not ok).

    Raises:
        DamagedEpisodeError: damage that is not a crash artefact, without ``drop_damaged``, or a
            ``gt.npz`` that cannot follow the kept frames; nothing is changed then.
        EpisodeFormatError: ``episode.json`` is missing or invalid.
    """
    path = Path(path)
    meta = load_meta(path / META_FILE)
    if meta.complete:
        report = validate(path)
        if report.ok:
            return RecoveryReport(path, changed=False, frames_kept=report.frame_rows)

    plan = _plan(path, meta, drop_damaged=drop_damaged, complete=meta.complete)
    backup = _backup_dir(path)
    has_backup = bool(plan.moved or plan.saved)
    entry = {"date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
             "frames_kept": len(plan.kept_rows), "dropped_lines": plan.dropped, "moved": plan.moved,
             "saved": plan.saved, "renamed": [list(r) for r in plan.renamed],
             "gt_cut": plan.gt.names if plan.gt is not None else [],
             "backup": str(backup.relative_to(path)) if has_backup else None}
    _apply(path, plan, meta.layout, backup, entry)

    meta.complete = True
    meta.frame_count = len(plan.kept_rows)
    meta.extra["recovery"] = [*meta.extra.get("recovery", []), entry]
    save_meta(path / META_FILE, meta)
    report = RecoveryReport(path, changed=True, frames_kept=len(plan.kept_rows), dropped=plan.dropped,
                            moved=plan.moved, saved=plan.saved, renamed=plan.renamed,
                            gt_cut=plan.gt.names if plan.gt is not None else [],
                            backup_dir=backup if has_backup else None, validation=validate(path))
    log.info("%s", report)
    return report
