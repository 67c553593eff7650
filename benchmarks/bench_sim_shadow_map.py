"""Issue 33: how much of a Cobot Magic sample's images is its simulator's shadow map.

The held-out frames' exact states (``*.gt.npz``) drawn again by the simulator
(``benchmarks/sim_render_bimanual_states.py``, no physics) with the scene's shadow map and with a
finer one, each through the recorder's JPEG, and scored against the recording per camera and
region: the first shows the re-render reproduces the recording; the second, what a renderer
exact in everything but the shadow map's texels (the stair-stepped edges of the key light's
shadows, which a wrist camera a few centimetres above the table sees several pixels wide)
would score. Neither trains anything: it says how much of a held-out PSNR goal the samples'
shadow-map texels take before any twin is scored. The scene's re-render is also scored as
drawn (no JPEG) and with only its colour subsampled as the recording's JPEG kept it
(:mod:`manisplat.reconstruct.chroma`, what a twin's render goes through before it is scored):
what a renderer right in every pixel scores against the recording without, and with, that model.

``MANISPLAT_SIMENV=SIMENV/bin/python python -m benchmarks sim_shadow_map [--samples S,...]
[--map-px 8192] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

import cv2
import h5py
import numpy as np

from benchmarks._harness import BENCH_DIR, shared_dir, simulator_python
from benchmarks._simulator import SimJob, run_sim_jobs
from manisplat.cli_args import positive
from manisplat.episode.images import StoredChroma, jpeg_chroma_subsampling

OWN_OPTIONS = True
SAMPLES = ("cobot_dual_small", "cobot_handover_small")
CAMERAS = ("cam_high", "cam_left_wrist", "cam_right_wrist")


def recorder_jpeg_bytes(rgb: np.ndarray, quality: int) -> bytes:
    """``rgb`` [H, W, 3] uint8 as the Cobot Magic recorder stores it: ``cv2.imencode`` of the RGB
    array (taken for BGR, so the chroma is subsampled on swapped channels) at ``quality``."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("cv2.imencode failed")
    return buf.tobytes()


def recorder_jpeg(rgb: np.ndarray, quality: int) -> np.ndarray:
    """``rgb`` [H, W, 3] uint8 as a reader gets it back from the recorder's JPEG
    (:func:`recorder_jpeg_bytes`, then ``cv2.imdecode``)."""
    return cv2.imdecode(np.frombuffer(recorder_jpeg_bytes(rgb, quality), np.uint8), cv2.IMREAD_COLOR)


def chroma_as_recorded(images: np.ndarray, stored: StoredChroma) -> np.ndarray:
    """``images`` [N, H, W, 3] uint8 with their colour subsampled as ``stored`` says the recording
    kept it (the reconstruction's model of the JPEG, without its quantisation), rounded to uint8."""
    import torch  # here: --help, and the benchmarks importing this module's helpers, stay quick

    from manisplat.reconstruct.chroma import subsample_chroma

    modelled = np.stack([subsample_chroma(torch.from_numpy(image).double(), stored).numpy() for image in images])
    return np.clip(np.rint(modelled), 0, 255).astype(np.uint8)


def recorded_chroma(sample: Path, camera: str) -> StoredChroma:
    """How the recording kept ``camera``'s colour: its first JPEG frame's subsampling, on the RGB
    arrays the recorder hands ``cv2.imencode`` (red taken for blue)."""
    with h5py.File(sample / "episode_0.hdf5", "r") as f:
        scheme = jpeg_chroma_subsampling(np.asarray(f[f"observations/images/{camera}"][0]).tobytes())
    return StoredChroma(scheme or "4:4:4", red_blue_swapped=True)


def region_of(label_names: list[str], manipulated: list[str]) -> dict[str, np.ndarray]:
    """Region -> label ids [K] of ``gen_bimanual.py``'s labels: the robot (both arms' links and
    wrist cameras), the ``manipulated`` objects and the static rest (background, mats, the others)."""
    names = list(map(str, label_names))
    robot = [i for i, n in enumerate(names) if n.startswith(("left/", "right/"))]
    objects = [i for i, n in enumerate(names) if n in {f"object/{m}" for m in manipulated}]
    static = [i for i in range(len(names)) if i not in robot and i not in objects]
    return {"static": np.array(static), "robot": np.array(robot), "object": np.array(objects)}


def region_psnr(images: np.ndarray, reference: np.ndarray, labels: np.ndarray,
                regions: dict[str, np.ndarray]) -> dict[str, float | None]:
    """PSNR (dB, 8-bit) of ``images`` [N, H, W, 3] against ``reference`` over every pixel ("full")
    and over each region's pixels (``labels`` [N, H, W], region -> label ids); None for a region
    no frame shows, inf where it matches exactly."""
    err = ((images.astype(np.float64) - reference.astype(np.float64)) ** 2).mean(axis=-1)
    out = {"full": _psnr(err.mean())}
    for name, ids in regions.items():
        inside = np.isin(labels, ids)
        out[name] = _psnr(err[inside].mean()) if inside.any() else None
    return out


def _psnr(mse: float) -> float:
    return float("inf") if mse == 0 else round(float(10 * np.log10(255.0 ** 2 / mse)), 2)


def recorded(sample: Path, frames: list[int]) -> dict[str, np.ndarray]:
    """Camera -> the recording's RGB images [N, H, W, 3] at ``frames``, decoded as the recorder
    encoded them (``cv2.imdecode`` of its bytes gives RGB)."""
    out = {}
    with h5py.File(sample / "episode_0.hdf5", "r") as f:
        for camera in CAMERAS:
            ds = f[f"observations/images/{camera}"]
            out[camera] = np.stack([cv2.imdecode(np.asarray(ds[i]), cv2.IMREAD_COLOR) for i in frames])
    return out


def write_states(path: Path, gt: Mapping[str, np.ndarray], objects: list[str], frames: list[int] | slice) -> Path:
    """The ground truth ``gt``'s exact states at ``frames`` (joints with gaps, each of ``objects``'
    poses) in ``path``, as ``sim_render_bimanual_states.py`` reads them; returns ``path``."""
    np.savez(path, q=gt["q"][frames], **{f"T_world_{k}": gt[f"T_world_{k}"][frames] for k in objects})
    return path


def redraw_job(sample: Path, task: str, states: Path, render: Path, report: Path, *options: str) -> SimJob:
    """The job that draws the ``states`` (:func:`write_states`) of ``sample``, a recording of
    ``task``, again with ``sim_render_bimanual_states.py`` (and its further ``options``) into
    ``render``, reporting to ``report``."""
    return SimJob(str(BENCH_DIR / "sim_render_bimanual_states.py"),
                  (str(states), "--calib", str(sample / "episode_0.calib.json"), "--task", task,
                   "--render", str(render), *options), report)


def rendered(folder: Path, camera: str, count: int) -> np.ndarray:
    """[count, H, W, 3] RGB renders of ``sim_render_bimanual_states.py`` for ``camera``."""
    return np.stack([cv2.cvtColor(cv2.imread(str(folder / camera / "rgb" / f"{k:06d}.png")), cv2.COLOR_BGR2RGB)
                     for k in range(count)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks sim_shadow_map", description=__doc__.splitlines()[0])
    p.add_argument("--samples", default=",".join(SAMPLES), help=f"shared Cobot Magic samples (default {','.join(SAMPLES)})")
    p.add_argument("--map-px", type=positive(int), default=8192, help="the finer shadow map's size (default 8192)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "sim_shadow_map.json")
    args = p.parse_args(argv)
    options = sys.argv[1:] if argv is None else argv
    from manisplat.reconstruct.plan import HOLDOUT_EVERY, HOLDOUT_OFFSET  # after the arguments: --help stays quick

    simenv, shared = simulator_python(), shared_dir()
    t0 = time.perf_counter()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.samples.split(","):
            sample = shared / "data" / name
            gt = np.load(sample / "episode_0.gt.npz")
            info = json.loads(str(gt["info"]))
            frames = list(range(HOLDOUT_OFFSET, len(gt["q"]), HOLDOUT_EVERY))  # the reconstruction's held-out frames
            spec = json.loads((sample / "episode_0.objects.json").read_text())
            manipulated = [k for k, o in spec["objects"].items() if o["role"] == "manipulated"]
            maps = {"scene": (), "fine": ("--shadow-map-px", str(args.map_px))}
            states = write_states(Path(tmp) / f"{name}_states.npz", gt, list(spec["objects"]), frames)
            jobs = [redraw_job(sample, spec["task"], states, Path(tmp) / f"{name}_{key}", Path(tmp) / f"{name}_{key}.json",
                               *extra) for key, extra in maps.items()]
            run_sim_jobs(simenv, jobs)
            map_px = {key: json.loads(job.report.read_text())["shadow_map_px"] for key, job in zip(maps, jobs)}
            quality = int(info["args"]["jpeg_quality"])
            recording, regions = recorded(sample, frames), region_of(gt["label_names"], manipulated)
            per_camera = {}
            for camera in CAMERAS:
                labels = gt[f"masks_{camera}"][frames]
                images = {key: rendered(Path(tmp) / f"{name}_{key}", camera, len(frames)) for key in maps}
                per_camera[camera] = {
                    f"re-rendered, {map_px['scene']} px map, jpeg": region_psnr(
                        np.stack([recorder_jpeg(x, quality) for x in images["scene"]]), recording[camera], labels, regions),
                    f"re-rendered, {map_px['fine']} px map, jpeg": region_psnr(
                        np.stack([recorder_jpeg(x, quality) for x in images["fine"]]), recording[camera], labels, regions),
                    f"{map_px['fine']} against {map_px['scene']} px map, no jpeg": region_psnr(
                        images["fine"], images["scene"], labels, regions),
                    f"re-rendered, {map_px['scene']} px map, no jpeg": region_psnr(
                        images["scene"], recording[camera], labels, regions),
                    f"re-rendered, {map_px['scene']} px map, chroma subsampled as modelled": region_psnr(
                        chroma_as_recorded(images["scene"], recorded_chroma(sample, camera)), recording[camera],
                        labels, regions),
                }
                print(name, camera, json.dumps(per_camera[camera]), flush=True)
            results[name] = {"frames": frames, "jpeg_quality": quality, "shadow_map_px": map_px, "cameras": per_camera}
    result = {"benchmark": "sim_shadow_map", "command": " ".join(["python -m benchmarks sim_shadow_map", *options]),
              "regions": "full; static (background, mats, objects left alone); robot (links, wrist cameras); object (manipulated)",
              "samples": results, "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0
