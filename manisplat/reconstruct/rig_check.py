"""A rig's calibration checked against its robots (a Cobot Magic: two arms, a head camera, two
wrist cameras): the head camera's extrinsic, each arm's base against the first arm's, and each
wrist camera's ``T_link6_cam``, corrected where the depth is sure of it.

* **Bases.** The head camera sees both arms. Fitted to one arm's links alone
  (:func:`~manisplat.reconstruct.extrinsic.refine_extrinsic` with ``links``), it gives the camera
  pose that arm's recorded base implies; two arms' fits differ by exactly the error of the
  base-to-base calibration. The first arm anchors the world (its base is kept, as the gauge must
  be fixed somewhere); another arm's base becomes ``T_cam(first) T_cam(other)^-1 T_world_base``,
  with the spread of both fits carried through. A base correction is applied by the rules of the
  camera's own (:func:`~manisplat.reconstruct.extrinsic.refusal`); then the head camera is the
  first arm's fit. Otherwise the base-to-base calibration stands and the head camera is fitted to
  every link, as for one arm.
* **Wrist cameras.** A wrist camera's own fingers are in the same place in every frame, which
  cannot pin the extrinsic down (on the shared Cobot Magic sample: a 1-sigma of 0.5 deg, and a
  fit 2 deg off). It sweeps over the table from many poses, though: its depth of the static
  scene must lie on the surface the (checked) head camera measured
  (:func:`~manisplat.reconstruct.static_surface.static_surface`), and its depth of any link
  (its fingers, the other arm) on that link; both fix ``T_mount_cam``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from manisplat.geometry import se3_exp
from manisplat.reconstruct.data import EpisodeData, retime
from manisplat.reconstruct.extrinsic import ExtrinsicCorrection, pose_difference, refine_extrinsic, refusal
from manisplat.reconstruct.masks import redraw_robot_masks
from manisplat.reconstruct.static_surface import static_surface
from manisplat.robot.arms import ArmSet

log = logging.getLogger(__name__)


@dataclass
class BaseCorrection:
    """What the head camera's depth says about one arm's base relative to the first arm's.

    Attributes:
        arm, reference: the arm checked and the arm that anchors the world.
        T_before, T_after: [4, 4] float64 ``T_world_base`` as recorded and as used.
        T_fitted: [4, 4] the fit's, applied or not.
        rotation_deg, translation_mm: the correction (rotation angle, the base origin's move).
        sigma_rotation_deg, sigma_translation_mm: its 1-sigma (both arms' fits: frames and links).
        rms_before_mm, rms_after_mm: the arm's depth residual at the recorded and the fitted base.
        applied, reason: whether the correction is used, and why not.
    """

    arm: str
    reference: str
    T_before: np.ndarray
    T_after: np.ndarray
    T_fitted: np.ndarray
    rotation_deg: float
    translation_mm: float
    sigma_rotation_deg: float
    sigma_translation_mm: float
    rms_before_mm: float
    rms_after_mm: float
    applied: bool
    reason: str = ""

    def to_dict(self) -> dict:
        return {"arm": self.arm, "reference": self.reference, "rotation_deg": self.rotation_deg,
                "translation_mm": self.translation_mm, "sigma_rotation_deg": self.sigma_rotation_deg,
                "sigma_translation_mm": self.sigma_translation_mm, "rms_before_mm": self.rms_before_mm,
                "rms_after_mm": self.rms_after_mm, "applied": self.applied, "reason": self.reason,
                "T_world_base": self.T_after.tolist(),
                "method": "the head camera fitted to each arm's links alone; the difference is the base-to-base error"}


@dataclass
class RigCheck:
    """The rig as checked: the fixed camera's correction (None: not checked), each other arm's
    base (name -> correction; none for one arm), each riding camera's (name -> correction, None
    where it could not be checked)."""

    camera: ExtrinsicCorrection | None
    bases: dict[str, BaseCorrection]
    riding: dict[str, ExtrinsicCorrection | None]

    def to_dict(self) -> dict:
        return {"bases": {arm: b.to_dict() for arm, b in self.bases.items()},
                "cameras": {name: None if c is None else {k: v for k, v in c.to_dict().items() if k != "T_correction"}
                            for name, c in self.riding.items()}}


def check_bases(data: EpisodeData, frames: list[int]) -> tuple[ExtrinsicCorrection | None, dict[str, BaseCorrection]]:
    """The fixed camera ``data`` and every arm's base after the first, checked against the robot's
    depth in ``frames`` (see the module). Nothing is changed here (:func:`apply_bases` does)."""
    if not isinstance(data.robot, ArmSet) or len(data.robot.arm_names) < 2:
        return refine_extrinsic(data, frames), {}
    arms = data.robot.arm_names
    fits = {arm: refine_extrinsic(data, frames, links=[n for n in data.robot.link_names if n.startswith(f"{arm}/")])
            for arm in arms}
    reference, bases = arms[0], {}
    for arm in arms[1:]:
        base = _base_correction(data, reference, arm, fits[reference], fits[arm])
        if base is not None:
            bases[arm] = base
    if any(b.applied for b in bases.values()):
        return fits[reference], bases
    return refine_extrinsic(data, frames), bases


def _base_correction(data: EpisodeData, reference: str, arm: str, fit_ref: ExtrinsicCorrection | None,
                     fit_arm: ExtrinsicCorrection | None) -> BaseCorrection | None:
    """``arm``'s base from the camera fits to the reference arm's links and to its own (None
    where either could not be fitted)."""
    if fit_ref is None or fit_arm is None:
        log.info("arm %s: base not checked (the head camera could not be fitted to %s alone)", arm,
                 reference if fit_ref is None else arm)
        return None
    T_base = np.asarray(data.robot.T_world_base[arm], dtype=np.float64)
    T_fitted = _moved_base(fit_ref.T_fitted, fit_arm.T_fitted, T_base)
    rot, trans = pose_difference(T_base, T_fitted)
    parts = [_base_spread(fit_ref, fit_arm, T_base, moved_ref) for moved_ref in (True, False)]
    sig_rot = math.sqrt(sum(p[0] ** 2 for p in parts))
    sig_trans = math.sqrt(sum(p[1] ** 2 for p in parts))
    refused = refusal(rot, trans, sig_rot, sig_trans, fit_arm.rms_before_mm / 1000, fit_arm.rms_after_mm / 1000,
                      subject=f"arm {arm}'s base")
    result = BaseCorrection(arm, reference, T_base, T_base.copy() if refused else T_fitted, T_fitted, rot, trans,
                            sig_rot, sig_trans, fit_arm.rms_before_mm, fit_arm.rms_after_mm, refused is None,
                            refused[0] if refused else "")
    log.info("arm %s: base against arm %s's: correction %.3f +- %.3f deg, %.2f +- %.2f mm (%s)", arm, reference, rot,
             sig_rot, trans, sig_trans, "applied" if result.applied else f"kept: {result.reason}")
    return result


def _moved_base(T_cam_ref: np.ndarray, T_cam_arm: np.ndarray, T_base: np.ndarray) -> np.ndarray:
    """The base that puts the arm where the camera fitted to it saw it, with the camera where the
    reference arm's fit put it: ``T_cam_ref T_cam_arm^-1 T_base``."""
    return T_cam_ref @ np.linalg.inv(T_cam_arm) @ T_base


def _base_spread(fit_ref: ExtrinsicCorrection, fit_arm: ExtrinsicCorrection, T_base: np.ndarray,
                 moved_ref: bool) -> tuple[float, float]:
    """1-sigma (deg, mm) of the moved base from one fit's error samples (the reference arm's when
    ``moved_ref``, else the arm's own), frames and links in quadrature."""
    fit = fit_ref if moved_ref else fit_arm
    nominal = _moved_base(fit_ref.T_fitted, fit_arm.T_fitted, T_base)
    total_deg, total_mm = 0.0, 0.0
    for spread in (fit.spreads or {}).values():
        angles, shifts = [], []
        for step in spread.steps:
            T = fit.T_fitted @ se3_exp(torch.as_tensor(step[:6])).numpy()
            moved = _moved_base(T, fit_arm.T_fitted, T_base) if moved_ref else _moved_base(fit_ref.T_fitted, T, T_base)
            deg, mm = pose_difference(nominal, moved)
            angles.append(deg)
            shifts.append(mm)
        total_deg += spread.scale * float(np.mean(np.square(angles))) if angles else 0.0
        total_mm += spread.scale * float(np.mean(np.square(shifts))) if shifts else 0.0
    return math.sqrt(total_deg), math.sqrt(total_mm)


def apply_bases(bases: dict[str, BaseCorrection], data: EpisodeData, views: dict[str, EpisodeData]) -> None:
    """Put every applied base correction into the robot model the cameras share and re-place
    the links (and riding cameras) of ``data`` and every view."""
    moved = {arm: b.T_after for arm, b in bases.items() if b.applied}
    if not moved:
        return
    for view in [data, *views.values()]:
        for arm, T in moved.items():
            view.robot.T_world_base[arm] = T.copy()  # views usually share data's model: the same dict
        view.arms = tuple(dataclasses.replace(a, T_world_base=moved[a.name].copy()) if a.name in moved else a
                          for a in view.arms)
        retime(view, view.time_offset_s)  # link poses, TCPs and riding cameras from the moved bases


def check_riding(data: EpisodeData, views: dict[str, EpisodeData],
                 frames: list[int]) -> dict[str, ExtrinsicCorrection | None]:
    """Each riding camera of ``views`` checked against the robot and the static surface the fixed
    camera ``data`` measures in ``frames[0]`` (its extrinsic already checked), and its corrected
    ``T_mount_cam`` put in place where it is applied."""
    riding = {name: view for name, view in views.items() if view.riding}
    if not riding:
        return {}
    try:
        surface = static_surface(data, frames[0])
    except ValueError as exc:
        log.info("wrist cameras checked against the robot alone (%s)", exc)
        surface = None
    out = {}
    for name, view in riding.items():
        if view.depth is None:
            log.info("camera %s: extrinsic not checked (no depth)", name)
            out[name] = None
            continue
        log.info("camera %s (on %s): checking T_mount_cam", name, view.mount)
        c = refine_extrinsic(view, frames, surface=surface)
        if c is not None and c.applied:
            view.T_mount_cam = torch.as_tensor(c.T_after, dtype=torch.float64)
            retime(view, view.time_offset_s)  # re-places the camera on its link in every frame
        out[name] = c
    return out



def check_rig(data: EpisodeData, views: dict[str, EpisodeData], frames: list[int]) -> RigCheck:
    """The whole rig checked against the robot and corrected in place, in order: the fixed
    camera ``data`` and the other arms' bases (:func:`check_bases`, :func:`apply_bases`), the
    camera's correction and camera/joint time offset where applied, its drawn robot masks drawn
    again if anything moved, then the riding cameras against what the corrected fixed camera sees
    (:func:`check_riding`). ``frames``: the training frames."""
    camera, bases = check_bases(data, frames)
    apply_bases(bases, data, views)
    if camera is not None and camera.applied:
        data.viewmat = torch.linalg.inv(torch.as_tensor(camera.T_after)).float()
    if camera is not None and camera.time_applied:
        retime(data, data.time_offset_s + camera.time_offset_s)
    moved = any(b.applied for b in bases.values()) or (camera is not None and (camera.applied or camera.time_applied))
    if moved and data.mask_source.startswith("drawn robot"):
        redraw_robot_masks(data, progress=False)  # drawn with the camera, bases and timing just corrected
    return RigCheck(camera, bases, check_riding(data, views, frames))


__all__ = ["BaseCorrection", "RigCheck", "apply_bases", "check_bases", "check_riding", "check_rig"]
