"""A small CPU renderer for synthetic data: flat-shaded triangle meshes over a textured ground
plane, seen by an OpenCV pinhole camera, giving RGB, z-depth and a label mask.

Meshes are drawn far to near (painter's algorithm) with OpenCV polygon fills, triangles that
reach behind the near plane cut at it; each triangle gets one depth (its vertices' mean), so
depth is exact on the analytic ground plane and within about one triangle's depth extent on
meshes; with ``exact_depth`` each pixel gets the depth where its ray meets the plane of the
triangle drawn there. Good enough for sample episodes and masks; it is not the Gaussian rasterizer.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_SHIFT = 4  # sub-pixel bits for cv2.fillConvexPoly


@dataclass(frozen=True)
class Camera:
    """An OpenCV pinhole camera: ``K`` (3, 3), image size, and ``T_world_cam`` (4, 4), metres."""

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray


@dataclass(frozen=True)
class MeshItem:
    """A mesh to draw: ``vertices`` (V, 3) in world coordinates, ``faces`` (F, 3) counter-clockwise
    seen from outside, an RGB ``color`` (0-255) and a mask ``label`` (1-255)."""

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[int, int, int]
    label: int


@dataclass(frozen=True)
class GroundPlane:
    """The plane z = 0 within ``extent`` = (xmin, xmax, ymin, ymax), checkered with ``square`` m tiles."""

    extent: tuple[float, float, float, float]
    square: float
    colors: tuple[tuple[int, int, int], tuple[int, int, int]]
    label: int


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` (4, 4) of an OpenCV camera (x right, y down, z forward) at ``eye`` facing ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the viewing direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def render(
    camera: Camera,
    meshes: list[MeshItem],
    ground: GroundPlane | None = None,
    *,
    background: tuple[int, int, int] = (200, 205, 215),
    light_dir=(0.3, -0.4, 1.0),
    near: float = 0.02,
    exact_depth: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render the scene (``exact_depth``: per-pixel depth on each triangle's plane, exact to
    millimetres, as the built-in sample uses; the default, one depth per triangle, is faster).

    Returns:
        rgb: (H, W, 3) uint8.
        depth: (H, W) float32 z-depth in metres, 0 where nothing was hit.
        mask: (H, W) uint8 labels, 0 for the background.
    """
    H, W = camera.height, camera.width
    rgb = np.empty((H, W, 3), np.uint8)
    rgb[:] = background
    depth = np.zeros((H, W), np.float32)
    mask = np.zeros((H, W), np.uint8)
    T_cam_world = np.linalg.inv(camera.T_world_cam)
    if ground is not None:
        _draw_ground(camera, T_cam_world, ground, rgb, depth, mask)
    light = np.asarray(light_dir, dtype=np.float64)
    light /= np.linalg.norm(light)

    polys, depths, colors, labels, planes = [], [], [], [], []
    for item in meshes:
        tri_world = item.vertices[item.faces]  # [F, 3, 3]
        normal = np.cross(tri_world[:, 1] - tri_world[:, 0], tri_world[:, 2] - tri_world[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        tri_cam = tri_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        to_camera = -tri_cam.mean(axis=1) @ T_cam_world[:3, :3]  # view vector, world frame
        visible = (np.einsum("fi,fi->f", normal, to_camera) > 0) & (tri_cam[:, :, 2] > near).any(axis=1)
        if not visible.any():
            continue
        tri_cam, normal = _clip_near(tri_cam[visible], normal[visible], near)
        uv = tri_cam @ camera.K.T
        uv = uv[:, :, :2] / uv[:, :, 2:3]
        shade = 0.35 + 0.65 * np.clip(normal @ light, 0.0, 1.0)
        polys.append(np.round(uv * (1 << _SHIFT)).astype(np.int32))
        depths.append(tri_cam[:, :, 2].mean(axis=1))
        colors.append(np.clip(shade[:, None] * np.asarray(item.color, dtype=np.float64), 0, 255))
        labels.append(np.full(len(shade), item.label, np.uint8))
        normal_cam = normal @ T_cam_world[:3, :3].T
        planes.append(np.concatenate([normal_cam, np.einsum("fi,fi->f", normal_cam, tri_cam[:, 0])[:, None],
                                      tri_cam[:, :, 2].min(1, keepdims=True), tri_cam[:, :, 2].max(1, keepdims=True)], 1))
    if not polys:
        return rgb, depth, mask
    polys_all, depth_all = np.concatenate(polys), np.concatenate(depths)
    colors_all, labels_all = np.concatenate(colors), np.concatenate(labels)
    drawn = np.full((H, W), -1, np.int32)
    for i in np.argsort(-depth_all):  # far to near
        poly = polys_all[i]
        cv2.fillConvexPoly(rgb, poly, colors_all[i].tolist(), lineType=cv2.LINE_8, shift=_SHIFT)
        cv2.fillConvexPoly(depth, poly, float(depth_all[i]), lineType=cv2.LINE_8, shift=_SHIFT)
        cv2.fillConvexPoly(mask, poly, int(labels_all[i]), lineType=cv2.LINE_8, shift=_SHIFT)
        if exact_depth:
            cv2.fillConvexPoly(drawn, poly, int(i), lineType=cv2.LINE_8, shift=_SHIFT)
    if exact_depth:
        _plane_depth(camera.K, np.concatenate(planes), drawn, depth)
    return rgb, depth, mask


def _clip_near(tri: np.ndarray, normal: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray]:
    """Cut the camera-frame triangles ``tri`` (F, 3, 3) that reach behind z = ``near`` (a camera
    close to a mesh, on a wrist) at that plane, corners in the same turning order: one corner in
    front leaves one triangle, two leave a quadrilateral, as two triangles. Returns the triangles
    (F', 3, 3) and their world-frame ``normal`` (F', 3), the uncut ones first and unchanged."""
    behind = tri[:, :, 2] <= near
    cut = behind.any(axis=1)
    if not cut.any():
        return tri, normal
    pieces, normals = [tri[~cut]], [normal[~cut]]

    def on_plane(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # where the edge a-b meets z = near
        return a + (b - a) * ((near - a[2]) / (b[2] - a[2]))

    for t, n, b in zip(tri[cut], normal[cut], behind[cut]):
        one_behind = b.sum() == 1
        a, p, q = np.roll(t, -int(np.flatnonzero(b == one_behind)[0]), axis=0)  # a: the corner alone on its side
        if one_behind:
            ap, qa = on_plane(a, p), on_plane(q, a)
            pieces.append(np.stack([[ap, p, q], [ap, q, qa]]))
        else:
            pieces.append(np.stack([[a, on_plane(a, p), on_plane(a, q)]]))
        normals.append(np.repeat(n[None], len(pieces[-1]), 0))
    return np.concatenate(pieces), np.concatenate(normals)


def _plane_depth(K: np.ndarray, planes: np.ndarray, drawn: np.ndarray, depth: np.ndarray) -> None:
    """Replace ``depth`` where a triangle was drawn (``drawn`` [H, W] its index, -1 none) by the
    z where the pixel's ray meets that triangle's plane (``planes`` [F, 6]: camera-frame normal,
    offset, and the triangle's z range, which bounds the result at grazing angles)."""
    rows, cols = np.nonzero(drawn >= 0)
    plane = planes[drawn[rows, cols]]
    ray = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones(len(rows))], 1)
    denom = np.einsum("ij,ij->i", plane[:, :3], ray)
    z = np.where(np.abs(denom) > 1e-9, plane[:, 3] / np.where(np.abs(denom) > 1e-9, denom, 1.0), plane[:, 4])
    depth[rows, cols] = np.clip(z, plane[:, 4], plane[:, 5]).astype(np.float32)


def _draw_ground(camera: Camera, T_cam_world: np.ndarray, ground: GroundPlane, rgb, depth, mask) -> None:
    """Ray-plane intersection per pixel: exact depth and a checker texture on z = 0."""
    H, W = camera.height, camera.width
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays_cam = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(camera.K).T  # z = 1
    R, eye = camera.T_world_cam[:3, :3], camera.T_world_cam[:3, 3]
    rays = rays_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -eye[2] / rays[..., 2]  # ray parameter; equals the z-depth since rays_cam has z = 1
    hit = eye + s[..., None] * rays
    xmin, xmax, ymin, ymax = ground.extent
    inside = (s > 0) & (hit[..., 0] >= xmin) & (hit[..., 0] <= xmax) & (hit[..., 1] >= ymin) & (hit[..., 1] <= ymax)
    checker = ((np.floor(hit[..., 0] / ground.square) + np.floor(hit[..., 1] / ground.square)) % 2).astype(int)
    palette = np.asarray(ground.colors, dtype=np.uint8)
    rgb[inside] = palette[checker[inside]]
    depth[inside] = s[inside].astype(np.float32)
    mask[inside] = ground.label
