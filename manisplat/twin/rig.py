"""The twin's arms and cameras: what a recording's rig was, as the twin keeps it.

A twin of a version 1 episode has one arm (named :data:`~manisplat.episode.format.V1_ARM`) whose
base is the twin's frame (``"base"``) and one camera fixed there. A twin of a version 2 episode
(a Cobot Magic: two arms, a head camera, two wrist cameras) is in the episode's world frame
(``"world"``): each arm at its ``T_world_base``, cameras fixed in the world or riding on a link
(``"<arm>/<link>"``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manisplat.episode.format import V1_ARM, WORLD_MOUNT

BASE_FRAME = "base"
"""The frame of a one-arm twin (its arm's base) and the mount of a camera fixed in it."""
FIXED_MOUNTS = (BASE_FRAME, WORLD_MOUNT)


def _pose(value, what: str) -> np.ndarray:
    T = np.asarray(value, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{what}: expected a finite 4x4 matrix, got shape {T.shape}")
    return T


@dataclass(frozen=True)
class TwinArm:
    """One arm of the twin.

    Attributes:
        name: the arm's name (:data:`V1_ARM` for a one-arm twin).
        description: its robot description (a built-in name or an absolute URDF path).
        model, joint_names: the episode's ``robot.model`` and ``robot.joint_names`` of this arm.
        T_world_base: [4, 4] float64 the arm's base in the twin's frame (m; identity for one arm).
    """

    name: str
    description: str
    model: str
    joint_names: tuple[str, ...]
    T_world_base: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_world_base", _pose(self.T_world_base, f"arm {self.name}: T_world_base"))
        object.__setattr__(self, "joint_names", tuple(self.joint_names))

    def to_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "model": self.model,
                "joint_names": list(self.joint_names), "T_world_base": self.T_world_base.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "TwinArm":
        return cls(d["name"], d["description"], d["model"], tuple(d["joint_names"]), np.array(d["T_world_base"]))


@dataclass(frozen=True)
class TwinCamera:
    """One camera of the twin (pinhole: the recording's distortion was removed before training).

    Attributes:
        name: the camera's name in the episode.
        K: [3, 3] float64 OpenCV intrinsics (px, integer pixel centres); width, height: px.
        mount: ``"base"`` / ``"world"``: fixed in the twin's frame; else the link it rides on, as the
            twin's robot names it (``"link6"``, ``"left/link6"``).
        T_mount_cam: [4, 4] float64 camera-to-mount (m): for a fixed camera its pose in the twin's
            frame, including any refinement made in training.
    """

    name: str
    K: np.ndarray
    width: int
    height: int
    mount: str
    T_mount_cam: np.ndarray

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise ValueError(f"camera {self.name}: K must be a finite 3x3 matrix")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name}: size {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "T_mount_cam", _pose(self.T_mount_cam, f"camera {self.name}: T_mount_cam"))

    @property
    def fixed(self) -> bool:
        """Whether the camera stands still in the twin's frame (else it rides on :attr:`mount`)."""
        return self.mount in FIXED_MOUNTS

    def to_dict(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height, "K": self.K.tolist(),
                "mount": self.mount, "T_mount_cam": self.T_mount_cam.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "TwinCamera":
        return cls(d["name"], np.array(d["K"]), d["width"], d["height"], d["mount"], np.array(d["T_mount_cam"]))


def one_arm(description: str, model: str, joint_names) -> TwinArm:
    """The one arm of a twin in its base frame."""
    return TwinArm(V1_ARM, description, model, tuple(joint_names), np.eye(4))


__all__ = ["BASE_FRAME", "FIXED_MOUNTS", "TwinArm", "TwinCamera", "one_arm"]
