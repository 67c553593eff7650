"""``manisplat-episode``: inspect, validate, recover, import, export, synthesize, copy episodes and set their
robot or how their images kept their colour.

Only argparse and the shared argument checks are imported up front: each command imports what it
needs (OpenCV, h5py, torch) after the arguments parsed, so ``--help`` and usage errors are quick.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from manisplat.cli_args import (add_version, bounded, finite_numbers, non_negative, pinhole_intrinsics,
                                positive)
from manisplat.episode.format import CHROMA_SUBSAMPLING, DIST_LENGTHS, EpisodeFormatError
from manisplat.exit_codes import ExitCode, exit_status_help

ACT_ARMS = ("left", "right", "single")
"""``--arm`` choices of ``import-act`` (the keys of the importer's ``ARM_COLUMNS``)."""
EXPORT_FORMATS = ("lerobot", "act-hdf5")
"""``--format`` choices of ``export``."""
SAMPLE_MIN_FRAMES = 8
"""The fewest frames ``write_sample_episode`` accepts."""
EPILOG = exit_status_help({
    ExitCode.OK: "done",
    ExitCode.FAILED: "validate: an error in any episode; recover: the result is still invalid",
    ExitCode.BAD_INPUT: "bad arguments; a missing, unreadable or damaged input (named); an output that exists\n"
                        "without --overwrite",
    ExitCode.INTERRUPTED: "interrupted (an export leaves nothing half-written)",
})


def _dataset_name(text: str) -> str:
    """An argparse type: an HDF5 dataset name without a group path."""
    if not text or "/" in text or text in (".", ".."):
        raise argparse.ArgumentTypeError(f"expected a plain dataset name without '/'; got {text!r}")
    return text


def _cmd_info(args: argparse.Namespace) -> int:
    from manisplat.episode.reader import Episode
    from manisplat.episode.summary import describe

    print(describe(Episode.open(args.episode)))
    return ExitCode.OK


def _cmd_validate(args: argparse.Namespace) -> int:
    from manisplat.episode.validation import validate

    status = ExitCode.OK
    for path in args.episodes:
        if not path.exists():  # nothing to validate: bad input, as in every other command
            print(f"error: {path} does not exist", file=sys.stderr)
            status = max(status, ExitCode.BAD_INPUT)
            continue
        report = validate(path, decode_images=not args.quick, progress=sys.stderr.isatty())
        print(report)
        status = max(status, ExitCode.OK if report.ok else ExitCode.FAILED)
    return status


def _cmd_recover(args: argparse.Namespace) -> int:
    from manisplat.episode.recovery import recover

    report = recover(args.episode, drop_damaged=args.drop_damaged)
    print(report)
    return ExitCode.OK if report.validation is None or report.validation.ok else ExitCode.FAILED


def _cmd_import_act(args: argparse.Namespace) -> int:
    one_arm = [flag for flag, value in (("--K", args.K), ("--arm", args.arm), ("--camera", args.camera),
                                        ("--dist", args.dist), ("--mount", args.mount),
                                        ("--robot-description", args.robot_description)) if value is not None]
    if args.calib is not None and one_arm:
        print(f"manisplat-episode import-act: error: --calib imports every arm and camera (format version 2); "
              f"{', '.join(one_arm)} {'belongs' if len(one_arm) == 1 else 'belong'} to a one-arm import (without --calib)",
              file=sys.stderr)
        return ExitCode.BAD_INPUT
    if args.calib is not None or not one_arm:  # without --calib, the importer says what is missing and how to give it
        return _import_cobot_magic(args)
    if args.K is None:
        print("manisplat-episode import-act: error: a one-arm import (--arm, --camera) needs --K fx,fy,cx,cy: these "
              "files store no intrinsics (or import every arm and camera with --calib FILE.calib.json)",
              file=sys.stderr)
        return ExitCode.BAD_INPUT
    import numpy as np

    from manisplat.episode.importers.act_hdf5 import import_act_hdf5

    fx, fy, cx, cy = args.K
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    episode = import_act_hdf5(args.file, args.out, K=K, arm=args.arm or "left", camera=args.camera or "cam_high",
                              fps=args.fps or 30.0, gripper_scale=args.gripper_scale, dist=args.dist or [],
                              mount=args.mount or "base", bgr=args.bgr,
                              robot_description=args.robot_description or "builtin:agilex_piper", task=args.task,
                              image_format=args.image_format, overwrite=args.overwrite)
    print(f"imported {len(episode)} frames from {args.file} into {episode.path}")
    return ExitCode.OK


def _import_cobot_magic(args: argparse.Namespace) -> int:
    from manisplat.episode.importers.cobot_magic import import_cobot_magic

    episode = import_cobot_magic(args.file, args.out, args.calib, fps=args.fps, gripper_scale=args.gripper_scale,
                                 bgr=args.bgr, task=args.task, image_format=args.image_format,
                                 overwrite=args.overwrite)
    print(f"imported {len(episode)} frames of the arms {', '.join(episode.arms)} and the cameras "
          f"{', '.join(episode.cameras)} from {args.file} into {episode.path} (format version 2)")
    return ExitCode.OK


_FORMAT_ONLY_OPTIONS = {"lerobot": ("task", "no_depth", "codec", "crf"),
                        "act-hdf5": ("image_key", "compress", "jpeg_quality")}
"""``export`` options that apply to one --format only (dest names)."""
_DEFAULTS_OFF = {"no_depth": False, "compress": False}


def _misplaced_options(args: argparse.Namespace) -> list[str]:
    """--options given that belong to the other --format."""
    given = []
    for fmt, names in _FORMAT_ONLY_OPTIONS.items():
        if fmt == args.format:
            continue
        given += ["--" + n.replace("_", "-") for n in names
                  if getattr(args, n) not in (None, _DEFAULTS_OFF.get(n, None))]
    return given


def _cmd_export(args: argparse.Namespace) -> int:
    from manisplat.episode.exporters.sources import ExportDestinationError

    misplaced = _misplaced_options(args)
    if misplaced:
        print(f"manisplat-episode export: error: {', '.join(misplaced)} do not apply to --format {args.format}",
              file=sys.stderr)
        return ExitCode.BAD_INPUT
    try:
        if args.format == "lerobot":
            return _export_lerobot(args)
        return _export_act(args)
    except (ExportDestinationError, ValueError) as exc:  # usage errors: --out, --camera, --image-key
        print(f"manisplat-episode export: error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT


def _export_lerobot(args: argparse.Namespace) -> int:
    from manisplat.episode.exporters.lerobot import DEFAULT_CRF, export_lerobot

    try:
        result = export_lerobot(args.episodes, args.out, task=args.task, fps=args.fps, camera=args.camera,
                                depth=False if args.no_depth else None, codec=args.codec or "libsvtav1",
                                crf=DEFAULT_CRF if args.crf is None else args.crf,
                                dtype="float64" if args.float64 else "float32", overwrite=args.overwrite,
                                progress=sys.stderr.isatty())
    except KeyboardInterrupt:
        print(f"\ninterrupted: nothing was written to {args.out} (the partial dataset beside it was removed)",
              file=sys.stderr)
        return ExitCode.INTERRUPTED
    print(f"exported {result.episodes} episodes ({result.frames} frames, {result.augmented} augmented; cameras "
          f"{', '.join(result.cameras)}) as a LeRobot v3.0 dataset at {result.path} ({result.data_files} data and "
          f"{result.video_files} video files); "
          f"provenance in {result.path}/meta/augmentation.json")
    return ExitCode.OK


def _export_act(args: argparse.Namespace) -> int:
    from manisplat.episode.exporters.act_hdf5 import DEFAULT_JPEG_QUALITY, export_act_hdf5

    try:
        entries = export_act_hdf5(args.episodes, args.out, camera=args.camera, image_key=_image_keys(args.image_key),
                                  compress=args.compress,
                                  jpeg_quality=DEFAULT_JPEG_QUALITY if args.jpeg_quality is None else args.jpeg_quality,
                                  dtype="float64" if args.float64 else "float32", fps=args.fps,
                                  overwrite=args.overwrite, progress=sys.stderr.isatty())
    except KeyboardInterrupt:
        print(f"\ninterrupted: nothing was written to {args.out} (the hidden folder being written was removed)",
              file=sys.stderr)
        return ExitCode.INTERRUPTED
    augmented = sum(e["augmented"] for e in entries)
    frames = sum(e["frames"] for e in entries)
    print(f"exported {len(entries)} episodes ({frames} frames, {augmented} augmented) to {args.out}/episode_*.hdf5; "
          f"provenance in {args.out}/augmentation.json")
    return ExitCode.OK


def _image_keys(given: list[str] | None) -> str | dict[str, str] | None:
    """``--image-key`` values: one plain KEY, or CAMERA=KEY pairs."""
    if not given or (len(given) == 1 and "=" not in given[0]):
        return given[0] if given else None
    if not all("=" in g for g in given):
        raise ValueError(f"--image-key: give one KEY, or CAMERA=KEY for each camera to rename; got {given}")
    return dict(g.split("=", 1) for g in given)


def _cmd_import_lerobot(args: argparse.Namespace) -> int:
    if args.calib is not None:
        return _import_lerobot_arms(args)
    missing = [o for o, v in (("--camera", args.camera), ("--K", args.K)) if v is None]
    if missing:
        print(f"manisplat-episode import-lerobot: error: a one-arm import needs {' and '.join(missing)} (a LeRobot "
              "dataset stores no intrinsics); or import every arm and camera with --calib FILE.calib.json --units "
              "JOINT,GRIPPER", file=sys.stderr)
        return ExitCode.BAD_INPUT
    import numpy as np

    from manisplat.episode.importers.lerobot import import_lerobot

    fx, fy, cx, cy = args.K
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    episode = import_lerobot(args.dataset, args.out, episode=args.episode, camera=args.camera, K=K,
                             arm=args.arm or "single",
                             units=args.units, gripper_scale=args.gripper_scale, dist=args.dist or [],
                             mount=args.mount or "base",
                             robot_description=args.robot_description or "builtin:agilex_piper",
                             image_format=args.image_format, overwrite=args.overwrite)
    print(f"imported episode {args.episode} ({len(episode)} frames) of {args.dataset} into {episode.path}")
    return ExitCode.OK


def _import_lerobot_arms(args: argparse.Namespace) -> int:
    one_arm = [o for o, v in (("--camera", args.camera), ("--K", args.K), ("--arm", args.arm), ("--dist", args.dist),
                              ("--mount", args.mount), ("--robot-description", args.robot_description))
               if v is not None]
    if one_arm:
        print(f"manisplat-episode import-lerobot: error: --calib imports every arm and camera (format version 2); "
              f"{', '.join(one_arm)} belong to a one-arm import (without --calib)", file=sys.stderr)
        return ExitCode.BAD_INPUT
    from manisplat.episode.importers.lerobot_arms import import_lerobot_arms

    episode = import_lerobot_arms(args.dataset, args.out, args.calib, episode=args.episode, units=args.units,
                                  gripper_scale=args.gripper_scale, image_format=args.image_format,
                                  overwrite=args.overwrite)
    print(f"imported episode {args.episode} ({len(episode)} frames) of {args.dataset}: arms "
          f"{', '.join(episode.arms)}, cameras {', '.join(episode.cameras)} into {episode.path} (format version 2)")
    return ExitCode.OK


def _units(text: str) -> Any:
    """argparse type of ``--units``."""
    from manisplat.episode.importers.units import parse_units

    try:
        return parse_units(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _cmd_sample(args: argparse.Namespace) -> int:
    from manisplat.episode.synthetic import write_sample_episode

    path = write_sample_episode(args.out, frames=args.frames, fps=args.fps, width=args.width, height=args.height,
                                seed=args.seed, task=args.task, overwrite=args.overwrite)
    print(f"wrote the sample episode ({args.frames} frames, {args.width}x{args.height}) to {path}")
    return ExitCode.OK


def _cmd_set_robot(args: argparse.Namespace) -> int:
    from manisplat.episode.relocate import set_robot

    try:
        old, new = set_robot(args.episode, args.description, arm=args.arm, embed=args.embed, overwrite=args.overwrite)
    except ValueError as exc:  # RobotModelError included: an unknown builtin, a URDF that does not load
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    what = "robot.description" if args.arm is None else f"arms.{args.arm}.description"
    print(f"{args.episode}: {what} {old!r} -> {new!r}")
    return ExitCode.OK


def _cmd_set_chroma(args: argparse.Namespace) -> int:
    from manisplat.episode.chroma import set_chroma_subsampling
    from manisplat.episode.images import describe_chroma

    try:
        old, new = set_chroma_subsampling(args.episode, args.scheme, camera=args.camera,
                                          red_blue_swapped=args.red_blue_swapped)
    except ValueError as exc:  # EpisodeFormatError included: no such camera, none named among several
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    where = f"camera {args.camera}: " if args.camera else ""
    print(f"{args.episode}: {where}colour stored {describe_chroma(old)} -> {describe_chroma(new)}")
    return ExitCode.OK


def _cmd_copy(args: argparse.Namespace) -> int:
    from manisplat.episode.relocate import copy_episode

    try:
        old, new = copy_episode(args.source, args.destination, embed=args.embed, overwrite=args.overwrite)
    except ValueError as exc:  # RobotModelError included
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    changed = f"; robot.description {old!r} -> {new!r}" if new != old else ""
    print(f"copied {args.source} to {args.destination}{changed}")
    return ExitCode.OK


def _add_import_options(p: argparse.ArgumentParser, source: str, *, one_arm_only: bool = False) -> None:
    """The options every importer shares: gripper scale, the camera's distortion and mount, the robot.
    With ``one_arm_only`` the last three default to None (a one-arm import fills in the defaults
    the help names), so that the command can tell that they were given."""
    note = " (one-arm import only)" if one_arm_only else ""
    p.add_argument("--gripper-scale", type=positive(float), default=1.0,
                   help=f"factor from the {source}'s gripper value to the finger gap in metres (default: %(default)s)")
    p.add_argument("--dist", type=finite_numbers(DIST_LENGTHS), default=None if one_arm_only else [],
                   metavar="k1,k2,...", help=f"OpenCV distortion coefficients, 0/4/5/8/12/14 of them{note} "
                                             "(default: none)")
    p.add_argument("--mount", default=None if one_arm_only else "base",
                   help=f"'base' or the link a wrist camera is fixed to{note} (default: base)")
    p.add_argument("--robot-description", default=None if one_arm_only else "builtin:agilex_piper",
                   help=f"how to read the joint angles: a URDF path or a builtin: name{note} "
                        "(default: builtin:agilex_piper)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``manisplat-episode`` and its subcommands."""
    parser = argparse.ArgumentParser(
        prog="manisplat-episode",
        description="Inspect, validate, recover, import, export, synthesize and copy ManiSplat episodes\n"
                    "(format versions 1 and 2, docs/episode-format.md).",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more: -v info, -vv debug (default: warnings only)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("info", help="print a summary of an episode",
                       description="Print a summary of an episode: its format version, frames, duration, "
                                   "declared and measured fps, every arm (robot, base, joint ranges in degrees, "
                                   "gripper range in mm), every camera (size, intrinsics, mount, how its images "
                                   "kept their colour, files) and whether it is complete.")
    p.add_argument("episode", type=Path, help="episode folder")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("validate", help="check episodes against the format; exit 1 if any has an error",
                       description="Check every file of each episode and list every problem with its file and "
                                   "row. Exit status: 0 all valid (warnings allowed), 1 an error in any "
                                   "episode, 2 bad arguments or a folder that does not exist.")
    p.add_argument("episodes", type=Path, nargs="+", metavar="EPISODE", help="episode folder(s)")
    p.add_argument("--quick", action="store_true",
                   help="only check that image files exist and are not empty, without decoding them "
                        "(misses truncated or wrong-size images; default: off, every image is decoded)")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("recover", help="make an interrupted episode valid again without losing complete frames",
                       description="Make an episode whose writer was killed valid again. Crash artefacts "
                                   "(temporary files, a torn last row, images without a row, trailing rows with "
                                   "missing or truncated images) and the originals of the rewritten files "
                                   "(frames.csv, joints.csv, gt.npz) are moved into EPISODE/.recovered/<time>/; "
                                   "nothing is deleted. Every per-frame file follows the kept frames. A complete, "
                                   "valid episode is left unchanged. Damage followed by good frames is refused "
                                   "unless --drop-damaged. Exit status 1 when the result is still invalid, e.g. "
                                   "when no frame could be kept.")
    p.add_argument("episode", type=Path, help="episode folder")
    p.add_argument("--drop-damaged", action="store_true",
                   help="also move aside damaged frames in the middle and renumber the remaining ones "
                        "(default: off, such damage is refused)")
    p.set_defaults(func=_cmd_recover)

    p = sub.add_parser("import-act", help="convert an ACT / ALOHA / Cobot Magic HDF5 episode",
                       description="Convert one ACT-style HDF5 episode (observations/qpos, observations/images/"
                                   "<cam>, optional images_depth and action) into an episode folder, frame by "
                                   "frame. With --calib FILE.calib.json: the whole file, every arm of the 14-D "
                                   "Cobot Magic layout (left, right) and every camera, with depth and actions, as "
                                   "a format version 2 episode; the calibration gives per camera K, dist, mount "
                                   "and T_mount_cam, per arm T_world_base and the robot description "
                                   "(docs/cobot-magic.md). With --arm/--camera/--K: one arm and one camera as a "
                                   "version 1 episode. The file holds no calibration: without either, the import "
                                   "is refused, naming what it needs.")
    p.add_argument("file", type=Path, metavar="FILE.hdf5", help="the HDF5 episode")
    p.add_argument("--out", type=Path, required=True, help="episode folder to create (required)")
    p.add_argument("--calib", type=Path, metavar="FILE.calib.json",
                   help="import every arm and camera with this calibration (format version 2; default: none)")
    p.add_argument("--K", type=pinhole_intrinsics(), metavar="fx,fy,cx,cy",
                   help="one-arm import: the camera's intrinsics in pixels (required there: these files store none; "
                        "default: none, which means the whole-file import, which needs --calib)")
    p.add_argument("--arm", choices=ACT_ARMS,
                   help="one-arm import: which arm of a 14-column dual-arm file, or 'single' for 7 columns "
                        "(default: left)")
    p.add_argument("--camera", help="one-arm import: image dataset under observations/images (default: cam_high)")
    p.add_argument("--fps", type=positive(float),
                   help="recording rate in Hz; t = index / fps (default: the calibration's fps with --calib, "
                        "else 30)")
    _add_import_options(p, "file", one_arm_only=True)
    p.add_argument("--bgr", action="store_true",
                   help="the stored images are BGR (default: off, RGB as Cobot Magic stores them)")
    p.add_argument("--task", help="task description stored in episode.json (default: none)")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png",
                   help="rgb file format (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing episode at --out (default: off, refused)")
    p.set_defaults(func=_cmd_import_act)

    p = sub.add_parser("export", help="write episodes as a LeRobot v3.0 dataset or ACT / Cobot Magic HDF5 files",
                       description="Write EPISODES, in the order given, as one dataset a policy learner reads, "
                                   "streaming one frame at a time. Everything is checked before anything is "
                                   "written: every episode complete, the same arms and cameras, one image size "
                                   "per camera, every image present. State and action are 7-D per arm [q1..q6 rad, "
                                   "gripper m], arm after arm in the episode's order (a Cobot Magic import: left, "
                                   "right, 14-D); the action is each arm's a1..a6,a_gripper, or without them the "
                                   "next frame's state. Every camera is exported (or those --camera names). "
                                   "--format lerobot: a LeRobot v3.0 dataset in OUT (meta/info.json, stats.json, "
                                   "tasks.parquet, episodes/, data/*.parquet, videos/observation.images.<camera>/"
                                   "*.mp4 per camera, depth as a uint16 mm column depth.<camera>), written beside OUT and "
                                   "renamed into place when complete; read it with LeRobotDataset(repo_id, "
                                   "root=OUT, video_backend='pyav') and back with import-lerobot. "
                                   "--format act-hdf5: OUT/episode_0.hdf5, ... (ACT / ALOHA / Cobot Magic layout: "
                                   "/observations/qpos and qvel (T, 7 per arm), /observations/images/<camera> per "
                                   "camera, /action (T, 7 per arm), attributes sim, compress, fps), written beside "
                                   "OUT and moved into it when complete; read back with `import-act FILE --arm "
                                   "single --camera NAME` (one arm) or `import-act FILE --calib FILE.calib.json` "
                                   "(two). Both write "
                                   "augmentation.json (LeRobot: meta/augmentation.json) naming each episode's "
                                   "source and, for augmented ones, their parent. Exit status: 0 done, 2 bad "
                                   "arguments or input (a non-empty --out without --overwrite included), "
                                   "130 interrupted.")
    p.add_argument("episodes", type=Path, nargs="+", metavar="EPISODE", help="episode folder(s)")
    p.add_argument("--format", choices=EXPORT_FORMATS, required=True, help="output layout (required)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (required): created; must be new or empty unless --overwrite")
    p.add_argument("--camera", action="append", metavar="NAME",
                   help="a camera to export, which every episode must have; repeat for several (default: every "
                        "camera of the first episode)")
    p.add_argument("--float64", action="store_true",
                   help="store state/qpos, qvel and action as float64, so joints round-trip bit-exact (default: "
                        "off, float32 as LeRobot, ACT and Cobot Magic expect: ACT's training code fails on float64)")
    p.add_argument("--overwrite", action="store_true",
                   help="lerobot: replace an earlier LeRobot dataset at --out once the new one is complete; "
                        "act-hdf5: remove an earlier export's episode_*.hdf5 and augmentation.json first, keeping "
                        "other files (default: off, a non-empty --out is refused)")
    p.add_argument("--fps", type=positive(int), metavar="F",
                   help="export rate in Hz; episodes recorded faster are resampled to the frame nearest each 1/F "
                        "step (default: the episodes' common rate; LeRobot needs a whole number)")
    g = p.add_argument_group("lerobot only")
    g.add_argument("--task", help="task description stored with every frame (default: each episode.json's task; "
                                  "an episode without one is an error)")
    g.add_argument("--no-depth", action="store_true",
                   help="leave depth out (default: depth.<camera> is written when the episodes have depth; an "
                        "episode without it is then an error)")
    g.add_argument("--codec", choices=("libsvtav1", "h264", "hevc"),
                   help="video encoder (default: libsvtav1, AV1 as LeRobot writes it)")
    g.add_argument("--crf", type=bounded(0, 63, kind=int),
                   help="video quality, lower is better and larger (default: 30, as LeRobot)")
    g = p.add_argument_group("act-hdf5 only")
    g.add_argument("--image-key", type=_dataset_name, action="append", metavar="[CAMERA=]KEY",
                   help="dataset name under /observations/images, e.g. cam_high to match an ACT task config: KEY "
                        "when one camera is exported, else CAMERA=KEY, repeated (default: the camera names)")
    g.add_argument("--compress", action="store_true",
                   help="store JPEG bytes padded to the longest frame plus /compress_len, attribute "
                        "compress=True, as ALOHA's recorder does (default: off, raw (T, H, W, 3) uint8 RGB)")
    g.add_argument("--jpeg-quality", type=bounded(0, 100, kind=int),
                   help="JPEG quality with --compress, 0..100; ALOHA's recorder uses 50, smaller but visibly "
                        "lossy (default: 90)")
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser("import-lerobot", help="convert one episode of a LeRobot v3.0 dataset",
                       description="Convert episode I of a LeRobot v3.0 dataset (meta/, data/, videos/) into an "
                                   "episode folder, frame by frame: observation.state -> q1..q6, gripper; action "
                                   "-> a1..a6, a_gripper (when it has the same layout); the camera's video frames "
                                   "matched to rows by timestamp (LeRobot's 1e-4 s tolerance); depth.<camera> "
                                   "(uint16 mm) when present; t = frame_index / fps. Joints are read as stored, so "
                                   "an export comes back bit-exact. The dataset holds no intrinsics: --K is "
                                   "required. With --calib FILE.calib.json --units JOINT,GRIPPER: every arm "
                                   "(the calibration's state columns, default left 0-6, right 7-13 of a 14-D "
                                   "state) and every observation.images.<camera> as a format version 2 episode; "
                                   "the units are required there, because PiPER plugins store degrees/mm, "
                                   "radians/metres or normalised values under the same names "
                                   "(docs/cobot-magic.md). Exit status: 0 done, 2 bad arguments or input.")
    p.add_argument("dataset", type=Path, metavar="DATASET_DIR", help="the LeRobot dataset folder")
    p.add_argument("--episode", type=non_negative(int), required=True, metavar="I",
                   help="episode_index to import (required)")
    p.add_argument("--out", type=Path, required=True, help="episode folder to create (required)")
    p.add_argument("--calib", type=Path, metavar="FILE.calib.json",
                   help="import every arm and every observation.images.<camera> as a format version 2 episode, "
                        "with this Cobot Magic calibration (per camera K, mount, T_mount_cam; per arm "
                        "T_world_base, robot description, state columns; docs/cobot-magic.md); needs --units "
                        "(default: none, a one-arm import)")
    p.add_argument("--units", type=_units, metavar="JOINT,GRIPPER",
                   help="units of the stored joints and gripper: rad,m (ManiSplat's export), deg,mm, deg,m or "
                        "rad,mm; values normalised to +-100 are refused (required with --calib; default without "
                        "it: rad,m)")
    p.add_argument("--camera", metavar="KEY",
                   help="one-arm import: video feature, e.g. observation.images.cam_high, or just its camera name "
                        "(required there; default: none)")
    p.add_argument("--K", type=pinhole_intrinsics(), metavar="fx,fy,cx,cy",
                   help="one-arm import: camera intrinsics in pixels (required there: LeRobot datasets store none; "
                        "default: none)")
    p.add_argument("--arm", choices=ACT_ARMS,
                   help="one-arm import: 'single' for 7-D state, or which arm of a 14-D dual-arm state "
                        "(default: single)")
    _add_import_options(p, "dataset", one_arm_only=True)
    p.add_argument("--image-format", choices=("png", "jpg"), default="png",
                   help="rgb file format (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing episode at --out (default: off, refused)")
    p.set_defaults(func=_cmd_import_lerobot)

    p = sub.add_parser("sample", help="write the built-in synthetic pick-and-place episode",
                       description="Write the built-in sample: the built-in PiPER picks a 4 cm box and places it "
                                   "18 cm away, seen by a fixed camera, with RGB, depth, masks, 200 Hz joints, "
                                   "actions and exact ground truth (gt.npz). Needs no files or devices.")
    p.add_argument("out", type=Path, metavar="OUT", help="episode folder to create")
    p.add_argument("--frames", type=bounded(SAMPLE_MIN_FRAMES, kind=int), default=64,
                   help=f"number of frames, at least {SAMPLE_MIN_FRAMES}; the motion is stretched over them "
                        "(default: %(default)s)")
    p.add_argument("--fps", type=positive(float), default=8.0, help="frame rate in Hz (default: %(default)s)")
    p.add_argument("--width", type=positive(int), default=160, help="image width in pixels (default: %(default)s)")
    p.add_argument("--height", type=positive(int), default=120, help="image height in pixels (default: %(default)s)")
    p.add_argument("--seed", type=non_negative(int), default=0,
                   help="0: the nominal camera; others move it by up to 5 cm (default: %(default)s)")
    p.add_argument("--task", choices=("pick_place", "reach"), default="pick_place",
                   help="pick_place: the box is picked and placed; reach: the arm hovers over it "
                        "(default: %(default)s)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing episode at OUT (default: off, refused)")
    p.set_defaults(func=_cmd_sample)

    p = sub.add_parser("set-robot", help="point robot.description at a URDF or built-in robot, or embed it",
                       description="Rewrite the episode's robot.description (how its joint angles read) after "
                                   "checking that it loads. A URDF path is stored relative to the episode when it "
                                   "lies inside it, absolute otherwise. --embed copies the URDF and the meshes it "
                                   "references (relative and package:// paths) into EPISODE/robot/ and points "
                                   "there, so the episode can be copied anywhere. In a format version 2 episode, "
                                   "--arm names the arm (robot/<arm>/ when embedded).")
    p.add_argument("episode", type=Path, metavar="EPISODE", help="episode folder")
    p.add_argument("description", nargs="?", metavar="DESCRIPTION",
                   help="a URDF path (relative to the current folder) or builtin:agilex_piper "
                        "(default: the episode's current robot.description, e.g. to --embed it)")
    p.add_argument("--arm", metavar="NAME",
                   help="the arm of a format version 2 episode whose description to set (default: the one arm; "
                        "required when the episode has several)")
    p.add_argument("--embed", action="store_true",
                   help="copy the URDF and its meshes into EPISODE/robot/ (robot/<arm>/ in version 2; default: off, "
                        "point at it)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing EPISODE/robot/ when embedding (default: off, refused)")
    p.set_defaults(func=_cmd_set_robot)

    p = sub.add_parser("set-chroma", help="say how a camera's images kept their colour when they were encoded",
                       description="Record in episode.json how a camera's images kept their colour when the camera "
                                   "or recorder encoded them (chroma subsampling: 4:2:0 is JPEG's and most video's "
                                   "usual, one colour sample per 2 x 2 pixels). JPEG files say it in their header; "
                                   "PNG files that were JPEG or video frames first (re-saved, or decoded by a tool "
                                   "that does not record it) do not. manisplat-reconstruct compares its renders "
                                   "with the images after the same subsampling. Refused where the images are JPEG "
                                   "files whose header says otherwise.")
    p.add_argument("episode", type=Path, metavar="EPISODE", help="episode folder")
    p.add_argument("scheme", choices=list(CHROMA_SUBSAMPLING), metavar="SCHEME",
                   help=f"one of {', '.join(CHROMA_SUBSAMPLING)} (4:4:4: every pixel's colour kept)")
    p.add_argument("--camera", metavar="NAME",
                   help="the camera (default: the one camera; required when the episode has several)")
    p.add_argument("--red-blue-swapped", action="store_true",
                   help="the encoder took red for blue (cv2.imencode of an RGB array, as ACT and Cobot Magic "
                        "recorders store frames; default: off)")
    p.set_defaults(func=_cmd_set_chroma)

    p = sub.add_parser("copy", help="copy an episode so that its robot description still resolves",
                       description="Copy every file of an episode (.recovered/ included). A relative "
                                   "robot.description pointing outside SRC is rewritten as an absolute path, or "
                                   "with --embed the URDF and its meshes are copied into DST/robot/. The copy is "
                                   "made beside DST and renamed into place.")
    p.add_argument("source", type=Path, metavar="SRC", help="episode folder to copy")
    p.add_argument("destination", type=Path, metavar="DST", help="episode folder to create")
    p.add_argument("--embed", action="store_true",
                   help="embed the robot description in DST/robot/ (default: off, an absolute path)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing episode at DST (default: off, refused)")
    p.set_defaults(func=_cmd_copy)
    return add_version(parser)


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
    except (EpisodeFormatError, OSError) as exc:  # FileExistsError included: no --overwrite
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
