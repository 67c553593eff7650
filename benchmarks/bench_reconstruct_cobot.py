"""Issue 33, items 1-2: a two-arm, three-camera Cobot Magic recording reconstructed with every
camera, and with the head camera alone. Each shared sample (``cobot_dual_small``,
``cobot_handover_small``) is imported as the user does (``manisplat-episode import-act --calib``),
the manipulated objects are prompted by one pixel each in the head camera's first frame (the
projection of their start, as a click would give it), and ``manisplat-reconstruct --no-masks``
runs twice, ``--cameras cam_high,cam_left_wrist,cam_right_wrist`` and ``--cameras cam_high``: both
arms drawn and driven in the world frame, objects segmented from depth in the head camera and
followed, each aligned with the arm that handles it; the wrist cameras posed by forward kinematics
at every frame, their masks drawn. Scored against the simulator's ground truth, which only this
benchmark reads: held-out PSNR / SSIM per camera and region (the simulator's masks; the render's
colour subsampled as the recording's JPEG kept it, and ``psnr_full_colour`` as drawn), object pose
errors in the world frame (fitted and start-anchored), wall time and time per iteration.

``python -m benchmarks reconstruct_cobot [--samples cobot_dual_small,...] [--settings all,head] [--iters 3000]
[--shadow-casters meshes|gaussians] [--shadow-receivers all|background|shaded]
[--rasterize-mode auto|classic|antialiased] [--lambda-mask L]
[--lambda-pose L] [--lambda-smooth L] [--pose-rate-final F] [--light-response auto|on|off]
[--fixed-camera-share S] [--seed S] [--supersample N] [--shadow-map-px N]
[--threads N] [--data DIR] [--work DIR] [--out FILE]``: ``--settings all --iters 9000`` gives the head camera about as many iterations as
``--settings head --iters 3000`` (one camera's image an iteration).

With ``--supersample N`` (N odd, the simulator's python in ``MANISPLAT_SIMENV``) the samples are
recorded as a camera would record them: their own states (the ground truth) drawn N x N times
finer by ``sim_render_bimanual_states.py --supersample`` and averaged, each pixel the mean over
its area, then stored through the recorder's JPEG as the sample's images were; the depth, joints,
calibration and truth are the sample's (:func:`camera_like`). The simulator's own images filter
the objects' prints by mipmap level, blurrier in the head camera a metre away than in the wrist
cameras a few centimetres away, which a sensor integrating its pixels does not. With
``--shadow-map-px N`` they are also drawn with a shadow map of N x N texels (the samples': 2048):
a finer map leaves less of the stair-stepped shadow edges that no camera sees
(``python -m benchmarks sim_shadow_map`` measures what they cost).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import h5py
import numpy as np

from benchmarks._harness import BENCH_DIR, shared_dir, simulator_python
from benchmarks._simulator import run_sim_jobs
from manisplat.cli_args import bounded, non_negative, open_fraction_or, positive
from manisplat.episode.cli import main as episode_main
from manisplat.episode.groundtruth import write_gt
from manisplat.reconstruct.cli import main as reconstruct_main
from manisplat.reconstruct.config import (FIXED_CAMERA_SHARE_WORDS, LIGHT_RESPONSE_CHOICES, RASTERIZE_CHOICES,
                                          SHADOW_CASTERS, SHADOW_RECEIVERS)

OWN_OPTIONS = True
HEAD = "cam_high"
CAMERAS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
SAMPLES = ("cobot_dual_small", "cobot_handover_small")
SETTINGS = {"all": ("all cameras", CAMERAS), "head": ("head camera alone", (HEAD,))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks reconstruct_cobot", description=__doc__.splitlines()[0])
    p.add_argument("--samples", default=",".join(SAMPLES), help=f"shared samples (default {','.join(SAMPLES)})")
    p.add_argument("--settings", default="all,head", help="which cameras to train: all, head or both (default all,head)")
    p.add_argument("--iters", type=int, default=3000, help="training iterations (default 3000, the CPU default)")
    p.add_argument("--shadow-casters", choices=SHADOW_CASTERS, default="gaussians",
                   help="manisplat-reconstruct --shadow-casters (default gaussians)")
    p.add_argument("--shadow-receivers", choices=SHADOW_RECEIVERS, default="all",
                   help="manisplat-reconstruct --shadow-receivers (default all, as the command's)")
    p.add_argument("--rasterize-mode", choices=RASTERIZE_CHOICES, default="auto",
                   help="manisplat-reconstruct --rasterize-mode (default auto, as the command's)")
    add_training_flags(p)
    p.add_argument("--seed", type=int, default=0, help="manisplat-reconstruct --seed (default 0, the command's)")
    p.add_argument("--supersample", type=int, default=1, metavar="N",
                   help="record the samples as a camera would: their states drawn N x N times finer and averaged "
                        "(N odd; default 1, the samples' own images)")
    p.add_argument("--shadow-map-px", type=positive(int), metavar="N",
                   help="draw the samples again (as --supersample does) with a shadow map of N x N texels "
                        "(default: the samples' own images, or the scene's map with --supersample)")
    p.add_argument("--threads", type=positive(int), metavar="N",
                   help="manisplat-reconstruct --threads (default: the command's, the free cores; give 1 to each of "
                        "two runs side by side on 2 cores)")
    p.add_argument("--data", type=Path, help="the folder holding the samples (default shared/data; "
                                             "sim_headlight draws copies elsewhere)")
    p.add_argument("--work", type=Path, help="keep the imported samples and the twins here (default: a temporary folder)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "reconstruct_cobot.json")
    args = p.parse_args(argv)
    settings = args.settings.split(",")
    if unknown := sorted(set(settings) - set(SETTINGS)):
        p.error(f"--settings: unknown {', '.join(unknown)} (choose from {', '.join(SETTINGS)})")
    if args.fixed_camera_share not in (None, *FIXED_CAMERA_SHARE_WORDS) and "head" in settings:
        p.error("--fixed-camera-share: the head camera alone has no riding camera to share the iterations with; "
                "give --settings all")
    if args.supersample < 1 or args.supersample % 2 == 0:
        p.error(f"--supersample takes an odd number of at least 1, not {args.supersample}")
    if args.work is not None and args.work.exists() and any(args.work.iterdir()):
        p.error(f"--work: {args.work} is not empty; give a new or empty folder")
    data = args.data or shared_dir() / "data"
    if missing := [name for name in args.samples.split(",") if not (data / name / "episode_0.hdf5").is_file()]:
        p.error(f"--samples: no episode_0.hdf5 for {', '.join(missing)} in {data}")
    simenv = simulator_python() if args.supersample > 1 or args.shadow_map_px is not None else None
    rows = []
    t0 = time.perf_counter()
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=True)
    with contextlib.nullcontext(args.work) if args.work is not None else tempfile.TemporaryDirectory() as tmp:
        for sample in args.samples.split(","):
            drawn = f"camera_like_x{args.supersample}" + ("" if args.shadow_map_px is None else f"_map{args.shadow_map_px}")
            source = data if simenv is None else camera_like(simenv, data, sample, Path(tmp) / drawn, args.supersample,
                                                             args.shadow_map_px)
            episode, prompts = imported_sample(source, sample, Path(tmp))
            for setting, cameras in (SETTINGS[key] for key in settings):
                out = Path(tmp) / f"{sample}_{len(cameras)}"
                options = ("--shadow-casters", args.shadow_casters, "--shadow-receivers", args.shadow_receivers,
                           "--rasterize-mode", args.rasterize_mode, "--seed", str(args.seed))
                options += training_options(args)
                options += () if args.threads is None else ("--threads", str(args.threads))
                row = reconstruct(episode, out, cameras, prompts, args.iters, options)
                rows.append(row | {"sample": sample, "setting": setting})
                print(json.dumps(rows[-1], default=float), flush=True)
    result = {"benchmark": "reconstruct_cobot",
              "command": "python -m benchmarks reconstruct_cobot " + " ".join(argv if argv is not None else sys.argv[1:]),
              "data": str(data), "supersample": args.supersample, "shadow_map_px": args.shadow_map_px,
              "images": "the samples' own" if simenv is None else
              f"the samples' states drawn {args.supersample} x {args.supersample} times finer and averaged"
              + ("" if args.shadow_map_px is None else f" with a shadow map of {args.shadow_map_px} texels a side")
              + ", through the recorder's JPEG",
              "threads": "the free cores (manisplat-reconstruct's default)" if args.threads is None else args.threads,
              "rows": rows,
              "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0


def imported_sample(data: Path, sample: str, folder: Path) -> tuple[Path, dict[str, tuple[float, float]]]:
    """The Cobot Magic ``sample`` of ``data`` (shared/data or a copy) imported into ``folder`` as the
    user does, with its truth where evaluation reads it (:func:`add_ground_truth`), and each
    manipulated object's prompt."""
    source, episode = data / sample, folder / sample
    if episode_main(["import-act", str(source / "episode_0.hdf5"), "--calib", str(source / "episode_0.calib.json"),
                     "--out", str(episode)]) != 0:
        raise RuntimeError(f"{sample}: import failed")
    return episode, add_ground_truth(episode, source)


def camera_like(simenv: Path, data: Path, sample: str, folder: Path, n: int, shadow_map_px: int | None = None) -> Path:
    """A copy of ``data/sample`` in ``folder/data/sample`` whose images are its own states (its
    ground truth's joints, gaps and object poses) drawn ``n`` x ``n`` times finer and averaged
    (with a shadow map of ``shadow_map_px`` texels a side where given, else the scene's),
    each through the recorder's JPEG at the sample's quality (the fingers drawn symmetric about
    their gap, as a twin draws them, where physics pushed one pad further while gripping); the
    depth, joints, calibration and truth are the sample's (``folder/robots`` links shared/robots,
    where the calibration's relative URDF path leads). Made once and kept; returns
    ``folder/data``, the copy's data folder."""
    from benchmarks.bench_sim_shadow_map import recorder_jpeg_bytes, redraw_job, write_states  # keeps --help quick

    source, copy = data / sample, folder / "data" / sample
    if (copy / "episode_0.hdf5").is_file():
        return copy.parent
    gt = np.load(source / "episode_0.gt.npz")
    spec = json.loads((source / "episode_0.objects.json").read_text())
    copy.parent.mkdir(parents=True, exist_ok=True)
    if not (folder / "robots").is_symlink():
        (folder / "robots").symlink_to(shared_dir() / "robots")
    drawn = folder / f"{sample}_drawn"
    states = write_states(folder / f"{sample}_states.npz", gt, list(spec["objects"]), slice(None))
    finer = () if shadow_map_px is None else ("--shadow-map-px", str(shadow_map_px))
    run_sim_jobs(simenv, [redraw_job(source, spec["task"], states, drawn, drawn / "render.json",
                                     "--supersample", str(n), *finer, "--workers", "2")], workers=1)
    quality = int(json.loads(str(gt["info"]))["args"]["jpeg_quality"])
    part = copy.parent / f"{sample}.part"
    shutil.rmtree(part, ignore_errors=True)
    shutil.copytree(source, part)
    with h5py.File(part / "episode_0.hdf5", "r+") as f:
        lengths = np.asarray(f["compress_len"], dtype=np.float32)
        if lengths.shape != (len(CAMERAS), len(gt["q"])):
            raise RuntimeError(f"{source}: compress_len is {lengths.shape}, not one row of {len(gt['q'])} frames "
                               f"per camera of {', '.join(CAMERAS)}")
        for row, camera in enumerate(CAMERAS):
            frames = [recorder_jpeg_bytes(cv2.cvtColor(cv2.imread(str(drawn / camera / "rgb" / f"{k:06d}.png")),
                                                       cv2.COLOR_BGR2RGB), quality) for k in range(len(gt["q"]))]
            padded = np.zeros((len(frames), max(map(len, frames))), np.uint8)
            for k, encoded in enumerate(frames):
                padded[k, :len(encoded)] = np.frombuffer(encoded, np.uint8)
                lengths[row, k] = len(encoded)
            del f[f"observations/images/{camera}"]
            f["observations/images"].create_dataset(camera, data=padded, chunks=(1, padded.shape[1]),
                                                    compression="gzip", compression_opts=4)
        f["compress_len"][...] = lengths
    part.rename(copy)
    return copy.parent


def _light_response(value: str) -> str:
    """``--light-response``'s value, one of the command's choices."""
    if value not in LIGHT_RESPONSE_CHOICES:
        raise argparse.ArgumentTypeError(f"{value!r} is none of {', '.join(LIGHT_RESPONSE_CHOICES)}")
    return value


#: manisplat-reconstruct's training settings passed on when given, each validated as the command does
TRAINING_FLAGS = {"--lambda-mask": non_negative(), "--lambda-pose": non_negative(), "--lambda-smooth": non_negative(),
                  "--pose-rate-final": bounded(1e-6, 1.0), "--light-response": _light_response,
                  "--fixed-camera-share": open_fraction_or(FIXED_CAMERA_SHARE_WORDS)}


def add_training_flags(parser: argparse.ArgumentParser) -> None:
    """Add :data:`TRAINING_FLAGS` to ``parser`` (unset: the command's default)."""
    for flag, kind in TRAINING_FLAGS.items():
        parser.add_argument(flag, type=kind, help=f"manisplat-reconstruct {flag} (default: the command's)")


def training_options(args: argparse.Namespace) -> tuple[str, ...]:
    """manisplat-reconstruct's options for the settings of :data:`TRAINING_FLAGS` given in ``args``."""
    return tuple(part for flag in TRAINING_FLAGS if (value := getattr(args, flag[2:].replace("-", "_"))) is not None
                 for part in (flag, str(value)))


def reconstruct(episode: Path, out: Path, cameras: tuple[str, ...], prompts: dict[str, tuple[float, float]],
                iters: int, options: tuple[str, ...] = ()) -> dict:
    """One timed ``manisplat-reconstruct`` run (with further ``options``) and its figures."""
    logging.disable(logging.WARNING)
    start = time.perf_counter()
    try:
        code = reconstruct_main([str(episode), "--out", str(out), "--cameras", ",".join(cameras), "--no-masks",
                                 "--quiet", "--iters", str(iters), *options]
                                + [a for name, (u, v) in prompts.items() for a in ("--object-point", f"{name}={u:.0f},{v:.0f}")])
    finally:
        logging.disable(logging.NOTSET)
    wall = time.perf_counter() - start
    if code != 0:
        raise RuntimeError(f"{episode.name}: manisplat-reconstruct exited {code}")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"cameras": list(cameras), "iters": iters, "wall_s": round(wall, 1), "ms_per_iter": metrics.get("ms_per_iter"),
            "options": list(options), "light": metrics.get("light"), "rasterize_mode": metrics.get("rasterize_mode"),
            "eps2d": metrics.get("eps2d"), "lambda_mask": metrics.get("lambda_mask"), "lambda_pose": metrics.get("lambda_pose"),
            "lambda_smooth": metrics.get("lambda_smooth"), "pose_rate_final": metrics.get("pose_rate_final"),
            "light_response": metrics.get("light_response"), "fixed_camera_share": metrics.get("fixed_camera_share"),
            "prompts": {k: [round(u), round(v)] for k, (u, v) in prompts.items()},
            "per_camera": {name: {"psnr": m["psnr"], "ssim": m["ssim"], "psnr_full_colour": m.get("psnr_full_colour")}
                           for name, m in metrics.get("cameras", {HEAD: metrics}).items()},
            "pose": metrics.get("pose"), "pose_anchored": metrics.get("pose_anchored"),
            "pose_pseudo": metrics.get("pose_pseudo"), "camera_check": metrics.get("camera")}


def add_ground_truth(episode: Path, source: Path) -> dict[str, tuple[float, float]]:
    """Put the simulator's truth where evaluation reads it (``gt.npz``: ``T_world_<object>`` of the
    manipulated objects; every camera's masks and the labels, which ``--no-masks`` keeps for scoring
    only) and return each manipulated object's prompt: its start projected into the head camera's
    first frame."""
    objects = json.loads((source / "episode_0.objects.json").read_text())["objects"]
    manipulated = [name for name, o in objects.items() if o["role"] == "manipulated"]
    gt = np.load(source / "episode_0.gt.npz")
    write_gt(episode / "gt.npz", {"t": gt["t"], **{f"T_world_{name}": gt[f"T_world_{name}"] for name in manipulated}},
             compressed=True)
    for camera in CAMERAS:
        masks = episode / "masks" / camera
        masks.mkdir(parents=True)
        for i, image in enumerate(gt[f"masks_{camera}"]):
            cv2.imwrite(str(masks / f"{i:06d}.png"), image)
    meta_path = episode / "episode.json"
    meta = json.loads(meta_path.read_text())
    meta["labels"] = {str(v): _label(name) for v, name in enumerate(gt["label_names"].tolist())}
    meta["objects"] = manipulated
    meta_path.write_text(json.dumps(meta, indent=1) + "\n")
    camera = meta["cameras"][HEAD]
    K, T_cam_world = np.asarray(camera["K"]), np.linalg.inv(np.asarray(camera["T_mount_cam"]))
    prompts = {}
    for name in manipulated:
        x = T_cam_world[:3, :3] @ np.asarray(objects[name]["T_start"])[:3, 3] + T_cam_world[:3, 3]
        u, v, w = K @ x
        prompts[name] = (u / w, v / w)
    return prompts


def _label(name: str) -> str:
    """The simulator's label name as an episode's: what rides on an arm is ``robot/<arm>/<part>``."""
    arm, _, link = name.partition("/")
    return f"robot/{name}" if arm in ("left", "right") and link else name  # links and the wrist cameras


if __name__ == "__main__":
    sys.exit(main())
