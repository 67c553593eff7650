"""The scene graph of Gaussians: a static background, robot links driven by forward kinematics,
and objects with per-frame SE(3) poses; ``G(t)`` is the union of all nodes placed at frame t."""

from manisplat.scene.gaussians import GaussianSet
from manisplat.scene.graph import BACKGROUND, ROBOT, Composed, Node, SceneGraph
from manisplat.scene.transforms import transform_gaussians

__all__ = ["BACKGROUND", "ROBOT", "Composed", "GaussianSet", "Node", "SceneGraph", "transform_gaussians"]
