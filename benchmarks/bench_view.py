"""manisplat-view: start-up, page load and frames per second in a headless browser, and --video
speed, for the built-in sample's twin and a 300k-Gaussian twin.

The sample's twin: ``manisplat-episode sample`` (64 frames, 160x120) reconstructed with
``--iters 1000`` (the README's first command). The 300k twin is that twin with its background
Gaussians copied (each copy shifted by a few millimetres) until the twin holds 300 000: a load
test of the viewer, not a reconstruction. The browser is Debian's chromium, headless, with
software WebGL (SwiftShader) on this machine's CPU cores: a worst case, far below a desktop GPU.
Page load: from the request to the first screenshot in which the Gaussians cover 5 % of the 3D
view. Frames per second: ``requestAnimationFrame`` callbacks per second over 5 s while the timeline
plays (each one a drawn frame). Screenshots of the three modes go to ``--out``.
"""

from __future__ import annotations

import shutil
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks._harness import BenchContext, MissingBenchmarkData

THREADED = False
TARGET_GAUSSIANS = 300_000
RAF_COUNTER = """
const done = arguments[arguments.length - 1];
let frames = 0; const start = performance.now();
function tick() { frames++; if (performance.now() - start < 5000) requestAnimationFrame(tick);
                  else done(frames / ((performance.now() - start) / 1000)); }
requestAnimationFrame(tick);
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _heavy_twin(source: Path, out: Path) -> int:
    """Copy the twin at ``source`` to ``out`` with its background tiled to TARGET_GAUSSIANS in all."""
    shutil.copytree(source, out)
    tensors = torch.load(out / "twin.pt", weights_only=True)
    total = sum(v.shape[0] for k, v in tensors.items() if k.startswith("node/") and k.endswith("/means"))
    keys = [k for k in tensors if k.startswith("node/background/")]
    count = tensors["node/background/means"].shape[0]
    copies = int(np.ceil((TARGET_GAUSSIANS - total + count) / count))
    rng = torch.Generator().manual_seed(0)
    for key in keys:
        tiled = tensors[key].repeat(copies, *([1] * (tensors[key].ndim - 1)))
        if key.endswith("/means"):
            tiled = tiled + 0.003 * torch.randn(tiled.shape, generator=rng, dtype=tiled.dtype)
        tensors[key] = tiled
    torch.save(tensors, out / "twin.pt")
    import json

    meta = json.loads((out / "twin.json").read_text())
    for node in meta["nodes"]:
        if node["name"] == "background":
            node["count"] = count * copies
    (out / "twin.json").write_text(json.dumps(meta, indent=1))
    return total - count + count * copies


def _browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    options.binary_location = shutil.which("chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader", "--window-size=1280,800", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    driver.set_script_timeout(60)
    return driver


def _screenshot(driver) -> np.ndarray:
    import cv2

    return cv2.imdecode(np.frombuffer(driver.get_screenshot_as_png(), np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]


def _measure(path: Path, shot: Path, ctx: BenchContext, select: int | None = None) -> dict[str, Any]:
    import viser
    from selenium.common.exceptions import TimeoutException

    from manisplat.view.app import Viewer
    from manisplat.view.content import load_content

    start = time.perf_counter()
    content = load_content(path)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    viewer = Viewer(content, server)
    startup_s = time.perf_counter() - start
    driver = _browser()
    try:
        start = time.perf_counter()
        driver.get(f"http://127.0.0.1:{server.get_port()}")
        drawn_s = None
        while time.perf_counter() - start < 300:
            try:
                image = _screenshot(driver)
            except TimeoutException:  # the renderer is busy for more than selenium's 10 s
                continue
            view = image[160:, : image.shape[1] - 360]
            if (np.abs(view.astype(int) - 255).sum(-1) > 30).mean() > 0.05:
                drawn_s = time.perf_counter() - start
                break
            time.sleep(0.2)
        if select is not None:
            viewer.select(select)
        viewer.set_frame(len(viewer.demo) // 2)
        time.sleep(2.0)
        try:
            driver.save_screenshot(str(shot))
            viewer._playing.value = True
            fps = float(driver.execute_async_script(RAF_COUNTER))
        except TimeoutException:
            fps = None  # not one frame in selenium's timeout
        viewer._playing.value = False
    finally:
        driver.quit()
        viewer.close()
        server.stop()
    gaussians = sum(len(n.gaussians) for n in content.twin.graph.nodes()) if content.twin is not None else 0
    return {"gaussians": gaussians, "startup_s": startup_s, "page_drawn_s": drawn_s, "browser_fps": fps}


def _cli_ready_s(path: Path) -> float:
    """Seconds from starting ``manisplat-view PATH`` in a new process to it printing its URL."""
    import subprocess
    import sys

    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "manisplat.view.cli", str(path), "--port", str(_free_port()), "-q"],
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        if "http://" not in line:
            raise RuntimeError(f"manisplat-view printed {line!r}")
        return time.perf_counter() - start
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    if shutil.which("chromium") is None or shutil.which("chromedriver") is None:
        raise MissingBenchmarkData("needs chromium and chromedriver (apt-get install chromium chromium-driver)")
    from manisplat.augment.cli import main as augment
    from manisplat.episode.synthetic import write_sample_episode
    from manisplat.reconstruct.cli import main as reconstruct
    from manisplat.view.content import load_content
    from manisplat.view.video import write_video

    rows = []
    iters = 100 if ctx.quick else 1000
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        episode = write_sample_episode(tmp / "demo_episode")
        assert reconstruct([str(episode), "--out", str(tmp / "demo_twin"), "--iters", str(iters), "-q"]) == 0
        assert augment([str(tmp / "demo_twin"), "--n", "3", "--out", str(tmp / "demo_aug"), "-q"]) == 0
        _heavy_twin(tmp / "demo_twin", tmp / "heavy_twin")
        cases = [("episode (sample)", episode, None), ("reconstruction (sample twin)", tmp / "demo_twin", None),
                 ("augmentation (sample twin, 3 new)", tmp / "demo_aug", 2),
                 ("reconstruction (300k-Gaussian twin)", tmp / "heavy_twin", None)]
        for name, path, select in cases:
            slug = name.split()[0] + ("_300k" if "300k" in name else "")
            row = {"case": name, "cli_ready_s": _cli_ready_s(path),
                   **_measure(path, ctx.out_dir / f"view_{slug}.png", ctx, select)}
            if name.startswith(("reconstruction", "augmentation")):
                content = load_content(path)
                video = write_video(content, tmp / f"{slug}.mp4")
                row.update({"video_frames": video.frames, "video_size": f"{video.width}x{video.height}",
                            "video_frames_per_s": video.frames_per_s})
            rows.append(row)
    ctx.notes.append("software WebGL (SwiftShader) in headless chromium on this machine's 2 CPU cores; cli_ready_s: "
                     "a new manisplat-view process until it prints its URL (imports included); startup_s: "
                     "load_content + building the viewer in a warm process; page_drawn_s: request to the Gaussians "
                     "drawn (empty: not within 300 s); browser_fps: empty when not one frame came in 60 s")
    return rows
