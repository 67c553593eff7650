"""What ``manisplat-reconstruct`` writes into its output folder.

* ``twin.json`` + ``twin.pt``: the twin, loadable with :meth:`manisplat.twin.Twin.load` (every
  arm and every camera trained; :mod:`manisplat.twin.files`).
* ``<node>.ply`` per node (background in the base frame, ``robot_<link>.ply`` in link frames,
  ``object_<name>.ply`` in the canonical object frame), 3DGS layout.
* ``object_poses.csv`` per object: ``frame, t, source, T_base_obj`` (16 numbers, row-major).
* ``phases.csv``: ``frame, t, phase`` per object.
* ``renders/test/NNNNNN.png``: the rendered RGB of every held-out frame, named by frame index, as
  the camera records it (its colour subsampled as the recording's: :mod:`manisplat.reconstruct.chroma`);
  ``renders/sheets/NNNNNN.png``: ground truth | render | error x4, labelled, with the frame and time.
* ``pose_plot.png``: rotation and translation per frame (ours, the phase-free baseline, ground truth).
* ``metrics.json``: ``psnr`` / ``ssim`` ({"full", "robot", "object"}; the same with the held-out
  frame's colour fitted on its static pixels: ``psnr_colour_fitted``, ``ssim_colour_fitted``; for a
  camera whose recording subsampled its colour, ``psnr_full_colour``: the render as drawn;
  ``psnr_per_frame``: the held-out ``frames`` and each one's PSNR per region), ``pose`` and
  ``pose_baseline`` ({object: {"et_cm", "er_deg"}}) when ground truth exists, ``wall_s``,
  ``iters``, ``plan``, ``camera`` (the extrinsic correction, when checked), ``rig`` (several arms
  or riding cameras: each other arm's base and each riding camera's ``T_mount_cam`` as checked,
  :mod:`manisplat.reconstruct.rig_check`); with shadows learned,
  ``light`` (the direction towards it in the base frame, its elevation and azimuth in deg, the
  per-channel strength) and ``shadow``: PSNR over the held-out frames' background pixels the
  learned shadows darken by more than :data:`SHADOWED` (``psnr``), the same pixels rendered
  without shadows (``psnr_without_shadows``: a shadow in the wrong place scores below it), and
  their share of the image (``pixels``).
* ``exposure.csv``: per frame, held out or not, the learned per-channel exposure gain.
* ``camera_refined.json`` (one arm): the camera as the reconstruction used it, in the
  ``manisplat-calibration`` format (``manisplat-calibrate apply camera_refined.json EPISODE``
  writes it back), with ``correction`` (deg, mm, 1-sigma, residuals) against the episode's.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import torch

from manisplat.align.phases import phase_of_frames
from manisplat.reconstruct.chroma import subsampled
from manisplat.reconstruct.data import EpisodeData, load_ground_truth
from manisplat.reconstruct.fusion import EpisodeSpan
from manisplat.reconstruct.metrics import fit_constant_offset, pose_errors, psnr, ssim, start_anchored_errors
from manisplat.reconstruct.trainer import Reconstruction
from manisplat.render.sheets import labelled_sheet
from manisplat.robot.arms import ArmSet
from manisplat.splat import save_ply
from manisplat.twin import Demonstration, Phase, Twin
from manisplat.twin.rig import TwinCamera
from manisplat.twin.support import SupportMap, support_map

log = logging.getLogger(__name__)


# What a run writes into --out (globs), removed by --overwrite; nothing else there is touched.
OWNED_OUTPUTS = ("twin.json", "twin.pt", "background.ply", "robot_*.ply", "object_*.ply", "object_poses*.csv", "phases.csv", "renders",
                 "pose_plot.png", "metrics.json", "checkpoint.pt", "checkpoint.pt.tmp",
                 "camera_refined.json", "exposure.csv", "episodes")


def remove_outputs(out: Path) -> int:
    """Remove what an earlier run wrote into ``out`` (:data:`OWNED_OUTPUTS`); return how many files."""
    removed = 0
    for pattern in OWNED_OUTPUTS:
        for path in sorted(out.glob(pattern)):
            if path.is_dir():
                removed += sum(1 for f in path.rglob("*") if f.is_file())
                shutil.rmtree(path)
            else:
                path.unlink()
                removed += 1
    return removed


def write_twin(rec: Reconstruction, alignments: dict, out: Path, spans: list[EpisodeSpan] | None = None) -> None:
    """The trained twin: every node's PLY, the object poses and the phases (no evaluation); for
    a fused recording (``spans``) the poses, phases and exposure per episode in ``episodes/<name>/``."""
    out.mkdir(parents=True, exist_ok=True)
    for node in rec.graph.nodes():
        save_ply(out / f"{node.name.replace('/', '_')}.ply", node.gaussians.ply_dict())
    evaluation = rec.evaluation_poses()
    t = rec.data.t.cpu().numpy()
    for span, parts in episode_alignments(rec, alignments, spans):
        folder = out / "episodes" / span.name if spans else out
        folder.mkdir(parents=True, exist_ok=True)
        frames = slice(span.start, span.end)
        for name, poses in evaluation.items():
            _write_poses(folder / (f"object_poses_{name}.csv" if len(evaluation) > 1 else "object_poses.csv"),
                         t[frames], poses[frames], parts[name].pseudo.source)
        _write_phases(folder / "phases.csv", t[frames], parts)
        if rec.exposure is not None:
            _write_exposure(folder / "exposure.csv", rec, span.frames)
    twin_of(rec, alignments, spans).save(out)
    if isinstance(rec.data.robot, ArmSet):
        log.info("several arms: camera_refined.json is not written (a calibration file holds one arm's camera); "
                 "the head camera's extrinsic as trained is in twin.json")
    else:
        (out / "camera_refined.json").write_text(json.dumps(camera_refined(rec), indent=1) + "\n")


def _write_exposure(path: Path, rec: Reconstruction, frames: range) -> None:
    """Per frame of ``frames`` (numbered from the first): whether it was held out and the learned
    per-channel gain (held-out frames': interpolated between training neighbours)."""
    held_out = set(rec.plan.test_frames)
    gains = rec.exposure.gains()
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "held_out", "gain_r", "gain_g", "gain_b"])
        for f in frames:
            w.writerow([f - frames.start, int(f in held_out)] + [f"{g:.5f}" for g in gains[f]])


def camera_refined(rec: Reconstruction) -> dict:
    """The camera the twin was trained with, as a ``manisplat-calibration`` file: the episode's
    intrinsics and distortion, the refined ``T_mount_cam`` (mount ``base``), ``latency_s`` (the
    camera latency the joints were paired with: the recorder's plus the offset found), and ``correction``:
    how far it is from the episode's (rotation deg, camera centre mm), with what the robot's depth
    said (:mod:`manisplat.reconstruct.extrinsic`) and the photometric share (``--refine-camera``)."""
    from manisplat.calib.result import FORMAT, VERSION
    from manisplat.episode import Episode
    from manisplat.episode.meta import utc_now
    from manisplat.reconstruct.extrinsic import pose_difference

    cam = Episode.open(rec.data.path).camera
    T_recorded = np.asarray(cam.T_mount_cam, dtype=np.float64)
    T_used = np.linalg.inv(rec.viewmat().detach().double().cpu().numpy())
    rotation, translation = pose_difference(T_recorded, T_used)
    correction = {"rotation_deg": rotation, "translation_mm": translation,
                  "T_correction": (np.linalg.inv(T_recorded) @ T_used).tolist(),
                  "robot_depth": rec.extrinsic.to_dict() if rec.extrinsic is not None else None,
                  "photometric": bool(rec.config.refine_camera)}
    return {"format": FORMAT, "version": VERSION, "date": utc_now(), "K": cam.K.tolist(), "dist": cam.dist.tolist(),
            "width": cam.width, "height": cam.height, "mount": "base", "T_mount_cam": T_used.tolist(),
            "latency_s": rec.data.recorded_latency_s - rec.data.time_offset_s, "source": "manisplat-reconstruct", "episode": str(rec.data.path),
            "correction": correction}


def twin_of(rec: Reconstruction, alignments: dict, spans: list[EpisodeSpan] | None = None) -> Twin:
    """The trained reconstruction as a :class:`~manisplat.twin.Twin` (evaluation poses per frame):
    every arm, every camera trained (the reference first, with its extrinsic as trained), and a
    source demonstration per episode (``spans``: the episodes of a fused recording, None: one)."""
    d = rec.data
    T_base_cam = np.linalg.inv(rec.viewmat().detach().double().cpu().numpy())
    return Twin(
        graph=rec.graph, background_rgb=torch.sigmoid(rec.background_logit.detach()), robot=d.robot,
        arms=list(d.arms), cameras=[_twin_camera(view, T_base_cam if name == d.camera_name else None)
                                    for name, view in rec.views.items()],
        labels=d.label_names, demonstrations=demonstrations_of(rec, alignments, spans),
        backend=rec.config.backend, support=measured_support(rec, T_base_cam),
    )


def episode_alignments(rec: Reconstruction, alignments: dict,
                       spans: list[EpisodeSpan] | None) -> list[tuple[EpisodeSpan, dict]]:
    """(episode, object -> its alignment in that episode) for each episode: the recording's one
    (``spans`` None) or each of a fused recording's (its part of each :class:`~manisplat.reconstruct.fusion.JoinedAlignment`)."""
    if spans is None:
        d = rec.data
        return [(EpisodeSpan(Path(d.path).name, Path(d.path), 0, d.n_frames, d.commands), alignments)]
    return [(span, {name: a.parts[k] for name, a in alignments.items()}) for k, span in enumerate(spans)]


def demonstrations_of(rec: Reconstruction, alignments: dict, spans: list[EpisodeSpan] | None) -> list[Demonstration]:
    """Each episode's demonstration: its frames' joints, trained object poses, pose sources,
    phases and recorded commands."""
    d, evaluation = rec.data, rec.evaluation_poses()
    demos = []
    for span, parts in episode_alignments(rec, alignments, spans):
        frames = slice(span.start, span.end)
        demos.append(Demonstration(
            episode=span.name, fps=d.fps, task=d.task, t=d.t[frames].cpu().numpy(), q=d.q[frames].cpu().numpy(),
            gripper=d.gripper[frames].cpu().numpy(), object_poses={n: p[frames] for n, p in evaluation.items()},
            pose_sources={n: list(a.pseudo.source) for n, a in parts.items()},
            phases={n: [Phase(s.kind, s.name, s.start, s.end) for s in a.segments] for n, a in parts.items()},
            commands=span.commands))
    return demos


def _twin_camera(view: EpisodeData, T_frame_cam: np.ndarray | None = None) -> TwinCamera:
    """A camera's view as the twin keeps it: fixed (at ``T_frame_cam`` when given, the extrinsic as
    trained) or riding on its link with ``T_mount_cam``."""
    if view.riding:
        return TwinCamera(view.camera_name, view.K_opencv.cpu().numpy(), *view.size, view.mount,
                          view.T_mount_cam.double().cpu().numpy())
    T = T_frame_cam if T_frame_cam is not None else np.linalg.inv(view.viewmat.double().cpu().numpy())
    return TwinCamera(view.camera_name, view.K_opencv.cpu().numpy(), *view.size, view.frame, T)


SUPPORT_FRAMES = 60  # training frames the support map's median is taken over (evenly spread)


def measured_support(rec: Reconstruction, T_base_cam: np.ndarray) -> SupportMap | None:
    """The support height map (:mod:`manisplat.twin.support`) from the training frames' depth
    where neither the robot nor an object is; None without depth or masks."""
    d = rec.data
    if d.depth is None or d.masks is None:
        return None
    train = rec.plan.train_frames
    frames = [train[int(k)] for k in np.linspace(0, len(train) - 1, min(SUPPORT_FRAMES, len(train)))]
    moving = torch.tensor(d.labels.moving, dtype=torch.uint8)
    background = ~torch.isin(d.masks[frames].cpu(), moving)
    return support_map(d.depth[frames].cpu().numpy(), background.numpy(), d.K_opencv.cpu().numpy(), T_base_cam)


def write_evaluation(rec: Reconstruction, alignments: dict, out: Path, *, wall_s: float,
                     ms_per_iter: float | None = None, spans: list[EpisodeSpan] | None = None,
                     camera: dict | None = None) -> dict:
    """Held-out renders and sheets, the pose plot and ``metrics.json``; return the metrics dict.
    ``wall_s``: the whole run (s); ``ms_per_iter``: training's time per iteration (ms). For a
    fused recording (``spans``), the figures of each episode in ``episodes`` and their mean at the
    top, the pose error also with one constant offset for every episode (``pose_one_offset``),
    and ``camera`` (each episode's check and the camera agreed on)."""
    evaluation = rec.evaluation_poses()
    metrics = {"psnr": {}, "ssim": {}, "iters": rec.step, "wall_s": round(wall_s, 1), "plan": rec.plan.to_dict(),
               "rasterize_mode": rec.graph.rasterize_mode, "eps2d": rec.graph.eps2d, "lambda_mask": rec.config.lambda_mask,
               "lambda_pose": rec.config.lambda_pose, "lambda_smooth": rec.config.lambda_smooth,
               "sh_degree": rec.config.sh_degree, "light_response": rec.config.light_response,
               "fixed_camera_weight": rec.config.fixed_camera_weight,
               "fixed_camera_share": rec.config.fixed_camera_share,
               "object_position_rate": rec.config.object_position_rate,
               "pose_rate_final": rec.config.pose_rate_final}
    if ms_per_iter is not None:
        metrics["ms_per_iter"] = round(ms_per_iter, 1)
    if spans:
        metrics.update(_fused_metrics(rec, alignments, evaluation, out, spans))
        metrics["plan"] = {k: v for k, v in metrics["plan"].items() if k != "test_frames"}
        if camera is not None:
            metrics["camera"] = camera
    else:
        reference = rec.data.camera_name
        per_camera = {name: _image_metrics(rec, evaluation, out, None if name == reference else name) for name in rec.views}
        metrics.update(per_camera[reference])
        if len(per_camera) > 1:
            metrics["cameras"] = per_camera
        if rec.extrinsic is not None:
            metrics["camera"] = {k: v for k, v in rec.extrinsic.to_dict().items() if k != "T_correction"}
        if rec.rig is not None:
            metrics["rig"] = rec.rig.to_dict()
        gt = load_ground_truth(rec.data.path)  # the only place ground truth is read
        if gt is not None:
            metrics.update(_pose_metrics(rec.data.frame, evaluation, alignments, gt, rec.data.t.cpu().numpy(),
                                         out / "pose_plot.png"))
    if rec.graph.shadows is not None:
        metrics["light"] = _light(rec.graph.shadows)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    return metrics


def _fused_metrics(rec: Reconstruction, alignments: dict, evaluation: dict[str, np.ndarray], out: Path,
                   spans: list[EpisodeSpan]) -> dict:
    """Per episode: the held-out image scores and (with ground truth) the pose errors; their
    means; the pose error with one constant offset over every episode (a start registered wrongly
    in one episode shows there, where each episode's own offset would absorb it)."""
    per_episode, ours_all, gt_all = {}, {}, {}
    t = rec.data.t.cpu().numpy()
    for k, (span, parts) in enumerate(episode_alignments(rec, alignments, spans)):
        frames = slice(span.start, span.end)
        scores = _image_metrics(rec, evaluation, out, frames=[f for f in rec.plan.test_frames if f in span.frames])
        gt = load_ground_truth(span.path)  # the only place ground truth is read
        if gt is not None:
            mine = {n: e[frames] for n, e in evaluation.items()}
            scores.update(_pose_metrics(rec.data.frame, mine, parts, gt, t[frames],
                                        out / "pose_plot.png" if k == 0 else None))
            for n, poses in mine.items():
                key = f"T_{rec.data.frame}_{n}"
                if key in gt:
                    ours_all.setdefault(n, []).append(poses)
                    gt_all.setdefault(n, []).append(gt[key])
        per_episode[span.name] = scores
    out_metrics = {"episodes": per_episode, **_mean_of(list(per_episode.values()))}
    if ours_all:
        out_metrics["pose_one_offset"] = {n: _rounded(pose_errors(np.concatenate(ours_all[n]), np.concatenate(gt_all[n])))
                                          for n in ours_all}
    return out_metrics


def _mean_of(scores: list[dict]) -> dict:
    """The mean over episodes of every number in their score dicts (nested alike; None skipped)."""
    first = scores[0]
    out = {}
    for key, value in first.items():
        if key == "psnr_per_frame":  # each episode's own frames: no mean
            continue
        if isinstance(value, dict):
            out[key] = _mean_of([s[key] for s in scores if isinstance(s.get(key), dict)])
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[key] = _nanmean([s[key] for s in scores if isinstance(s.get(key), (int, float))])
    return out


def _write_poses(path: Path, t: np.ndarray, poses: np.ndarray, source: list[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "t", "source"] + [f"T{r}{c}" for r in range(4) for c in range(4)])
        for i, (ti, T) in enumerate(zip(t, poses)):
            w.writerow([i, f"{ti:.6f}", source[i]] + [repr(float(x)) for x in T.reshape(-1)])


def _write_phases(path: Path, t: np.ndarray, alignments: dict) -> None:
    names = {obj: phase_of_frames(a.segments, len(t)) for obj, a in alignments.items()}
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "t"] + [f"phase_{obj}" if len(names) > 1 else "phase" for obj in names])
        for i, ti in enumerate(t):
            w.writerow([i, f"{ti:.6f}"] + [names[obj][i] for obj in names])


@torch.no_grad()
def _image_metrics(rec: Reconstruction, evaluation: dict[str, np.ndarray], out: Path, camera: str | None = None,
                   frames: list[int] | None = None) -> dict:
    """Held-out renders, sheets and scores of ``camera`` (None: the reference camera, in
    ``renders/test`` and ``renders/sheets``; another in ``renders/<camera>/``): ``psnr`` / ``ssim`` per region with the frame's exposure
    interpolated from its training neighbours, and ``psnr_colour_fitted`` / ``ssim_colour_fitted``
    with an affine colour transform fitted on the frame's own static pixels
    (:func:`colour_fitted`): what the twin gets right apart from a camera's exposure, which no
    training frame can tell for a held-out one. Renders are scored (and written) as the camera
    recorded them, their colour subsampled as its images' was; for such a camera
    ``psnr_full_colour`` scores the render as drawn. ``frames``: those held-out frames (default all)."""
    view = rec.view(camera)
    folder = out / "renders" if camera is None else out / "renders" / camera
    renders, sheets = folder / "test", folder / "sheets"
    renders.mkdir(parents=True, exist_ok=True)
    sheets.mkdir(parents=True, exist_ok=True)
    keys = ("psnr", "ssim", "psnr_colour_fitted", "ssim_colour_fitted", "psnr_full_colour")
    scores = {k: {"full": [], "robot": [], "object": []} for k in keys}
    shadow = {"psnr": [], "psnr_without_shadows": [], "pixels": []}
    frames = list(rec.plan.test_frames if frames is None else frames)
    for f in frames:
        drawn = rec.render(f, evaluation, camera, recorded=False)[0]
        image = rec.as_recorded(drawn, camera).clamp(0, 1)
        target = view.image(f)
        rgb8 = (image.cpu().numpy() * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(renders / f"{f:06d}.png"), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        error = ((image - target).abs().mean(-1, keepdim=True).expand(-1, -1, 3) * 4).clamp(0, 1)
        sheet = (torch.cat([target, image, error], dim=1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        sheet = labelled_sheet(sheet, SHEET_COLUMNS, f"{view.camera_name} frame {f}  t = {float(view.t[f]):.2f} s")
        cv2.imwrite(str(sheets / f"{f:06d}.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
        valid = view.valid  # pixels the recording covers after undistortion (None: all)
        masks = {"full": valid}
        if view.masks is not None or view.eval_masks is not None:
            masks.update({k: view.eval_region(f, k) if valid is None else view.eval_region(f, k) & valid
                          for k in ("robot", "object")})
        static = torch.ones_like(target[..., 0], dtype=torch.bool) if valid is None else valid.clone()
        for k in ("robot", "object"):
            if k in masks:
                static &= ~masks[k]
        fitted = colour_fitted(image, target, static)
        for key, region in masks.items():
            if subsampled(view.chroma_subsampling) is not None:
                scores["psnr_full_colour"][key].append(psnr(drawn.clamp(0, 1), target, region))
            scores["psnr"][key].append(psnr(image, target, region))
            scores["ssim"][key].append(ssim(image, target, region))
            scores["psnr_colour_fitted"][key].append(psnr(fitted, target, region))
            scores["ssim_colour_fitted"][key].append(ssim(fitted, target, region))
        if rec.graph.shadows is not None:
            unshaded = _without_shadows(rec, f, evaluation, camera)
            shadowed = static & ((image - unshaded).abs().amax(-1) > SHADOWED)
            shadow["pixels"].append(float(shadowed.float().mean()))
            shadow["psnr"].append(psnr(image, target, shadowed))
            shadow["psnr_without_shadows"].append(psnr(unshaded, target, shadowed))
    summary = {metric: {k: _nanmean(v) for k, v in by_region.items() if v}
               for metric, by_region in scores.items() if any(by_region.values())}
    summary["psnr_per_frame"] = {"frames": frames, **{k: [_finite_or_none(x) for x in v]
                                                       for k, v in scores["psnr"].items() if v}}
    if shadow["pixels"]:
        summary["shadow"] = {k: _nanmean(v) for k, v in shadow.items()}
    return summary


SHADOWED = 4 / 255  # a background pixel the learned shadows darken by more than this is scored as shadowed


def _without_shadows(rec: Reconstruction, frame: int, evaluation: dict[str, np.ndarray],
                     camera: str | None = None) -> torch.Tensor:
    """The held-out render [H, W, 3] of ``frame`` by ``camera`` with the learned shadows switched off."""
    shadows, rec.graph.shadows = rec.graph.shadows, None
    try:
        return rec.render(frame, evaluation, camera)[0].clamp(0, 1)
    finally:
        rec.graph.shadows = shadows


def _light(shadows) -> dict:
    """The learned light: direction towards it [3] (base frame), elevation and azimuth (deg), strength [3],
    what casts the links' shadows ("meshes" or "gaussians") and the shadow map's size (pixels a side)."""
    d = shadows.direction.detach().double().cpu()
    d = d / d.norm()
    return {"direction": [round(float(x), 5) for x in d],
            "elevation_deg": round(math.degrees(math.asin(max(-1.0, min(1.0, float(d[2]))))), 2),
            "azimuth_deg": round(math.degrees(math.atan2(float(d[1]), float(d[0]))), 2),
            "strength": [round(float(x), 4) for x in shadows.strength.detach().cpu()],
            "receivers": shadows.receivers,
            "strength_moving": None if shadows.moving_strength is None else
            [round(float(x), 4) for x in shadows.moving_strength.detach().cpu()],
            "casters": "meshes" if shadows.has_casters else "gaussians",
            "shadow_map_px": shadows.resolution}


def colour_fitted(image: torch.Tensor, target: torch.Tensor, fit_region: torch.Tensor) -> torch.Tensor:
    """``image`` [H, W, 3] through the affine colour transform (3 x 3 and an offset, least squares
    in float64) that best maps it to ``target`` over ``fit_region`` [H, W] bool pixels, clamped to
    [0, 1]. Fitted on static pixels, it cannot absorb an error of the robot or the objects.

    The fit is pulled towards the identity (:data:`COLOUR_FIT_RIDGE`): where the static pixels
    span few colours (a plain table and wall), the directions they do not span stay as rendered
    instead of taking whatever the least squares leaves there, which would recolour an object of
    another colour and score an exposure correction as an object error."""
    x = image[fit_region].double()
    if len(x) < 64:
        return image
    A = torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype, device=x.device)], 1)
    prior = torch.eye(4, 3, dtype=x.dtype, device=x.device)  # x -> x, no offset
    ridge = COLOUR_FIT_RIDGE * len(x) * torch.eye(4, dtype=x.dtype, device=x.device)
    X = torch.linalg.solve(A.T @ A + ridge, A.T @ target[fit_region].double() + ridge @ prior)  # [4, 3]
    full = torch.cat([image.double(), torch.ones_like(image[..., :1], dtype=torch.float64)], -1)
    return (full @ X).clamp(0, 1).to(image.dtype)


COLOUR_FIT_RIDGE = 1e-3
"""Weight per pixel of the identity prior in :func:`colour_fitted` (colour values in [0, 1]):
negligible along colours the static pixels vary in by more than a few per cent (variance above
~1e-3), decisive along those they do not (the built-in sample's table and wall: variance 1e-5)."""


SHEET_COLUMNS = ("ground truth", "render", "|error| x4")


def _finite_or_none(value: float) -> float | None:
    """``value`` rounded to 0.01 for ``metrics.json``, None where it is NaN (a region the frame does not show)."""
    return None if math.isnan(value) else round(value, 2)


def _nanmean(values: list[float]) -> float | None:
    finite = [v for v in values if not math.isnan(v)]
    return round(float(np.mean(finite)), 4) if finite else None


def _pose_metrics(frame: str, evaluation: dict[str, np.ndarray], alignments: dict, gt: dict[str, np.ndarray],
                  t: np.ndarray, plot: Path | None) -> dict:
    """Object pose errors of ours, of the pseudo ground truth alone and of the tracking-only
    baseline, by both definitions (:mod:`manisplat.reconstruct.metrics`), against ``gt`` (gt.npz;
    poses ``T_<frame>_<object>``), for the frames of ``t`` [T] s; the pose plot to ``plot``."""
    result: dict[str, dict] = {"pose": {}, "pose_anchored": {}, "pose_pseudo": {}, "pose_baseline": {}}
    plots = {}
    for name, ours in evaluation.items():
        key = f"T_{frame}_{name}"
        if key not in gt:
            continue
        alignment = alignments[name]
        phases = [(s.name, s.start, s.end) for s in alignment.segments]
        result["pose"][name] = _rounded(pose_errors(ours, gt[key]))
        anchored = start_anchored_errors(ours, gt[key], phases)
        if anchored is not None:
            result["pose_anchored"][name] = _rounded(anchored)
        pseudo = alignment.pseudo.poses
        result["pose_pseudo"][name] = {"fitted": _rounded(pose_errors(pseudo, gt[key])),
                                       "anchored": _rounded(start_anchored_errors(pseudo, gt[key], phases))}
        base = alignment.baseline
        if base is not None:
            result["pose_baseline"][name] = _rounded(pose_errors(base, gt[key]))
        plots[name] = (ours, base, gt[key])
    if plots and plot is not None:
        _pose_plot(plot, t, plots)
    return {k: v for k, v in result.items() if v}


def _rounded(value):
    """Floats in nested dicts rounded to 4 decimals (None kept)."""
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    return round(value, 4) if isinstance(value, float) else value


def _pose_plot(path: Path, t: np.ndarray, plots: dict) -> None:
    import matplotlib.pyplot as plt

    fig = pose_figure(t, plots)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def pose_figure(t: np.ndarray, plots: dict):
    """Per object (``plots``: name -> (ours, baseline or None, ground truth), each [T, 4, 4]):
    translation (x, y, z, cm) and rotation angle from the start (deg) against ``t`` [T] (s).
    Colours name the axis, line styles the source; the ground truth is drawn wide and pale under
    the estimates so that both stay visible where they agree. Returns the matplotlib figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from manisplat.geometry import rotation_error

    styles = {"ground truth": {"linestyle": "-", "linewidth": 4.0, "alpha": 0.3},
              "per-frame baseline": {"linestyle": ":", "linewidth": 1.0, "alpha": 0.9},
              "ours": {"linestyle": "-", "linewidth": 1.2, "alpha": 1.0}}
    fig, axes = plt.subplots(len(plots), 2, figsize=(11, 3.4 * len(plots)), squeeze=False)
    for row, (name, (ours, base, gt)) in enumerate(plots.items()):
        series = {"ground truth": gt, "per-frame baseline": base, "ours": ours}
        for label, poses in series.items():
            if poses is None:
                continue
            aligned = poses if label == "ground truth" else poses @ fit_constant_offset(poses, gt)
            trans = aligned[:, :3, 3] * 100
            for k in range(3):
                axes[row, 0].plot(t, trans[:, k], color=f"C{k}", **styles[label])
            angle = np.degrees(rotation_error(torch.as_tensor(aligned[:1, :3, :3]).expand(len(aligned), 3, 3),
                                              torch.as_tensor(aligned[:, :3, :3])).numpy())
            axes[row, 1].plot(t, angle, color="k", **styles[label])
        present = [label for label, poses in series.items() if poses is not None]
        source_handles = [Line2D([], [], color="k", label=label, **styles[label]) for label in present]
        axis_handles = [Line2D([], [], color=f"C{k}", label=axis) for k, axis in enumerate("xyz")]
        axes[row, 0].set(title=f"{name}: translation (after the constant offset)", xlabel="t (s)", ylabel="cm")
        axes[row, 1].set(title=f"{name}: rotation from the first frame", xlabel="t (s)", ylabel="deg")
        axes[row, 0].legend(handles=axis_handles + source_handles, fontsize=7, ncol=2)
        axes[row, 1].legend(handles=source_handles, fontsize=7)
    fig.tight_layout()
    return fig
