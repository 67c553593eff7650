"""``manisplat-episode``: inspect, validate, recover, import and synthesize episodes."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from manisplat.cli_args import numbers
from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.importers.act_hdf5 import ARM_COLUMNS, import_act_hdf5
from manisplat.episode.reader import Episode
from manisplat.episode.recover import recover
from manisplat.episode.summary import describe
from manisplat.episode.validate import validate


def _cmd_info(args: argparse.Namespace) -> int:
    print(describe(Episode.open(args.episode)))
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    status = 0
    for path in args.episodes:
        report = validate(path, decode_images=not args.quick, progress=sys.stderr.isatty())
        print(report)
        status = max(status, 0 if report.ok else 1)
    return status


def _cmd_recover(args: argparse.Namespace) -> int:
    report = recover(args.episode, drop_damaged=args.drop_damaged)
    print(report)
    return 0 if report.validation is None or report.validation.ok else 1


def _cmd_import_act(args: argparse.Namespace) -> int:
    fx, fy, cx, cy = args.K
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    episode = import_act_hdf5(args.file, args.out, K=K, arm=args.arm, camera=args.camera, fps=args.fps,
                              gripper_scale=args.gripper_scale, dist=args.dist, mount=args.mount, bgr=args.bgr,
                              robot_description=args.robot_description, task=args.task,
                              image_format=args.image_format, overwrite=args.overwrite)
    print(f"imported {len(episode)} frames from {args.file} into {episode.path}")
    return 0


def _cmd_sample(args: argparse.Namespace) -> int:
    from manisplat.episode.synthetic import write_sample_episode

    path = write_sample_episode(args.out, frames=args.frames, fps=args.fps, width=args.width, height=args.height,
                                seed=args.seed, task=args.task, overwrite=args.overwrite)
    print(f"wrote the sample episode ({args.frames} frames, {args.width}x{args.height}) to {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``manisplat-episode`` and its subcommands."""
    parser = argparse.ArgumentParser(
        prog="manisplat-episode",
        description="Inspect, validate, recover, import and synthesize ManiSplat episodes (format v1).")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-v: info, -vv: debug); default: warnings only")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("info", help="print a summary of an episode",
                       description="Print a summary of an episode: frames, duration, declared and measured "
                                   "fps, joint ranges (degrees), gripper range (mm), camera, files present "
                                   "and whether it is complete.")
    p.add_argument("episode", type=Path, help="episode folder")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("validate", help="check episodes against the format; exit 1 if any has an error",
                       description="Check every file of each episode and list every problem with its file and "
                                   "row. Exit status: 0 all valid (warnings allowed), 1 an error in any "
                                   "episode, 2 usage error.")
    p.add_argument("episodes", type=Path, nargs="+", metavar="EPISODE", help="episode folder(s)")
    p.add_argument("--quick", action="store_true",
                   help="only check that image files exist and are not empty, without decoding them "
                        "(misses truncated or wrong-size images)")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("recover", help="make an interrupted episode valid again without losing complete frames",
                       description="Make an episode whose writer was killed valid again. Crash artefacts "
                                   "(temporary files, a torn last row, images without a row, trailing rows with "
                                   "missing or truncated images) and the original CSV files are moved into "
                                   "EPISODE/.recovered/<time>/; nothing is deleted. A complete, valid episode is "
                                   "left unchanged. Damage followed by good frames is refused unless "
                                   "--drop-damaged.")
    p.add_argument("episode", type=Path, help="episode folder")
    p.add_argument("--drop-damaged", action="store_true",
                   help="also move aside damaged frames in the middle and renumber the remaining ones")
    p.set_defaults(func=_cmd_recover)

    p = sub.add_parser("import-act", help="convert an ACT / ALOHA / Cobot Magic HDF5 episode",
                       description="Convert one ACT-style HDF5 episode (observations/qpos, observations/images/"
                                   "<cam>, optional images_depth and action) into an episode folder, frame by "
                                   "frame. The file holds no intrinsics: --K is required.")
    p.add_argument("file", type=Path, metavar="FILE.hdf5", help="the HDF5 episode")
    p.add_argument("--out", type=Path, required=True, help="episode folder to create")
    p.add_argument("--K", type=numbers((4,)), required=True, metavar="fx,fy,cx,cy",
                   help="camera intrinsics in pixels (required: these files store none)")
    p.add_argument("--arm", choices=sorted(ARM_COLUMNS), default="left",
                   help="which arm of a 14-column dual-arm file, or 'single' for 7 columns (default left)")
    p.add_argument("--camera", default="cam_high", help="image dataset under observations/images (default cam_high)")
    p.add_argument("--fps", type=float, default=30.0, help="recording rate in Hz; t = index / fps (default 30)")
    p.add_argument("--gripper-scale", type=float, default=1.0,
                   help="factor from the file's gripper value to the finger gap in metres (default 1)")
    p.add_argument("--dist", type=numbers((0, 4, 5, 8, 12, 14)), default=[], metavar="k1,k2,...",
                   help="OpenCV distortion coefficients (default none)")
    p.add_argument("--mount", default="base", help="'base' or the link a wrist camera is fixed to (default base)")
    p.add_argument("--bgr", action="store_true", help="the stored images are BGR (default: RGB, as Cobot Magic stores)")
    p.add_argument("--robot-description", default="builtin:agilex_piper",
                   help="how to read the joint angles: URDF path or builtin:agilex_piper (default)")
    p.add_argument("--task", help="task description stored in episode.json")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png", help="rgb file format (default png)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing episode at --out")
    p.set_defaults(func=_cmd_import_act)

    p = sub.add_parser("sample", help="write the built-in synthetic pick-and-place episode",
                       description="Write the built-in sample: the built-in PiPER picks a 4 cm box and places it "
                                   "18 cm away, seen by a fixed camera, with RGB, depth, masks, 200 Hz joints, "
                                   "actions and exact ground truth (gt.npz). Needs no files or devices.")
    p.add_argument("out", type=Path, metavar="OUT", help="episode folder to create")
    p.add_argument("--frames", type=int, default=64, help="number of frames; the motion is stretched over them (default 64)")
    p.add_argument("--fps", type=float, default=16.0, help="frame rate in Hz (default 16)")
    p.add_argument("--width", type=int, default=160, help="image width in pixels (default 160)")
    p.add_argument("--height", type=int, default=120, help="image height in pixels (default 120)")
    p.add_argument("--seed", type=int, default=0, help="0: the nominal camera; others move it by up to 5 cm (default 0)")
    p.add_argument("--task", choices=("pick_place", "reach"), default="pick_place",
                   help="pick_place: the box is picked and placed; reach: the arm hovers over it (default pick_place)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing episode at OUT")
    p.set_defaults(func=_cmd_sample)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``manisplat-episode`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2)
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2),
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (EpisodeFormatError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
