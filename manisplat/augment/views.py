"""Whether a new demonstration shows its objects from where the recording did.

A twin knows an object's surface from the sides its fixed cameras saw in the demonstrations it
was trained on. A new pose can turn a side towards the camera that no demonstration showed: the
twin then draws colours it never fitted there (on the fused pick-and-place benchmark a new
demonstration 33 deg from every recorded view scores 20.2 dB in the box region, those within
12 deg 22.6-25.2: ``docs/benchmarks.md``). More demonstrations of the scene show more sides
(``manisplat-reconstruct EP1 EP2 ...``).

The views are the unit directions, in the object's frame, from the object to each fixed camera
in every frame of every demonstration where its origin projects into that camera's image (a
frame where the gripper hides it counts too: the twin does not keep the masks). A new frame's
*view change* is the angle from its direction to the nearest of them; a new demonstration's is
the largest over its frames and fixed cameras. Wrist cameras are not counted either way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UNSEEN_WARN_DEG = 15.0  # a view change above this draws a side the recording did not show


@dataclass(frozen=True)
class SeenViews:
    """Where each object was seen from: ``cameras`` [C, 4, 4] the fixed cameras' poses
    (camera-to-twin frame) and ``directions`` object -> [K, 3] unit directions (object frame)."""

    cameras: np.ndarray
    directions: dict[str, np.ndarray]

    @classmethod
    def of(cls, twin) -> SeenViews | None:
        """The views of ``twin``'s fixed cameras over all its demonstrations; None without a fixed
        camera."""
        fixed = [cam for cam in twin.cameras.values() if cam.fixed]
        if not fixed:
            return None
        directions: dict[str, list[np.ndarray]] = {name: [] for name in twin.objects}
        for demo in twin.demonstrations.values():
            for name, recorded in demo.object_poses.items():
                poses = np.asarray(recorded, np.float64)
                for cam in fixed:
                    inside = _in_image(cam, poses[:, :3, 3])
                    directions[name].append(_directions(cam.T_mount_cam, poses[inside]))
        return cls(np.stack([cam.T_mount_cam for cam in fixed]),
                   {name: np.concatenate(d) if d else np.zeros((0, 3)) for name, d in directions.items()})

    def change_deg(self, object_poses: dict[str, np.ndarray]) -> dict[str, float]:
        """object -> the largest angle (deg) over frames and fixed cameras between the view of
        ``object_poses`` [T, 4, 4] (twin frame) and the nearest recorded view (180 where the
        object was never in view)."""
        out = {}
        for name, poses in object_poses.items():
            seen = self.directions.get(name, np.zeros((0, 3)))
            if len(seen) == 0:
                out[name] = 180.0
                continue
            worst = 0.0
            for T_cam in self.cameras:
                nearest = (_directions(T_cam, np.asarray(poses, np.float64)) @ seen.T).max(axis=1)
                worst = max(worst, float(np.degrees(np.arccos(np.clip(nearest.min(), -1.0, 1.0)))))
            out[name] = round(worst, 2)
        return out


def _directions(T_cam: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """[T, 3] unit directions (object frame) from objects at ``poses`` [T, 4, 4] to the centre of
    the camera at ``T_cam`` [4, 4]."""
    d = np.einsum("tji,tj->ti", poses[:, :3, :3], T_cam[:3, 3] - poses[:, :3, 3])
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _in_image(cam, points: np.ndarray) -> np.ndarray:
    """[T] whether the points [T, 3] (twin frame) lie in front of ``cam`` and project into its image."""
    T = np.linalg.inv(cam.T_mount_cam)
    p = points @ T[:3, :3].T + T[:3, 3]
    front = p[:, 2] > 1e-6
    uv = (p[:, :2] / np.where(front, p[:, 2], 1.0)[:, None]) * np.diag(cam.K)[:2] + cam.K[:2, 2]
    return front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)


__all__ = ["SeenViews", "UNSEEN_WARN_DEG"]
