"""manisplat-view in a real headless browser (Debian's chromium through selenium, software WebGL):
the page shows the scene, the robot's meshes stand where the robot projects, and moving the frame
slider moves them. Skipped where chromium, chromedriver or selenium is missing (.ci/run installs them)."""

from __future__ import annotations

import shutil
import time
from typing import Callable, TypeVar

import cv2
import numpy as np
import pytest
import torch

pytest.importorskip("selenium", reason="selenium is not installed (pip install selenium)")
CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None,
                                reason="needs Debian's chromium and chromium-driver (apt-get install chromium "
                                       "chromium-driver)")

from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.options import Options  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

import viser  # noqa: E402

from manisplat.geometry.rotation import quat_to_matrix  # noqa: E402
from manisplat.view.app import Viewer  # noqa: E402
from manisplat.view.content import load_content  # noqa: E402

T = TypeVar("T")
TIMEOUT_S = 90.0
"""Software WebGL on a loaded 2-core runner is slow; every wait is on a condition, bounded by this."""
PANEL_W = 360
TOAST = (320, 160)
"""Screen parts that are not the 3D view: the GUI panel on the right, the WebGL notice at the top left."""


def _wait_for(condition: Callable[[], T], what: str) -> T:
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        value = condition()
        if value is not None and value is not False and (not isinstance(value, dict) or value):
            return value
        time.sleep(0.25)
    raise AssertionError(f"timed out after {TIMEOUT_S:.0f} s waiting for {what}")


@pytest.fixture
def browser():
    options = Options()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader", "--window-size=1000,700", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    yield driver
    driver.quit()


def _screenshot(driver) -> np.ndarray:
    png = driver.get_screenshot_as_png()
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _view_mask(image: np.ndarray) -> np.ndarray:
    mask = np.ones(image.shape[:2], bool)
    mask[:, image.shape[1] - PANEL_W:] = False
    mask[:TOAST[1], :TOAST[0]] = False
    return mask


def _orange(image: np.ndarray) -> np.ndarray:
    """Pixels of the meshes' flat orange (235, 120, 40) under the viewer's lights."""
    r, g, b = (image[..., c].astype(int) for c in range(3))
    return (r > 150) & (b < 90) & (r - g > 60) & (r - b > 100) & _view_mask(image)


def _project(points: np.ndarray, camera, width: int, height: int) -> np.ndarray:
    """[N, 2] pixels of base-frame ``points`` in the browser's view (viser: OpenCV axes, vertical fov)."""
    R = quat_to_matrix(torch.as_tensor(np.array(camera.wxyz), dtype=torch.float64)).numpy()
    in_camera = (points - np.array(camera.position)) @ R
    focal = height / 2 / np.tan(camera.fov / 2)
    return in_camera[:, :2] / in_camera[:, 2:3] * focal + np.array([width / 2, height / 2])


def _links_hit(image: np.ndarray, content, viewer, camera, radius: int = 8) -> float:
    """Share of the arm's link origins (base excluded) with orange pixels within ``radius`` px."""
    demo, i = viewer.demo, viewer.frame
    links = content.robot.forward_kinematics(torch.as_tensor(demo.q[i]), torch.as_tensor(demo.gripper[i])).numpy()
    uv = _project(links[1:, :3, 3], camera, image.shape[1], image.shape[0])
    orange = _orange(image)
    hits = [orange[max(0, int(v) - radius):int(v) + radius + 1, max(0, int(u) - radius):int(u) + radius + 1].any()
            for u, v in uv]
    return float(np.mean(hits))


def _arm_pixels(content, demo, i: int, camera, shape: tuple[int, ...]) -> np.ndarray:
    links = content.robot.forward_kinematics(torch.as_tensor(demo.q[i]), torch.as_tensor(demo.gripper[i])).numpy()
    return _project(links[:, :3, 3], camera, shape[1], shape[0])


def _orange_centre(image: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """(u, v) centre of the orange pixels inside ``box`` (u0, v0, u1, v1): the robot, not the frustum's image."""
    u0, v0, u1, v1 = box
    rows, cols = np.nonzero(_orange(image)[v0:v1, u0:u1])
    assert len(rows) > 20, "no robot meshes drawn around the robot"
    return np.array([cols.mean() + u0, rows.mean() + v0])


def test_the_browser_shows_the_scene_and_the_slider_moves_the_robot(folders, browser, free_port):
    content = load_content(folders["recon"])
    server = viser.ViserServer(host="127.0.0.1", port=free_port, verbose=False)
    viewer = Viewer(content, server)
    try:
        browser.get(f"http://127.0.0.1:{server.get_port()}")
        clients = _wait_for(server.get_clients, "the page to connect")
        camera = next(iter(clients.values())).camera

        def scene_shown():  # the twin's Gaussians cover a good part of the 3D view
            image = _screenshot(browser)
            drawn = (np.abs(image.astype(int) - 255).sum(-1) > 30) & _view_mask(image)
            return image if drawn.sum() > 0.05 * _view_mask(image).sum() else None

        _wait_for(scene_shown, "the twin's Gaussians to be drawn")
        viewer.set_layer("gaussians", False)
        viewer.set_layer("meshes", True)
        start = _wait_for(lambda: (lambda im: im if _links_hit(im, content, viewer, camera) >= 0.75 else None)(
            _screenshot(browser)), "the robot's meshes where the robot projects (frame 0)")
        demo, last = viewer.demo, len(viewer.demo) - 1
        arm = np.concatenate([_arm_pixels(content, demo, i, camera, start.shape) for i in (0, last)])
        box = (*(arm.min(axis=0) - 30).astype(int).clip(0), *(arm.max(axis=0) + 30).astype(int))
        before = _orange_centre(start, box)

        slider = browser.find_elements(By.CSS_SELECTOR, '[role="slider"]')[0]  # timeline: frame, then speed
        slider.send_keys(Keys.END)
        _wait_for(lambda: viewer.frame == last, "the frame slider to reach the last frame")
        end = _wait_for(lambda: (lambda im: im if _links_hit(im, content, viewer, camera) >= 0.75 else None)(
            _screenshot(browser)), "the robot's meshes where the robot projects at the last frame")
        after = _orange_centre(end, box)
        tcp = content.robot.tcp_pose(torch.as_tensor(demo.q[[0, last]])).numpy()[:, :3, 3]
        expected = np.diff(_project(tcp, camera, end.shape[1], end.shape[0]), axis=0)[0]
        assert np.linalg.norm(after - before) > 3  # the robot moved on screen
        assert np.dot(after - before, expected) > 0  # the way its TCP moved
    finally:
        viewer.close()
        server.stop()
