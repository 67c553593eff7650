"""A readable summary of an episode (what ``manisplat-episode info`` prints)."""

from __future__ import annotations

import numpy as np

from manisplat.episode.format import GT_FILE, JOINTS_FILE
from manisplat.episode.images import DEPTH, KINDS, list_images
from manisplat.episode.reader import Episode


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


def describe(episode: Episode) -> str:
    """Several lines: frames, duration, declared vs measured fps, joint ranges (degrees),
    gripper range (mm), camera, robot, files present and the ``complete`` flag."""
    meta, frames, cam = episode.meta, episode.frames, episode.camera
    n = len(frames)
    duration = float(frames.t[-1] - frames.t[0]) if n else 0.0
    lines = [
        f"episode   {episode.path}",
        f"complete  {'yes' if meta.complete else 'NO: run `manisplat-episode recover`'}",
        f"source    {meta.source}, created {meta.created}",
        f"frames    {n} (frame_count {meta.frame_count}), duration {duration:.3f} s",
        f"fps       declared {meta.fps:g}, measured {_rate(frames.t)}",
        f"camera    {cam.name} {cam.width}x{cam.height}, fx={cam.K[0, 0]:.2f} fy={cam.K[1, 1]:.2f} "
        f"cx={cam.K[0, 2]:.2f} cy={cam.K[1, 2]:.2f}, dist {cam.dist.tolist() or 'none'}, mount {cam.mount}, "
        f"T_mount_cam {'set' if cam.T_mount_cam is not None else 'null (uncalibrated)'}",
        f"robot     {meta.robot.model}, angles per {meta.robot.description}",
    ]
    if n:
        deg = np.degrees(frames.q)
        lines.append("joints    " + "  ".join(f"q{j + 1} [{_one_decimal(deg[:, j].min())}, {_one_decimal(deg[:, j].max())}]"
                                              for j in range(6)) + " deg")
        lines.append(f"gripper   [{1e3 * frames.gripper.min():.1f}, {1e3 * frames.gripper.max():.1f}] mm")
    if frames.extra:
        lines.append(f"columns   {', '.join(frames.extra)}" + (" (actions)" if frames.actions is not None else ""))
    files = []
    for kind in KINDS:
        by_index = list_images(episode.path / kind.folder)[0]
        if by_index:
            suffixes = sorted({n[-3:] for names in by_index.values() for n in names})
            files.append(f"{kind.folder}/ {len(by_index)} {'/'.join(suffixes)}"
                         + (f" (depth_scale {meta.depth_scale:g} m)" if kind is DEPTH and meta.depth_scale else ""))
    joints = episode.joints()
    if joints is not None:
        files.append(f"{JOINTS_FILE} {len(joints)} rows at {_rate(joints.t, detail=False)}")
    if (episode.path / GT_FILE).is_file():
        files.append(GT_FILE)
    lines.append(f"files     {'; '.join(files)}")
    if meta.labels:
        lines.append(f"labels    {len(meta.labels)}: " + ", ".join(f"{k}={v}" for k, v in sorted(meta.labels.items())))
    if meta.objects:
        lines.append(f"objects   {', '.join(meta.objects)}")
    return "\n".join(lines)


def _one_decimal(x: float) -> str:
    """``x`` to one decimal, without the "-0.0" of a tiny negative."""
    text = f"{x:.1f}"
    return "0.0" if text == "-0.0" else text
