"""A readable summary of an episode (what ``manisplat-episode info`` prints)."""

from __future__ import annotations

import numpy as np

from manisplat.episode.format import GT_FILE, JOINTS_FILE
from manisplat.episode.images import DEPTH, KINDS, StoredChroma, describe_chroma, list_images
from manisplat.episode.layout import CameraFiles
from manisplat.episode.meta import CameraInfo
from manisplat.episode.reader import Episode, FrameTable


def _rate(t: np.ndarray, detail: bool = True) -> str:
    """Measured rate of timestamps ``t`` (N,) seconds, from the median interval (and its spread)."""
    if len(t) < 2:
        return "n/a (fewer than 2 samples)"
    dt = np.diff(t)
    text = f"{1.0 / np.median(dt):.3f} Hz"
    if detail:
        text += (f" (interval median {1e3 * np.median(dt):.2f} ms, "
                 f"min {1e3 * dt.min():.2f}, max {1e3 * dt.max():.2f})")
    return text


def _joint_lines(frames: FrameTable, indent: str = "") -> list[str]:
    if not len(frames):
        return []
    deg = np.degrees(frames.q)
    return [f"{indent}joints    " + "  ".join(f"q{j + 1} [{_one_decimal(deg[:, j].min())}, "
                                            f"{_one_decimal(deg[:, j].max())}]" for j in range(6)) + " deg",
            f"{indent}gripper   [{1e3 * frames.gripper.min():.1f}, {1e3 * frames.gripper.max():.1f}] mm"]


def _camera_text(cam: CameraInfo, colour: StoredChroma | None) -> str:
    return (f"{cam.width}x{cam.height}, fx={cam.K[0, 0]:.2f} fy={cam.K[1, 1]:.2f} "
            f"cx={cam.K[0, 2]:.2f} cy={cam.K[1, 2]:.2f}, dist {cam.dist.tolist() or 'none'}, mount {cam.mount}, "
            f"T_mount_cam {'set' if cam.T_mount_cam is not None else 'null (uncalibrated)'}, "
            f"colour stored {describe_chroma(colour)}")


def _image_files(episode: Episode, files: CameraFiles) -> list[str]:
    found = []
    for kind in KINDS:
        rel = files.folder(kind)
        by_index = list_images(episode.path / rel)[0]
        if by_index:
            suffixes = sorted({n[-3:] for names in by_index.values() for n in names})
            found.append(f"{rel}/ {len(by_index)} {'/'.join(suffixes)}"
                         + (f" (depth_scale {episode.meta.depth_scale:g} m)"
                            if kind is DEPTH and episode.meta.depth_scale else ""))
    return found


def describe(episode: Episode) -> str:
    """Several lines: format version, frames, duration, declared vs measured fps, and per arm its
    robot, base, joint ranges (degrees), gripper range (mm), per camera its size, intrinsics,
    mount, how its images kept their colour and files, then the other files present and the ``complete`` flag."""
    if episode.meta.version != 1:
        return _describe_v2(episode)
    meta, frames, cam = episode.meta, episode.frames, episode.camera
    n = len(frames)
    duration = float(frames.t[-1] - frames.t[0]) if n else 0.0
    lines = [
        f"episode   {episode.path}",
        f"format    version {meta.version} (one arm, one camera)",
        f"complete  {'yes' if meta.complete else 'NO: run `manisplat-episode recover`'}",
        f"source    {meta.source}, created {meta.created}",
        f"frames    {n} (frame_count {meta.frame_count}), duration {duration:.3f} s",
        f"fps       declared {meta.fps:g}, measured {_rate(frames.t)}",
        f"camera    {cam.name} {_camera_text(cam, episode.chroma_subsampling())}",
        f"robot     {meta.robot.model}, angles per {meta.robot.description}",
    ]
    lines += _joint_lines(frames)
    if frames.extra:
        lines.append(f"columns   {', '.join(frames.extra)}" + (" (actions)" if frames.actions is not None else ""))
    files = _image_files(episode, episode.layout.cameras[0])
    joints = episode.joints()
    if joints is not None:
        files.append(f"{JOINTS_FILE} {len(joints)} rows at {_rate(joints.t, detail=False)}")
    if (episode.path / GT_FILE).is_file():
        files.append(GT_FILE)
    lines.append(f"files     {'; '.join(files)}")
    return "\n".join(lines + _labels_lines(episode))


def _labels_lines(episode: Episode) -> list[str]:
    meta, lines = episode.meta, []
    if meta.labels:
        lines.append(f"labels    {len(meta.labels)}: " + ", ".join(f"{k}={v}" for k, v in sorted(meta.labels.items())))
    if meta.objects:
        lines.append(f"objects   {', '.join(meta.objects)}")
    return lines


def _describe_v2(episode: Episode) -> str:
    meta, layout = episode.meta, episode.layout
    t = episode.arm_frames(layout.arms[0].name).t
    n = len(t)
    duration = float(t[-1] - t[0]) if n else 0.0
    lines = [
        f"episode   {episode.path}",
        f"format    version {meta.version}: {len(meta.arms)} arm(s) {', '.join(meta.arms)}; "
        f"{len(meta.cameras)} camera(s) {', '.join(meta.cameras)}",
        f"complete  {'yes' if meta.complete else 'NO: run `manisplat-episode recover`'}",
        f"source    {meta.source}, created {meta.created}",
        f"frames    {n} (frame_count {meta.frame_count}), duration {duration:.3f} s",
        f"fps       declared {meta.fps:g}, measured {_rate(t)}",
    ]
    for name, arm in meta.arms.items():
        frames = episode.arm_frames(name)
        base = ("null (uncalibrated)" if arm.T_world_base is None
                else "at (" + ", ".join(f"{x:.3f}" for x in arm.T_world_base[:3, 3]) + ") m")
        lines.append(f"arm {name}: {arm.model}, angles per {arm.description}, base {base}"
                     + (", actions" if frames.actions is not None else ""))
        lines += _joint_lines(frames, "  ")
        joints = episode.joints(name)
        if joints is not None:
            lines.append(f"  stream    {layout.arm(name).joints_file} {len(joints)} rows at "
                         f"{_rate(joints.t, detail=False)}")
    for files in layout.cameras:
        cam = meta.cameras[files.name]
        own_t = files.time_column in episode.columns
        lines.append(f"camera {files.name}: {_camera_text(cam, episode.chroma_subsampling(files.name))}"
                     + (f", own times ({files.time_column})" if own_t else ""))
        lines.append(f"  files     {'; '.join(_image_files(episode, files)) or 'none'}")
    owned = {c for a in layout.arms for c in episode.columns if a.owns(c)}
    shared = [c for c in episode.columns if c not in layout.frame_columns and c not in owned]
    if shared:
        lines.append(f"columns   {', '.join(shared)}")
    if (episode.path / GT_FILE).is_file():
        lines.append(f"files     {GT_FILE}")
    return "\n".join(lines + _labels_lines(episode))


def _one_decimal(x: float) -> str:
    """``x`` to one decimal, without the "-0.0" of a tiny negative."""
    text = f"{x:.1f}"
    return "0.0" if text == "-0.0" else text
