"""Issue 33: what the simulator's headlight costs a twin trained on several cameras.

MuJoCo lights every image it draws with a headlight of that image's camera (the shared scenes:
ambient 0.25, diffuse 0.35 along the camera's axis), so one surface is brighter in a camera that
faces it than in one that sees it obliquely. A real camera carries no light, and a twin gives a
surface one colour (view-dependent only through its SH bands): the head camera and a wrist camera
ask it for different ones. This benchmark draws copies of the shared Cobot Magic samples without
the headlight's diffuse part (``shared/tools/sim`` copied, the copy's scene patched; the same
arguments as the sample's, so the same states, which it checks against the sample's ``gt.npz``),
measures the headlight's share of each camera's light per region, and reconstructs the copies as
``reconstruct_cobot`` reconstructs the shared samples.

``MANISPLAT_SIMENV=SIMENV/bin/python python -m benchmarks sim_headlight [--samples S,...]
[--settings all,head] [--iters 3000] [--work DIR] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, shared_dir, simulator_python
from benchmarks._simulator import sim_env
from benchmarks.bench_sim_shadow_map import CAMERAS, recorded, region_of
from manisplat.cli_args import positive

OWN_OPTIONS = True
SCENE = "bimanual_scene.xml"
HEADLIGHT = re.compile(r"<headlight\b[^>]*>")
DIFFUSE = re.compile(r'\bdiffuse="[^"]*"')
STATES = ("q", "gripper")  # with every T_world_* of the ground truth: what the copy must repeat
MIN_PIXELS = 50  # a region's pixels in a frame below which its share is not taken
SAME_STATE = 1e-6  # m, rad: the largest difference of a state drawn again (another machine's physics: ~1e-12)


def without_headlight(scene: str) -> str:
    """``scene`` (MJCF text) with its headlight's diffuse part set to zero (ambient and specular
    kept). ValueError unless the scene has exactly one ``<headlight>`` with a ``diffuse``."""
    lights = HEADLIGHT.findall(scene)
    if len(lights) != 1 or not DIFFUSE.search(lights[0]):
        raise ValueError(f"expected one <headlight ... diffuse=...> element, found {lights or 'none'}")
    return scene.replace(lights[0], DIFFUSE.sub('diffuse="0 0 0"', lights[0]), 1)


def simulator_copy(shared: Path, root: Path) -> Path:
    """``shared/tools/sim`` copied to ``root/tools/sim`` with :func:`without_headlight` applied to
    its scene, ``root/robots`` linked to ``shared/robots`` (the tools find the robot two folders
    up). The copy's sim folder."""
    sim = root / "tools" / "sim"
    if not sim.exists():
        shutil.copytree(shared / "tools" / "sim", sim)
        (sim / SCENE).write_text(without_headlight((sim / SCENE).read_text()))
    if not (root / "robots").exists():
        (root / "robots").symlink_to(shared / "robots")
    return sim


def generator_args(info: dict) -> list[str]:
    """``gen_bimanual.py``'s arguments that drew a sample, from its ``gt.npz["info"]["args"]``."""
    a = info["args"]
    args = ["--task", a["task"], "--seed", str(a["seed"]), "--object-range", *map(str, a["object_range"]),
            "--width", str(a["width"]), "--height", str(a["height"]), "--fps", str(a["fps"]),
            "--jpeg-quality", str(a["jpeg_quality"]), "--tilt-deg", str(a["tilt_deg"]),
            "--cam-high-pos", *map(str, a["cam_high_pos"]), "--cam-high-target", *map(str, a["cam_high_target"]),
            "--cam-high-fovy", str(a["cam_high_fovy"]), "--timestep", str(a["timestep"]),
            "--control-dt", str(a["control_dt"])]
    if a.get("frames") is not None:
        args += ["--frames", str(a["frames"])]
    if a.get("compress"):
        args.append("--compress")
    if a.get("record_noise"):
        args += ["--record-noise", *(["--noise-seed", str(a["noise_seed"])] if a.get("noise_seed") is not None else [])]
    if a.get("no_shadows"):
        args.append("--no-shadows")
    return args


def drawn_again(simenv: Path, sim: Path, sample: Path, out: Path) -> Path:
    """``sample`` drawn by the simulator copy ``sim`` into ``out`` (once) with the arguments that
    drew it; RuntimeError unless the copy's states are the sample's (within :data:`SAME_STATE`)."""
    truth = np.load(sample / "episode_0.gt.npz")
    if not (out / "episode_0.hdf5").exists():
        args = generator_args(json.loads(str(truth["info"])))
        done = subprocess.run([str(simenv), "gen_bimanual.py", *args, "--out", str(out)], cwd=sim, env=sim_env(),
                              stdout=subprocess.DEVNULL, check=False)
        if done.returncode != 0 or not (out / "episode_0.hdf5").exists():
            raise RuntimeError(f"gen_bimanual.py {' '.join(args)} exited {done.returncode}")
    copy = np.load(out / "episode_0.gt.npz")
    keys = [*STATES, *(k for k in truth.files if k.startswith("T_world_"))]
    if differ := [k for k in keys if k not in copy.files or truth[k].shape != copy[k].shape
                  or not np.allclose(truth[k], copy[k], rtol=0.0, atol=SAME_STATE)]:
        raise RuntimeError(f"{out}: the states drawn again differ from {sample}'s ({', '.join(differ)})")
    return out


def headlight_share(lit: Path, unlit: Path, frames: list[int]) -> dict[str, dict[str, dict[str, float]]]:
    """Camera -> region -> the headlight's share of the recorded light (1 - unlit / lit summed over
    the region's pixels of a frame): median, lowest and highest over ``frames``."""
    truth = np.load(lit / "episode_0.gt.npz")
    spec = json.loads((lit / "episode_0.objects.json").read_text())
    regions = region_of(truth["label_names"], [k for k, o in spec["objects"].items() if o["role"] == "manipulated"])
    with_light, without = recorded(lit, frames), recorded(unlit, frames)
    out: dict[str, dict[str, dict[str, float]]] = {}
    for camera in CAMERAS:
        out[camera] = {}
        masks = truth[f"masks_{camera}"][frames]  # read once: each key of an npz decompresses the whole array
        for region, ids in {"full": None, **regions}.items():
            shares = []
            for k, labels in enumerate(masks):
                inside = np.ones(labels.shape, bool) if ids is None else np.isin(labels, ids)
                lit_sum = float(with_light[camera][k][inside].astype(np.float64).sum())
                if inside.sum() >= MIN_PIXELS and lit_sum > 0:
                    shares.append(1.0 - float(without[camera][k][inside].astype(np.float64).sum()) / lit_sum)
            if shares:
                out[camera][region] = {"median": round(float(np.median(shares)), 3), "min": round(min(shares), 3),
                                       "max": round(max(shares), 3), "frames": len(shares)}
    return out


def made_by(reconstructed: Path) -> set[tuple[str, str, int]]:
    """(sample, setting, iterations) of every row of a ``reconstruct_cobot`` JSON."""
    return {(row["sample"], row["setting"], row["iters"]) for row in json.loads(reconstructed.read_text())["rows"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks sim_headlight", description=__doc__.splitlines()[0])
    p.add_argument("--samples", default="cobot_dual_small", help="shared Cobot Magic samples (default cobot_dual_small)")
    p.add_argument("--settings", default="all,head", help="reconstruct_cobot --settings (default all,head)")
    p.add_argument("--iters", type=positive(int), default=3000, help="training iterations (default 3000)")
    p.add_argument("--work", type=Path, help="the simulator's copy, the samples drawn again and their reconstructions "
                                              "(reconstruct_cobot.json), reused when present (default a temporary folder)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "sim_headlight.json")
    args = p.parse_args(argv)
    from benchmarks.bench_reconstruct_cobot import SETTINGS, main as reconstruct_cobot  # the pipeline: after --help
    if unknown := sorted(set(args.settings.split(",")) - set(SETTINGS)):
        p.error(f"--settings: unknown {', '.join(unknown)} (choose from {', '.join(SETTINGS)})")
    from manisplat.reconstruct.plan import HOLDOUT_EVERY, HOLDOUT_OFFSET

    simenv, shared = simulator_python(), shared_dir()
    work = (args.work or Path(tempfile.mkdtemp(prefix="sim_headlight_"))).resolve()
    t0 = time.perf_counter()
    sim = simulator_copy(shared, work)
    shares = {}
    for name in args.samples.split(","):
        copy = drawn_again(simenv, sim, shared / "data" / name, work / "data" / name)
        frames = list(range(HOLDOUT_OFFSET, len(np.load(copy / "episode_0.gt.npz")["q"]), HOLDOUT_EVERY))
        shares[name] = headlight_share(shared / "data" / name, copy, frames)
        print(name, json.dumps(shares[name]), flush=True)
    reconstructed = work / "reconstruct_cobot.json"
    asked = {(name, SETTINGS[key][0], args.iters) for name in args.samples.split(",") for key in args.settings.split(",")}
    if not reconstructed.exists() or not asked <= made_by(reconstructed):
        code = reconstruct_cobot(["--data", str(work / "data"), "--samples", args.samples, "--settings", args.settings,
                                  "--iters", str(args.iters), "--out", str(reconstructed)])
        if code != 0:
            raise RuntimeError(f"reconstruct_cobot exited {code}")
    result = {"benchmark": "sim_headlight",
              "command": " ".join(["python -m benchmarks sim_headlight", *(sys.argv[1:] if argv is None else argv)]),
              "headlight": "the copies' scene: <headlight ambient=0.25 diffuse=0 specular=0> (the samples': diffuse 0.35)",
              "headlight_share_held_out": shares, "reconstruct_cobot": json.loads(reconstructed.read_text()),
              "wall_s": round(time.perf_counter() - t0, 1), "work": str(work)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0
