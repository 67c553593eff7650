"""The flat-shaded painter: OpenCV camera axes, exact ground-plane depth, occlusion order."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from manisplat.render.painter import Camera, GroundPlane, MeshItem, look_at, render


def camera(width=80, height=60, eye=(0.0, -2.0, 0.5), target=(0.0, 0.0, 0.3), up=(0.0, 0.0, 1.0)) -> Camera:
    f = 0.9 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(K, width, height, look_at(eye, target, up))


def test_look_at_gives_opencv_axes():
    T = look_at((1.0, 0.0, 0.0), (2.0, 0.0, 0.0))  # looking along +x
    assert np.allclose(T[:3, 2], [1, 0, 0])  # z forward
    assert np.allclose(T[:3, 0], [0, -1, 0])  # x right = -y (left is +y)
    assert np.allclose(T[:3, 1], [0, 0, -1])  # y down
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 1), (0, 0, 0))


def test_ground_depth_is_exact_z_depth():
    cam = camera()
    ground = GroundPlane((-5, 5, -5, 5), 0.1, ((255, 255, 255), (0, 0, 0)), 7)
    rgb, depth, mask = render(cam, [], ground)
    v, u = 45, 20
    ray = np.linalg.inv(cam.K) @ [u, v, 1.0]
    world_dir = cam.T_world_cam[:3, :3] @ ray
    eye = cam.T_world_cam[:3, 3]
    s = -eye[2] / world_dir[2]
    assert mask[v, u] == 7
    assert abs(depth[v, u] - s) < 1e-6  # z-depth, since ray has z = 1
    assert set(np.unique(mask)) == {0, 7}  # sky above the horizon stays background


def test_nearer_mesh_occludes_farther_one_and_depth_matches():
    cam = camera(eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))  # straight down
    near = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    near.apply_translation((0.0, 0.0, 0.5))
    far = trimesh.creation.box(extents=(0.6, 0.6, 0.2))
    items = [MeshItem(np.asarray(far.vertices), np.asarray(far.faces), (0, 0, 255), 2),
             MeshItem(np.asarray(near.vertices), np.asarray(near.faces), (255, 0, 0), 1)]
    rgb, depth, mask = render(cam, items)
    cy, cx = cam.height // 2, cam.width // 2
    assert mask[cy, cx] == 1 and abs(depth[cy, cx] - (2.0 - 0.6)) < 1e-6  # top face of the near box
    assert 2 in np.unique(mask)


def test_empty_scene_is_background():
    rgb, depth, mask = render(camera(), [])
    assert rgb.shape == (60, 80, 3) and not depth.any() and not mask.any()


def test_a_mesh_reaching_behind_the_camera_is_cut_at_the_near_plane():
    cam = camera(eye=(0.0, 0.0, 0.5), target=(0.0, 2.0, 0.0))
    floor = MeshItem(np.array([[-1.0, -1, 0], [1, -1, 0], [1, 3, 0], [-1, 3, 0]]), np.array([[0, 1, 2], [0, 2, 3]]),
                     (90, 90, 90), 3)  # the plane z = 0 from behind the camera to 3 m ahead
    _, depth, mask = render(cam, [floor], exact_depth=True)
    _, ground_depth, ground_mask = render(cam, [], GroundPlane((-1, 1, -1, 3), 0.1, ((0, 0, 0), (9, 9, 9)), 3))
    drawn = mask == 3
    assert drawn[-1].all() and (drawn ^ (ground_mask == 3)).sum() < 0.02 * drawn.size  # up to edge pixels
    both = drawn & (ground_mask == 3)
    assert np.allclose(depth[both], ground_depth[both], atol=1e-4)
