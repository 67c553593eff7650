"""Lens distortion is removed on load: the episode's images, depth and masks become the pinhole
camera's with the same K, which the rasterizer renders."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from manisplat.episode import Episode
from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.lens import Undistortion, undistortion_for

K = np.array([[136.0, 0.0, 79.5], [0.0, 136.0, 59.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.15, 0.05, 0.001, -0.001, 0.0])  # stronger than an OAK's, so the test sees it


def _distortion_maps(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted image, where it lies in the pinhole image (what a real
    lens does; independent of the module under test: cv2.undistortPoints, not initUndistortRectifyMap)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], 1)[:, None]
    pin = cv2.undistortPoints(pts, K, dist, P=K)[:, 0]
    return pin[:, 0].reshape(height, width).astype(np.float32), pin[:, 1].reshape(height, width).astype(np.float32)


def test_points_land_where_the_pinhole_camera_projects_them():
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-0.4, 0.4, (40, 2)), rng.uniform(1.0, 2.0, 40)]
    distorted, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, DIST)
    pinhole = points[:, :2] / points[:, 2:] * K[0, 0] + K[:2, 2]
    lens = Undistortion(K, DIST, 160, 120)
    # the map sends each pinhole pixel to its distorted position: sample it at the pinhole points
    at = lambda m, p: cv2.remap(m, p[:, 0].astype(np.float32)[None], p[:, 1].astype(np.float32)[None], cv2.INTER_LINEAR)[0]  # noqa: E731
    inside = (pinhole[:, 0] > 1) & (pinhole[:, 0] < 158) & (pinhole[:, 1] > 1) & (pinhole[:, 1] < 118)
    mapped = np.stack([at(lens.map_x, pinhole), at(lens.map_y, pinhole)], 1)
    assert inside.sum() > 20
    assert np.abs(mapped[inside] - distorted[inside, 0]).max() < 0.05  # px
    assert lens.shift_px > 3  # the lens moves pixels: the comparison above is not trivial


def test_a_pinhole_camera_needs_no_undistortion():
    assert undistortion_for(K, np.zeros(5), 160, 120) is None
    assert undistortion_for(K, [], 160, 120) is None
    assert undistortion_for(K, DIST, 160, 120) is not None


def test_coverage_is_reported_for_a_pincushion_lens():
    lens = Undistortion(K, np.array([0.2, 0.0, 0.0, 0.0, 0.0]), 160, 120)
    assert 0.5 < lens.valid_fraction < 1.0  # the corners of the pinhole image were never recorded
    image = lens.rgb(np.full((120, 160, 3), 200, np.uint8))
    assert (image[~lens.valid] == 0).all() and (image[lens.valid] == 200).all()


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    """The sample episode and a copy seen through a distorting lens (camera.dist set)."""
    root = tmp_path_factory.mktemp("lens")
    pinhole = write_sample_episode(root / "pinhole", frames=12)
    distorted = root / "distorted"
    import shutil

    shutil.copytree(pinhole, distorted)
    ep = Episode.open(distorted)
    cam = ep.camera
    mx, my = _distortion_maps(cam.K, DIST, cam.width, cam.height)
    for folder, interpolation in (("rgb", cv2.INTER_LINEAR), ("depth", cv2.INTER_NEAREST), ("masks", cv2.INTER_NEAREST)):
        for path in sorted((distorted / folder).glob("*.png")):
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(path), cv2.remap(image, mx, my, interpolation, borderMode=cv2.BORDER_REPLICATE))
    meta = json.loads((distorted / "episode.json").read_text())
    meta["camera"]["dist"] = DIST.tolist()
    (distorted / "episode.json").write_text(json.dumps(meta))
    return pinhole, distorted


def test_a_distorted_episode_loads_as_the_pinhole_camera_saw_it(episodes):
    pinhole, distorted = load_episode_data(episodes[0]), load_episode_data(episodes[1])
    assert distorted.dist == tuple(DIST)
    border = (slice(6, -6), slice(6, -6))  # the replicated border of the distorted copy is not compared
    raw = Episode.open(episodes[1])
    for i in (0, 6, 11):
        ref = pinhole.rgb[i].numpy().astype(float)[border]
        error = np.abs(distorted.rgb[i].numpy().astype(float)[border] - ref).mean()
        raw_error = np.abs(raw.rgb(i).astype(float)[border] - ref).mean()
        assert error < 0.75 * raw_error, (i, error, raw_error)  # two bilinear resamplings blur this smooth image
        ref_labels = pinhole.masks[i].numpy()[border]
        moving = (ref_labels > 0) & (ref_labels != 11)  # robot links (1-9) and the box (10); 11 is the table
        labels_agree = (distorted.masks[i].numpy()[border] == ref_labels)[moving].mean()
        raw_agree = (raw.mask(i)[border] == ref_labels)[moving].mean()
        assert 1 - labels_agree < 0.5 * (1 - raw_agree), (labels_agree, raw_agree)  # near the centre: small shifts
        za, zb = distorted.depth[i].numpy()[border], pinhole.depth[i].numpy()[border]
        both = (za > 0) & (zb > 0)
        assert (np.abs(za - zb)[both] < 1e-3).mean() > 0.95  # nearest neighbour: depths are not blended
