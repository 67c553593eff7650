"""Check an episode folder against the format and report every problem, each naming its file and row."""

from __future__ import annotations

import contextlib
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from lxml import etree
from tqdm import tqdm

from manisplat.episode.format import (FRAMES_FILE, GRIPPER_RANGE_M, GT_FILE, JOINT_COLUMNS, META_FILE, V1_ARM,
                                      EpisodeFormatError, image_name)
from manisplat.episode.fsio import TMP_SUFFIX
from manisplat.episode.groundtruth import frame_count_problems, read_gt
from manisplat.episode.images import DEPTH, KINDS, MASK, RGB, ImageKind, decode_image, image_problem, list_images
from manisplat.episode.layout import CameraFiles, Layout, is_v2_raw, layout_of_raw, v1_layout
from manisplat.episode.meta import meta_problems, parse_meta_text
from manisplat.episode.tables import CsvRow, scan_csv

Severity = Literal["error", "warning"]


@dataclass(frozen=True)
class Problem:
    """One thing wrong with an episode.

    Attributes:
        file: path relative to the episode folder (``frames.csv``, ``rgb/000007.png``).
        row: 1-based line of ``frames.csv``/``joints.csv`` (the header is line 1); for an image,
            the ``frames.csv`` line of its frame; None when no line applies.
        message: what is wrong.
        severity: ``"error"`` (the episode is invalid) or ``"warning"`` (suspicious but readable).
    """

    file: str
    row: int | None
    message: str
    severity: Severity = "error"

    def __str__(self) -> str:
        if self.row is None:
            where = self.file
        elif self.file.endswith(".csv"):
            where = f"{self.file}:{self.row}"
        else:
            where = f"{self.file} ({FRAMES_FILE} line {self.row})"
        return f"{where}: {self.severity}: {self.message}"


@dataclass
class ValidationReport:
    """The result of :func:`validate`.

    Attributes:
        path: the episode folder.
        problems: every problem found, in file order.
        frame_rows: data rows in ``frames.csv`` (0 when it is missing).
    """

    path: Path
    problems: list[Problem] = field(default_factory=list)
    frame_rows: int = 0

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "warning"]

    @property
    def ok(self) -> bool:
        """True when there is no error (warnings allowed)."""
        return not self.errors

    def __str__(self) -> str:
        status = "OK" if self.ok else "INVALID"
        head = (f"{self.path}: {status} ({self.frame_rows} frames, {len(self.errors)} errors, "
                f"{len(self.warnings)} warnings)")
        return "\n".join([head] + [f"  {p}" for p in self.problems])


@dataclass
class _Facts:
    """What the later checks need from ``episode.json``, each None when that field is unusable."""

    readable: bool = False
    layout: Layout = field(default_factory=v1_layout)
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)  # camera -> (width, height)
    frame_count: int | None = None
    depth_scale: float | None = None
    labels: set[int] | None = None
    objects: list[str] | None = None


def _valid_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= 0


def _check_meta(path: Path) -> tuple[list[Problem], _Facts]:
    facts = _Facts()
    try:
        raw = parse_meta_text((path / META_FILE).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return [Problem(META_FILE, None, "missing")], facts
    except (OSError, UnicodeDecodeError, EpisodeFormatError) as exc:
        return [Problem(META_FILE, None, f"unreadable: {exc}")], facts
    facts.readable = True
    problems = [Problem(META_FILE, None, m) for m in meta_problems(raw)]
    if raw.get("complete") is False:
        problems.append(Problem(META_FILE, None, "incomplete episode: run `manisplat-episode recover`"))
    layout = layout_of_raw(raw)
    v2 = is_v2_raw(raw)
    if layout is not None:
        facts.layout = layout
    if v2:
        cameras = raw.get("cameras") if isinstance(raw.get("cameras"), dict) else {}
        arms = raw.get("arms") if isinstance(raw.get("arms"), dict) else {}
    else:
        camera = raw.get("camera")
        cameras = {facts.layout.cameras[0].name: camera} if isinstance(camera, dict) else {}
        arms = {V1_ARM: raw.get("robot")}
    for name, camera in cameras.items():
        camera = camera if isinstance(camera, dict) else {}
        if _valid_int(camera.get("width")) and _valid_int(camera.get("height")):
            facts.sizes[name] = (camera["width"], camera["height"])
    if _valid_int(raw.get("frame_count")):
        facts.frame_count = raw["frame_count"]
    scale = raw.get("depth_scale")
    if isinstance(scale, (int, float)) and not isinstance(scale, bool) and scale > 0:
        facts.depth_scale = float(scale)
    labels = raw.get("labels", {})
    if isinstance(labels, dict) and all(isinstance(k, str) and k.isdigit() for k in labels):
        facts.labels = {int(k) for k in labels}
    objects = raw.get("objects", [])
    if isinstance(objects, list) and all(isinstance(o, str) for o in objects):
        facts.objects = objects
    for name, arm in arms.items():
        arm = arm if isinstance(arm, dict) else {}
        field_name = f"arms.{name}.description" if v2 else "robot.description"
        problems += _check_robot_description(path, arm.get("description"), field_name)
    if v2:
        problems += check_mount_links(path, arms, cameras)
    return problems, facts


def _check_robot_description(path: Path, description: Any, field_name: str = "robot.description") -> list[Problem]:
    """A warning when ``robot.description`` (or an arm's) names a URDF that is not there (e.g. a
    relative path in a copied episode): the joint data stay valid, but nothing can draw or move the robot."""
    if not isinstance(description, str) or not description or description.startswith("builtin:"):
        return []
    urdf = Path(os.path.abspath(path / description))
    if urdf.is_file():
        return []
    return [Problem(META_FILE, None, f"{field_name} {description!r} not found (looked at {urdf}); point it "
                                     f"at the URDF with `manisplat-episode set-robot {path} DESCRIPTION [--embed]`",
                    "warning")]


def _link_names(path: Path, description: str) -> list[str] | None:
    """The links of a robot description (a URDF read for its ``<link>`` names, a built-in robot
    loaded), or None when it cannot be read (``_check_robot_description`` reports that)."""
    if description.startswith("builtin:"):
        from manisplat.robot import load_robot  # loads torch: only for a built-in robot with a mounted camera

        try:
            return list(load_robot(description, load_meshes=False).link_names)
        except (ValueError, OSError):
            return None
    try:
        root = etree.parse(os.path.abspath(path / description)).getroot()
    except (OSError, etree.XMLSyntaxError):
        return None
    return [link.get("name") for link in root.iter("link")]


def check_mount_links(path: Path, arms: dict[str, Any], cameras: dict[str, Any]) -> list[Problem]:
    """An error for each version 2 camera mounted on a link its arm's robot description does not have
    (``arms``, ``cameras``: the ``episode.json`` objects; URDF paths relative to ``path``)."""
    problems, links = [], {}
    for name, camera in cameras.items():
        mount = camera.get("mount") if isinstance(camera, dict) else None
        if not (isinstance(mount, str) and mount.count("/") == 1):
            continue
        arm, link = mount.split("/")
        description = arms.get(arm, {}).get("description") if isinstance(arms.get(arm), dict) else None
        if not isinstance(description, str) or not description or not link:
            continue
        if description not in links:
            links[description] = _link_names(path, description)
        known = links[description]
        if known is not None and link not in known:
            problems.append(Problem(META_FILE, None, f"cameras.{name}.mount {mount!r}: arm {arm!r} has no link "
                                                     f"{link!r} (its links: {', '.join(known)})"))
    return problems


def _indices(rows: list[CsvRow]) -> list[tuple[int, int]]:
    """``(line, frame index)`` of every row whose index field reads, even if another field does not
    (so a NaN in ``q3`` is one problem, not also a missing frame)."""
    found = []
    for row in rows:
        if row.values is not None:
            found.append((row.line, int(row.values[0])))
        else:
            with contextlib.suppress(ValueError):
                found.append((row.line, int(row.text.split(",", 1)[0])))
    return found


def _check_frames(path: Path, facts: _Facts) -> tuple[list[Problem], dict[int, int] | None, int]:
    """Problems of ``frames.csv``, its frame index -> first line (None when unusable), and its row count."""
    try:
        scan = scan_csv(path / FRAMES_FILE, facts.layout.frame_columns, ("index",))
    except FileNotFoundError:
        return [Problem(FRAMES_FILE, None, "missing")], None, 0
    problems = []
    if scan.header_problem:
        problems.append(Problem(FRAMES_FILE, 1, scan.header_problem))
    problems += [Problem(FRAMES_FILE, r.line, r.problem) for r in scan.rows if r.problem]
    if facts.frame_count is not None and len(scan.rows) != facts.frame_count:
        problems.append(Problem(FRAMES_FILE, None, f"has {len(scan.rows)} rows but {META_FILE} "
                                                   f"frame_count is {facts.frame_count}"))
    if scan.header_problem:
        return problems, None, len(scan.rows)
    if not scan.rows:
        problems.append(Problem(FRAMES_FILE, None, "holds no frame (only its header): an episode needs at least "
                                                   "one frame"))

    rows: dict[int, int] = {}
    previous = -1
    for line, index in _indices(scan.rows):
        if index in rows:
            problems.append(Problem(FRAMES_FILE, line, f"duplicate index {index} (also on line {rows[index]})"))
            continue
        if index < 0:
            problems.append(Problem(FRAMES_FILE, line, f"index {index} is negative"))
        elif index > previous + 1:
            gap = f"{previous + 1}" if index == previous + 2 else f"{previous + 1}..{index - 1}"
            problems.append(Problem(FRAMES_FILE, line,
                                    f"index jumps from {previous} to {index}: frame(s) {gap} missing"))
        elif index < previous:
            problems.append(Problem(FRAMES_FILE, line, f"index {index} after {previous}: rows out of order"))
        rows[index] = line
        previous = max(previous, index)

    lines, values = scan.parsed()
    t = values[:, 1]
    for k in np.flatnonzero(np.diff(t) <= 0) + 1:
        problems.append(Problem(FRAMES_FILE, int(lines[k]), f"t={t[k]!r} is not after t={t[k - 1]!r} of line "
                                                            f"{lines[k - 1]}: t must be strictly increasing"))
    lo, hi = GRIPPER_RANGE_M
    for arm in facts.layout.arms:
        column = arm.state[-1]
        gripper = values[:, scan.columns.index(column)]
        outside = np.flatnonzero((gripper < lo) | (gripper > hi))
        if outside.size:
            k = outside[0]
            problems.append(Problem(FRAMES_FILE, int(lines[k]), f"{column} outside [{lo}, {hi}] m on {outside.size} "
                                                                f"row(s), first {gripper[k]!r} m", "warning"))
    return problems, rows, len(scan.rows)


def _check_images(path: Path, kind: ImageKind, camera: CameraFiles, rows: dict[int, int] | None, facts: _Facts,
                  decode: bool, progress: bool) -> list[Problem]:
    rel = camera.folder(kind)
    folder = path / rel
    if kind is RGB and not folder.is_dir():
        return [Problem(f"{rel}/", None, "missing folder (every frame needs an rgb image)")]
    by_index, others = list_images(folder)
    problems = []
    width, height = facts.sizes.get(camera.name, (None, None))
    for name in others:
        why = ("temporary file of an interrupted write (run `manisplat-episode recover`)"
               if name.endswith(TMP_SUFFIX) else "unexpected file (not a frame image)")
        problems.append(Problem(f"{rel}/{name}", None, why, "warning"))
    if not by_index and kind is not RGB:
        return problems
    if kind is DEPTH and facts.readable and facts.depth_scale is None:
        problems.append(Problem(META_FILE, None, f"{rel}/ holds images but depth_scale is missing or not positive"))

    suffixes = Counter(n[-4:] for names in by_index.values() for n in names)
    usual = suffixes.most_common(1)[0][0] if suffixes else kind.suffixes[0]
    if rows is not None:
        for index, line in rows.items():
            if index not in by_index:
                problems.append(Problem(f"{rel}/{image_name(index, usual)}", line,
                                        "missing image for this frame"))
        for index in sorted(set(by_index) - set(rows)):
            problems.append(Problem(f"{rel}/{by_index[index][0]}", None,
                                    f"extra frame: no row in {FRAMES_FILE} has index {index}"))

    unlabelled: dict[int, str] = {}
    for index, names in tqdm(sorted(by_index.items()), desc=f"{path.name}/{rel}", unit="img",
                             disable=not progress, leave=False):
        file = f"{rel}/{names[0]}"
        line = rows.get(index) if rows is not None else None
        if len(names) > 1:
            problems.append(Problem(file, line, f"several files for frame {index}: {', '.join(names)}"))
        if names[0][-4:] not in kind.suffixes:
            problems.append(Problem(file, line, f"{kind.folder} images must be {' or '.join(kind.suffixes)}"))
        if not decode:
            if (folder / names[0]).stat().st_size == 0:
                problems.append(Problem(file, line, "empty file"))
            continue
        image = decode_image(folder / names[0])
        if image is None:
            problems.append(Problem(file, line, "cannot decode (truncated or corrupt)"))
            continue
        problem = image_problem(image, kind, width, height)
        if problem:
            problems.append(Problem(file, line, problem))
        elif kind is MASK and facts.labels is not None:
            for value in np.unique(image).tolist():
                if value not in facts.labels:
                    unlabelled.setdefault(value, file)
    for value, file in sorted(unlabelled.items()):
        problems.append(Problem(file, None, f"mask value {value} is not in {META_FILE} labels "
                                            f"(first seen here)", "warning"))
    return problems


def _check_image_folders(path: Path, layout: Layout) -> list[Problem]:
    """Version 2: what ``rgb/``, ``depth/`` and ``masks/`` hold besides the cameras' folders."""
    problems = []
    names = {c.subfolder for c in layout.cameras}
    for kind in KINDS:
        folder = path / kind.folder
        if not folder.is_dir():
            continue
        for entry in sorted(folder.iterdir()):
            if entry.is_dir() and entry.name in names:
                continue
            what = ("a folder of no camera in episode.json" if entry.is_dir()
                    else "a file outside the cameras' folders")
            problems.append(Problem(f"{kind.folder}/{entry.name}", None,
                                    f"unexpected: {what} (cameras: {', '.join(sorted(names))})", "warning"))
    return problems


def _check_joints(path: Path, file: str) -> list[Problem]:
    if not (path / file).is_file():
        return []
    scan = scan_csv(path / file, JOINT_COLUMNS)
    problems = []
    if scan.header_problem:
        return [Problem(file, 1, scan.header_problem)]
    problems += [Problem(file, r.line, r.problem) for r in scan.rows if r.problem]
    lines, values = scan.parsed()
    t = values[:, 0]
    for k in np.flatnonzero(np.diff(t) <= 0) + 1:
        problems.append(Problem(file, int(lines[k]), f"t={t[k]!r} is not after t={t[k - 1]!r} of line "
                                                     f"{lines[k - 1]}: t must be strictly increasing"))
    return problems


def _check_gt(path: Path, facts: _Facts, frame_rows: int) -> list[Problem]:
    """Problems of ``gt.npz``: unreadable, or a per-frame array not as long as ``frames.csv``."""
    if not (path / GT_FILE).is_file():
        return []
    try:
        arrays = read_gt(path / GT_FILE)
    except EpisodeFormatError as exc:
        return [Problem(GT_FILE, None, str(exc).removeprefix(f"{path / GT_FILE}: "))]
    return [Problem(GT_FILE, None, m) for m in frame_count_problems(arrays, facts.objects or [], frame_rows)]


def validate(path: str | Path, *, decode_images: bool = True, progress: bool = False) -> ValidationReport:
    """Check every file of the episode folder ``path`` and report all problems found.

    Checks ``episode.json`` (fields, K, T_mount_cam, complete flag), ``frames.csv`` (header, every
    row, indices 0..T-1, strictly increasing t, row count, gripper range), the images of every
    row in ``rgb/`` and, when present, ``depth/`` and ``masks/`` (present, no extra ones, fully
    decodable, channels, bit depth and size; mask values in ``labels``), ``joints.csv``, and the
    per-frame arrays of ``gt.npz`` (one row per ``frames.csv`` row). A ``robot.description``
    URDF that is not there is a warning. A version 2 episode is checked for every arm (its
    columns, its ``joints_<arm>.csv``, its description) and every camera (its image folders at
    its own size, its mount on an existing arm and link or ``world``).

    Args:
        path: episode folder.
        decode_images: decode every image fully (catches truncation); False only checks that
            the files exist and are not empty (``--quick``).
        progress: show a tqdm progress bar over the images.
    """
    path = Path(path)
    report = ValidationReport(path)
    if not path.is_dir():
        report.problems.append(Problem(".", None, f"{path} is not a folder"))
        return report
    meta_problems_, facts = _check_meta(path)
    frame_problems, rows, report.frame_rows = _check_frames(path, facts)
    report.problems += meta_problems_ + frame_problems
    layout = facts.layout
    if layout.version != 1:
        report.problems += _check_image_folders(path, layout)
    for camera in layout.cameras:
        for kind in KINDS:
            report.problems += _check_images(path, kind, camera, rows, facts, decode_images, progress)
    for arm in layout.arms:
        report.problems += _check_joints(path, arm.joints_file)
    if rows is not None:
        report.problems += _check_gt(path, facts, report.frame_rows)
    return report
