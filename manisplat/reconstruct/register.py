"""Find an object's start in another episode: where the canonical model (points and colours in
its own frame) lies among the points that episode's first frame shows of it.

Objects start upright on the table, so the pose is searched in four degrees of freedom: a turn
about the vertical and a translation. Each turn of a grid starts an ICP whose correspondences
are nearest neighbours in position and colour together (colour weighed by
:data:`COLOUR_WEIGHT_M`: a cylinder or a square box fits its own turns equally well in shape
alone; its print does not). The start with the lowest residual wins, and is refined point to
plane (each observed point's distance along its model neighbour's normal): two first frames
see different sides of the object, and the sides only one of them shows pull a point-to-point
fit off by a few degrees (on the fused pick-and-place benchmark's 19 registrations a median of
2.1 deg, up to 5.6; ``docs/benchmarks.md``), while a point may slide along the face it lies on.
Several episodes are registered in turn against all the sides found so far (:func:`register_starts`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from manisplat.geometry.normals import point_normals

YAW_STEP_DEG = 10.0  # the grid of turns each ICP starts from
COLOUR_WEIGHT_M = 0.02  # 1.0 of colour difference (RGB in [0, 1]) counts as 2 cm
ICP_ITERATIONS = 30
PLANE_NEIGHBOURS = 10  # points whose plane gives a point's normal (the point-to-plane refinement)
PLANE_MAX_M = 0.004  # the refinement pairs an observed point with a model point this near (m) ...
PLANE_AGREE_DEG = 30.0  # ... whose normal agrees with its own this well: both on one face
TRIM = 0.8  # each iteration fits the best-matched 80 % of the observed points (the rest: unseen sides)


@dataclass(frozen=True)
class Registration:
    """``T_base_obj`` [4, 4] float64 and the trimmed RMS residual (m, position and weighed colour
    together) of the best start; ``runner_up_m`` the best residual of a turn more than 30 deg away."""

    T_base_obj: np.ndarray
    residual_m: float
    runner_up_m: float


def register_start(model_points: np.ndarray, model_colours: np.ndarray, observed_points: np.ndarray,
                   observed_colours: np.ndarray) -> Registration:
    """The pose ``T_base_obj`` that puts the model (``model_points`` [N, 3] m in the object frame,
    ``model_colours`` [N, 3] in [0, 1]) on the observation (``observed_points`` [M, 3] m in the base
    frame, ``observed_colours`` [M, 3]): a turn about the base's z and a translation.

    Raises:
        ValueError: fewer than 10 points on either side, or values that are not finite.
    """
    for name, pts in (("model", model_points), ("observation", observed_points)):
        if len(pts) < 10:
            raise ValueError(f"register_start: the {name} has {len(pts)} points (at least 10 needed)")
        if not np.isfinite(pts).all():
            raise ValueError(f"register_start: the {name}'s points are not all finite")
    model = np.hstack([np.asarray(model_points, np.float64), COLOUR_WEIGHT_M * np.asarray(model_colours, np.float64)])
    tree = cKDTree(model)
    observed = np.asarray(observed_points, np.float64)
    colours = COLOUR_WEIGHT_M * np.asarray(observed_colours, np.float64)
    centre = observed.mean(0)
    results = []
    for yaw in np.radians(np.arange(0.0, 360.0, YAW_STEP_DEG)):
        # the observation in the object frame: x_obj = Rz(-yaw) (x_base - t), t starting at the centroids' offset
        t0 = centre - _rz(yaw) @ model_points.mean(0)
        results.append(_icp(tree, observed, colours, yaw, t0))
    best = min(range(len(results)), key=lambda k: results[k][2])
    far = [r[2] for r in results if abs(_wrap(r[0] - results[best][0])) > np.radians(30)]
    normals = point_normals(model_points, PLANE_NEIGHBOURS)
    yaw, t, residual = _plane_icp(tree, normals, observed, colours, *results[best][:2])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rz(yaw), t
    return Registration(T, float(residual), float(min(far)) if far else float("inf"))


def register_starts(model_points: np.ndarray, model_colours: np.ndarray,
                    observations: list[tuple[np.ndarray, np.ndarray]]) -> list[Registration]:
    """Each observation (points [M, 3] base frame, colours [M, 3]) registered in turn
    (:func:`register_start`) against the model and every observation registered before it, taken
    into the object frame: a later start finds the sides the earlier ones added. Against the
    first frame alone, a start showing a side that frame saw only edge-on came out 4.9 deg off on
    the fused benchmark's scripted episodes (0.3 deg so; the 19 registrations within 0.3 deg)."""
    points, colours = [np.asarray(model_points, np.float64)], [np.asarray(model_colours, np.float64)]
    found = []
    for p, c in observations:
        reg = register_start(np.concatenate(points), np.concatenate(colours), p, c)
        R, t = reg.T_base_obj[:3, :3], reg.T_base_obj[:3, 3]
        points.append((np.asarray(p, np.float64) - t) @ R)
        colours.append(np.asarray(c, np.float64))
        found.append(reg)
    return found


def _icp(tree: cKDTree, observed: np.ndarray, colours: np.ndarray, yaw: float,
         t: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Trimmed point-to-point ICP in (yaw, t) from a start; returns (yaw, t [3], trimmed RMS m)."""
    for _ in range(ICP_ITERATIONS):
        R = _rz(yaw)
        local = (observed - t) @ R  # R^T (x - t), row-wise
        dist, idx = tree.query(np.hstack([local, colours]))
        keep = np.argsort(dist)[: max(10, int(TRIM * len(dist)))]
        target = tree.data[idx[keep], :3]  # model points, object frame
        source = observed[keep]  # base frame
        # best yaw and t with source ~ Rz(yaw) target + t: a 2-D Procrustes in x, y; z by the mean
        ms, mt = source.mean(0), target.mean(0)
        a, b = target[:, :2] - mt[:2], source[:, :2] - ms[:2]
        new_yaw = float(np.arctan2((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum(), (a * b).sum()))
        new_t = ms - _rz(new_yaw) @ mt
        step = abs(_wrap(new_yaw - yaw)) + float(np.linalg.norm(new_t - t))
        yaw, t = new_yaw, new_t
        if step < 1e-6:
            break
    local = (observed - t) @ _rz(yaw)
    dist, _ = tree.query(np.hstack([local, colours]))
    dist = np.sort(dist)[: max(10, int(TRIM * len(dist)))]
    return yaw, t, float(np.sqrt(np.mean(dist ** 2)))


def _plane_icp(tree: cKDTree, normals: np.ndarray, observed: np.ndarray, colours: np.ndarray, yaw: float,
               t: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Point-to-plane ICP in (yaw, t) from a start (``normals`` [N, 3] of the model points, object
    frame): each step the Gauss-Newton step of sum (n . (R^T (x - t) - q))^2 over the pairs within
    :data:`PLANE_MAX_M` whose normals agree within :data:`PLANE_AGREE_DEG`; returns (yaw, t [3],
    the trimmed RMS m of :func:`_icp`)."""
    seen_normals = point_normals(observed, PLANE_NEIGHBOURS)
    for _ in range(ICP_ITERATIONS):
        R = _rz(yaw)
        local = (observed - t) @ R
        dist, idx = tree.query(np.hstack([local, colours]))
        near = np.linalg.norm(local - tree.data[idx, :3], axis=1) < PLANE_MAX_M
        agree = np.abs(np.einsum("ni,ni->n", normals[idx] @ R.T, seen_normals)) > np.cos(np.radians(PLANE_AGREE_DEG))
        keep = np.flatnonzero(near & agree)
        if len(keep) < 10:
            break
        n = normals[idx[keep]] @ R.T  # base frame
        q = tree.data[idx[keep], :3] @ R.T + t  # the matched model points, base frame
        x = observed[keep]
        c = q.mean(0)
        v = q - c
        # q moves to Rz(d) (q - c) + c + dt: a residual n . (x - q) changes by -n . (d z x v + dt)
        J = np.column_stack([n[:, 1] * v[:, 0] - n[:, 0] * v[:, 1], n])
        r = np.einsum("ni,ni->n", n, x - q)
        step, *_ = np.linalg.lstsq(J, r, rcond=None)
        d, dt = float(step[0]), step[1:]
        yaw, t = yaw + d, _rz(d) @ (t - c) + c + dt
        if abs(d) + float(np.linalg.norm(dt)) < 1e-7:
            break
    local = (observed - t) @ _rz(yaw)
    dist, _ = tree.query(np.hstack([local, colours]))
    dist = np.sort(dist)[: max(10, int(TRIM * len(dist)))]
    return float(_wrap(yaw)), t, float(np.sqrt(np.mean(dist ** 2)))


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


__all__ = ["Registration", "register_start", "register_starts"]
