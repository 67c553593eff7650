"""Keep an episode's ``robot.description`` (every arm's, in version 2) resolving when the episode moves: point it elsewhere
(``set_robot``), copy an episode with it rewritten (``copy_episode``), or embed the URDF and its
meshes in the episode (``embed_urdf``), so that the episode is self-contained.

A relative description is read from the episode folder, so it breaks when the episode is copied
elsewhere. An embedded robot lives in ``<episode>/robot/``: the URDF at its top, every mesh and
texture it references under ``robot/meshes/``, the copy's paths rewritten to them.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from lxml import etree

from manisplat.episode.format import META_FILE, VERSION, EpisodeFormatError
from manisplat.episode.meta import ArmInfo, EpisodeMeta, load_meta, save_meta
from manisplat.episode.writer import check_destination
from manisplat.robot import description_file, load_robot

ROBOT_DIR = "robot"
"""Folder of an embedded robot description inside the episode."""
_REFERENCING = ("mesh", "texture")  # URDF elements whose ``filename`` names a file


def _referenced_file(filename: str, urdf: Path) -> Path:
    """The file a URDF ``filename`` attribute names: relative to the URDF, ``file://``, absolute,
    or ``package://<package>/...`` with the package being a folder named so above the URDF (or
    beside one of its parent folders), as in a ROS workspace."""
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://"):].partition("/")
        folders = [urdf.parent, *urdf.parent.parents]
        roots = [f for f in folders if f.name == package] + [f / package for f in folders if (f / package).is_dir()]
        if not roots:
            raise FileNotFoundError(f"{urdf}: {filename}: no folder named {package!r} above the URDF or beside "
                                    "one of its parent folders")
        file = roots[0] / rest
    elif filename.startswith("file://"):
        file = Path(filename[len("file://"):])
    else:
        file = urdf.parent / filename
    if not file.is_file():
        raise FileNotFoundError(f"{urdf}: {filename} not found (looked at {file})")
    return file


def embed_urdf(urdf: Path, folder: Path) -> Path:
    """Copy ``urdf`` into the new ``folder`` and every mesh and texture it references into
    ``folder/meshes/``, rewriting the copy's paths to them; returns the copied URDF."""
    try:
        tree = etree.parse(str(urdf), etree.XMLParser(recover=False))
    except etree.XMLSyntaxError as exc:
        raise ValueError(f"{urdf}: not a readable URDF ({exc})") from None
    folder.mkdir(parents=True)
    copies: dict[Path, str] = {}
    for element in tree.getroot().iter(*_REFERENCING):
        filename = element.get("filename")
        if not filename:
            continue
        source = _referenced_file(filename, urdf).resolve()
        if source not in copies:
            name, n = source.name, 1
            while name in {Path(c).name for c in copies.values()}:
                name, n = f"{source.stem}_{n}{source.suffix}", n + 1
            (folder / "meshes").mkdir(exist_ok=True)
            shutil.copy2(source, folder / "meshes" / name)
            copies[source] = f"meshes/{name}"
        element.set("filename", copies[source])
    tree.write(str(folder / urdf.name), xml_declaration=True, encoding="utf-8")
    return folder / urdf.name


def _reference(file: Path, episode: Path) -> str:
    """How ``episode.json`` names ``file``: relative when it lies inside the episode (it moves
    with it), absolute otherwise."""
    file, episode = file.resolve(), episode.resolve()
    return str(file.relative_to(episode)) if file.is_relative_to(episode) else str(file)


def _replace_folder(new: Path, target: Path) -> None:
    """Put the folder ``new`` at ``target``, replacing what is there (removed only once ``new`` is in place)."""
    old = target.with_name(f".{target.name}.old")
    if target.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(target, old)
    os.replace(new, target)
    if old.exists():
        shutil.rmtree(old)


def _fresh(path: Path) -> Path:
    """``path`` for a temporary folder of ours: what an interrupted run left there is removed."""
    if path.exists():
        shutil.rmtree(path)
    return path


def _arm(meta: EpisodeMeta, arm: str | None) -> ArmInfo:
    """The arm ``arm`` names, or the one arm; raises :class:`EpisodeFormatError` naming the arms."""
    if arm is None:
        if len(meta.arms) != 1:
            raise EpisodeFormatError(f"{meta.origin} has arms {', '.join(meta.arms)}: name one (--arm NAME)")
        return next(iter(meta.arms.values()))
    if arm not in meta.arms:
        raise EpisodeFormatError(f"{meta.origin} has no arm {arm!r}; arms: {', '.join(meta.arms)}")
    return meta.arms[arm]


def set_robot(episode: str | Path, description: str | None = None, *, arm: str | None = None, embed: bool = False,
              overwrite: bool = False) -> tuple[str, str]:
    """Point the episode's ``robot.description`` (a version 2 arm's description) at another robot
    description, or embed it.

    Args:
        episode: episode folder.
        description: a ``builtin:`` name or a URDF path (relative to the current folder); it is
            stored relative to the episode when it lies inside it, absolute otherwise. Default:
            the episode's current description.
        arm: the arm of a version 2 episode (needed when it has several).
        embed: copy the URDF and its meshes into ``<episode>/robot/`` (``robot/<arm>/`` in
            version 2) and point there.
        overwrite: replace an existing ``<episode>/robot/`` (``robot/<arm>/``) when embedding.

    The description is loaded first (with its meshes when embedded); ``episode.json`` is then
    rewritten atomically. Returns ``(old, new)`` descriptions.

    Raises:
        FileNotFoundError, RobotModelError: the description does not resolve or load.
        FileExistsError: ``robot/`` exists and not ``overwrite``.
        ValueError: ``embed`` with a built-in description (nothing to embed); EpisodeFormatError:
            no such arm, or no ``arm`` for an episode with several.
    """
    path = Path(episode)
    meta = load_meta(path / META_FILE)
    chosen = _arm(meta, arm)
    old = chosen.description
    base = path if description is None else Path.cwd()
    description = old if description is None else description
    file = description_file(description, base)
    if not embed:
        new = description if file is None else _reference(file, path)
        load_robot(new, base_dir=path, load_meshes=False)
    else:
        if file is None:
            raise ValueError(f"{description} is built in: nothing to embed")
        folder = ROBOT_DIR if meta.version == VERSION else f"{ROBOT_DIR}/{chosen.name}"
        target = path / folder
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target}: exists (an embedded robot); replace it with --overwrite")
        staging = _fresh(path / f".{folder.replace('/', '-')}.tmp")
        try:
            load_robot(str(embed_urdf(file, staging)))
            target.parent.mkdir(exist_ok=True)
            _replace_folder(staging, target)
        finally:
            if staging.exists():
                shutil.rmtree(staging)
        new = f"{folder}/{file.name}"
    chosen.description = new
    save_meta(path / META_FILE, meta)
    return old, new


def _relocate_descriptions(meta: EpisodeMeta, src: Path, staging: Path, embed: bool) -> dict[str, tuple[str, str]]:
    """Rewrite, in ``meta``, every arm's description that points outside ``src``: absolute, or
    with ``embed`` copied into ``staging/robot/`` (``robot/<arm>/`` when the arms use different
    URDFs). Returns arm name -> ``(old, new)``."""
    changes: dict[str, tuple[str, str]] = {}
    outside: dict[Path, list[str]] = {}  # URDF outside src -> the arms that use it
    for name, arm in meta.arms.items():
        file = description_file(arm.description, src)
        changes[name] = (arm.description, arm.description)
        if file is not None and not file.resolve().is_relative_to(src.resolve()):
            outside.setdefault(file.resolve(), []).append(name)
    for file, names in outside.items():
        if embed:
            folder = ROBOT_DIR if len(outside) == 1 else f"{ROBOT_DIR}/{names[0]}"
            if (staging / folder).exists():
                raise FileExistsError(f"{src / folder}: exists but the robot description points elsewhere "
                                      f"({meta.arms[names[0]].description}); embed into the copy with "
                                      "`manisplat-episode set-robot`")
            new = f"{folder}/{embed_urdf(file, staging / folder).name}"
        for name in names:
            old = meta.arms[name].description
            if not embed:
                new = old if Path(old).is_absolute() else str(file)
            meta.arms[name].description = new
            changes[name] = (old, new)
    return changes


def copy_episode(source: str | Path, destination: str | Path, *, embed: bool = False,
                 overwrite: bool = False) -> tuple[str, str]:
    """Copy the episode ``source`` (every file, ``.recovered/`` included) to ``destination`` so
    that the robot description of each of its arms still resolves there.

    A relative description pointing outside ``source`` becomes absolute; with ``embed`` the URDF
    and its meshes are copied into ``destination/robot/`` instead (``robot/<arm>/`` per URDF when
    the arms of a version 2 episode use different ones). Built-in names, absolute paths and files
    inside ``source`` are kept. The copy is made in a temporary folder beside ``destination`` and
    renamed into place; an episode already there is replaced only with ``overwrite`` (after the
    copy succeeded). Returns ``(old, new)`` descriptions (with several arms, each is
    ``"<arm>: <description>"`` joined by ``"; "``).

    Raises:
        FileNotFoundError, RobotModelError: a description does not resolve.
        FileExistsError: ``destination`` is refused (see :func:`check_destination`).
        ValueError: ``destination`` is ``source`` or inside it.
    """
    src, dst = Path(source), Path(destination)
    meta = load_meta(src / META_FILE)
    if dst.resolve().is_relative_to(src.resolve()):
        raise ValueError(f"{dst} is {src} or inside it: copy the episode elsewhere")
    for arm in meta.arms.values():
        description_file(arm.description, src)  # raises when it does not resolve
    check_destination(dst, overwrite)
    dst.parent.mkdir(parents=True, exist_ok=True)
    staging = _fresh(dst.with_name(f".{dst.name}.copy.tmp"))
    try:
        shutil.copytree(src, staging)
        changes = _relocate_descriptions(meta, src, staging, embed)
        if any(old != new for old, new in changes.values()):
            save_meta(staging / META_FILE, meta)
        for arm in meta.arms.values():
            load_robot(arm.description, base_dir=staging, load_meshes=embed)
        _replace_folder(staging, dst)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    if len(changes) == 1:
        return next(iter(changes.values()))
    return tuple("; ".join(f"{name}: {pair[k]}" for name, pair in changes.items()) for k in (0, 1))
