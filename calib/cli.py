"""``manisplat-calibrate``: boards, intrinsics, capture, hand-eye solve, latency, apply.

The exit codes are in :data:`EPILOG`. Each command imports what it needs (OpenCV, torch, scipy)
when it runs, so ``--help`` and usage errors answer without loading any of them.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from manisplat.calib.errors import CalibrationError, DegenerateMotionError, InputError, NotEnoughDataError
from manisplat.cli_args import add_version, bounded, finite, positive
from manisplat.exit_codes import ExitCode, exit_status_help

if TYPE_CHECKING:
    import numpy as np


DESCRIPTION = ("Calibrate a camera against a PiPER: print a ChArUco board, get the intrinsics, capture still "
               "poses, solve camera-to-base (eye-to-hand) or camera-to-flange (eye-in-hand), or a two-arm rig's "
               "cameras and arm bases (solve-rig), estimate the camera latency, and write the result into "
               "episodes. `manisplat-calibrate COMMAND --help` explains each command.")
EPILOG = exit_status_help({
    ExitCode.OK: "success",
    ExitCode.FAILED: "the calibration failed for another reason (inconsistent data, divergence)",
    ExitCode.BAD_INPUT: "bad arguments or unreadable input (missing file, bad JSON, wrong image size)",
    ExitCode.INSUFFICIENT_DATA: "the data cannot determine the result: too few usable views or detections, or\n"
                                "degenerate motion (the poses do not determine the result, nothing moves)",
})


def _board_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", required=True, type=Path,
                   help="board.json (as `manisplat-calibrate board` writes it; required)")


def _solve_args(p: argparse.ArgumentParser, moving_help: str) -> None:
    """The options ``solve`` and ``solve-rig`` share: corner offset, closed forms, still frames."""
    p.add_argument("--corner-offset", type=finite(), metavar="PX",
                   help="px subtracted from OpenCV's ChArUco corners (default: measured for the installed OpenCV)")
    p.add_argument("--no-opencv", action="store_true",
                   help="start only from our own closed form (default: also try OpenCV's closed forms)")
    p.add_argument("--max-joint-speed", type=positive(), default=0.02, help=f"{moving_help} (default 0.02)")
    p.add_argument("--allow-moving", action="store_true",
                   help="use every frame, moving or not (default: skip moving frames)")


def cmd_board(a: argparse.Namespace) -> int:
    from manisplat.calib.board import BoardSpec, write_printables
    spec = BoardSpec(dictionary=a.dictionary, squares_x=a.squares_x, squares_y=a.squares_y,
                     square_length_m=a.square_mm / 1000.0, marker_length_m=a.marker_mm / 1000.0,
                     legacy_pattern=a.legacy)
    paths = write_printables(spec, a.out, px_per_mm=a.px_per_mm, paper=a.paper)
    for kind, path in paths.items():
        print(f"wrote {path}")
    print("print the PDF at 100 % scale (no 'fit to page'), check the 100 mm bar, measure one square and "
          "put the measured length into square_length_m")
    return ExitCode.OK


def cmd_intrinsics(a: argparse.Namespace) -> int:
    import numpy as np

    from manisplat.calib.intrinsics import intrinsics_from_images, intrinsics_from_oak
    if a.oak or a.oak_json:
        if not (a.width and a.height):
            raise InputError("--width and --height (the recording size) are required with --oak/--oak-json")
        cam = intrinsics_from_oak(a.width, a.height, calib_json=a.oak_json, resize=a.resize, device=a.device)
        out = {"format": "manisplat-intrinsics", **cam.to_dict(), "source": "oak factory calibration"}
        print(f"OAK factory intrinsics at {a.width}x{a.height}: fx {cam.K[0, 0]:.2f} fy {cam.K[1, 1]:.2f} "
              f"cx {cam.K[0, 2]:.2f} cy {cam.K[1, 2]:.2f}, {len(cam.dist)} distortion coefficients")
    else:
        from manisplat.calib.board import load_board
        if a.board is None:
            raise InputError("--board is required to solve intrinsics from images")
        spec = load_board(a.board)
        images = _images(a)
        res = intrinsics_from_images(images, spec, model=a.model, min_coverage=a.min_coverage)
        out = {**res.to_dict(), "source": "board frames"}
        k = res.camera.K
        print(f"{res.views} views: RMS {res.rms_px:.3f} px, coverage {res.coverage:.0%}; fx {k[0, 0]:.2f} "
              f"fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f} (1-sigma {np.round(res.std, 2).tolist()} px)")
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {a.out}")
    return ExitCode.OK


def _images(a: argparse.Namespace) -> list[np.ndarray]:
    import cv2
    if a.episode:
        from manisplat.episode import Episode
        ep = Episode.open(a.episode)
        return [ep.rgb(i) for i in range(0, len(ep), max(1, a.step))]
    if not a.images:
        raise InputError("give --oak, --oak-json, --episode or --images")
    paths = sorted(p for pattern in a.images for p in Path().glob(pattern)) if any("*" in x for x in a.images) \
        else [Path(x) for x in a.images]
    out = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"{p}: cannot read image")
        out.append(img)
    return out


def cmd_capture(a: argparse.Namespace) -> int:
    from manisplat.calib.board import load_board
    from manisplat.calib.capture import capture
    from manisplat.robot import load_robot
    spec = load_board(a.board)
    robot = load_robot(a.description, load_meshes=False)
    if a.replay:
        from manisplat.drivers.replay import EpisodeArm, EpisodeCamera
        arm, camera = EpisodeArm(a.replay), EpisodeCamera(a.replay)
    else:
        from manisplat.drivers.oak import OakCamera, OakConfig
        from manisplat.drivers.piper import PiperArm
        arm = PiperArm.open(a.can, a.interface, read_only=True)
        camera = OakCamera(OakConfig(width=a.width, height=a.height, fps=a.fps))
    try:
        n = capture(arm, camera, robot, spec, a.out, link=a.link if a.mount == "base" else a.mount, mount=a.mount,
                    auto=a.auto, settle_s=a.settle, frames_per_pose=a.frames_per_pose, max_poses=a.max_poses,
                    description=a.description, overwrite=a.overwrite, clock="source" if a.replay else "host")
    finally:
        camera.close()
        arm.close()
    if n < 3:
        print(f"only {n} poses recorded; hand-eye calibration needs at least 3 (15-25 recommended)", file=sys.stderr)
        return ExitCode.INSUFFICIENT_DATA
    print(f"next: manisplat-calibrate solve {a.out} --board {a.board} --out calibration.json --mount {a.mount}")
    return ExitCode.OK


def cmd_solve(a: argparse.Namespace) -> int:
    import numpy as np

    from manisplat.calib.board import load_board
    from manisplat.calib.episode_solve import solve_episode
    from manisplat.calib.result import build_calibration, save_calibration
    spec = load_board(a.board)
    camera = None
    if a.intrinsics:
        from manisplat.calib.intrinsics import load_intrinsics
        camera = load_intrinsics(a.intrinsics)
    solved = solve_episode(a.episode, spec, mount=a.mount, link=a.link, camera=camera,
                           corner_offset=a.corner_offset, use_opencv=not a.no_opencv,
                           max_joint_speed=None if a.allow_moving else a.max_joint_speed)
    latency = None
    if a.latency_from:
        from manisplat.calib.latency import estimate_latency
        latency = estimate_latency(a.latency_from, max_offset_s=a.max_offset)
    cal = build_calibration(solved, spec.to_dict(), None if latency is None else latency.to_dict())
    save_calibration(a.out, cal)
    r = solved.result
    s, u = cal["residuals"], cal["uncertainty"]
    T = r.T_mount_cam
    print(f"{a.episode}: {s['views_used']}/{s['views_total']} views, {r.poses} distinct poses, "
          f"{len(solved.rejected)} frames refused; start {r.start}")
    print(f"reprojection RMS {s['rms_px']:.3f} px (median {s['median_px']:.3f}, max {s['max_px']:.3f}); "
          f"1-sigma {u['T_mount_cam_rot_std_deg']:.4f} deg, {u['T_mount_cam_trans_std_mm']:.3f} mm")
    print(f"T_{r.mount}_cam translation {np.round(T[:3, 3], 5).tolist()} m")
    for note in r.notes:
        print(f"note: {note}")
    print(f"wrote {a.out}")
    if a.report:
        from manisplat.calib.report import write_report
        print(f"wrote {write_report(solved, a.report, cal, latency)}")
    return ExitCode.OK


def cmd_latency(a: argparse.Namespace) -> int:
    from manisplat.calib.latency import estimate_latency
    est = estimate_latency(a.episode, max_offset_s=a.max_offset, use_calibration=not a.uncalibrated,
                           max_span_s=a.max_span)
    print(f"{a.episode}: latency {est.latency_s * 1000:.2f} +- {est.std_s * 1000:.2f} ms (t_frame - t_exposure; "
          f"correlation {est.correlation:.3f} over {est.intervals} frame intervals from t = {est.window_s[0]:.2f} "
          f"to {est.window_s[1]:.2f} s, robot signal in {est.signal})")
    if a.json:
        Path(a.json).write_text(json.dumps(est.to_dict(), indent=1) + "\n", encoding="utf-8")
    return ExitCode.OK


def cmd_solve_rig(a: argparse.Namespace) -> int:
    from manisplat.calib.board import load_board
    from manisplat.calib.rig import solve_rig
    from manisplat.calib.rig_file import build_rig, save_rig
    spec = load_board(a.board)
    solved = solve_rig(a.episode, spec, world=a.world, corner_offset=a.corner_offset, use_opencv=not a.no_opencv,
                       max_joint_speed=None if a.allow_moving else a.max_joint_speed)
    rig = build_rig(solved, spec.to_dict())
    save_rig(a.out, rig)
    print(f"{a.episode}: world = {rig['world_frame']}")
    for name, cam in rig["cameras"].items():
        r = cam["residuals"]
        print(f"  camera {name} on {cam['mount']}: {r['views_used']} views, reprojection RMS {r['rms_px']:.3f} px "
              f"({cam['method']})")
    for arm, entry in rig["arms"].items():
        u = entry["uncertainty"]
        print(f"  arm {arm}: base at {[round(x, 4) for x in (row[3] for row in entry['T_world_base'][:3])]} m "
              f"(through {entry['from_camera']}; 1-sigma {u['other_rot_std_deg']:.4f} deg, "
              f"{u['other_trans_std_mm']:.3f} mm)")
    print(f"wrote {a.out}")
    return ExitCode.OK


def cmd_apply(a: argparse.Namespace) -> int:
    from manisplat.calib.errors import read_json
    from manisplat.calib.result import apply_calibration, load_calibration
    from manisplat.calib.rig_file import apply_rig, check_rig, is_rig
    raw = read_json(Path(a.calibration), "calibration file")
    if is_rig(raw):
        rig = check_rig(a.calibration, raw)
        for ep in a.episodes:
            notes = apply_rig(rig, ep, source=str(Path(a.calibration).resolve()))
            print(f"{ep}: cameras and arm bases calibrated (world: {rig['world_frame']})")
            for note in notes:
                print(f"  note: {note}")
        return ExitCode.OK
    cal = load_calibration(a.calibration)
    for ep in a.episodes:
        apply_calibration(cal, ep, source=str(Path(a.calibration).resolve()))
        print(f"{ep}: camera calibrated (mount {cal['mount']}"
              + (f", latency {cal['latency_s'] * 1000:.1f} ms" if cal.get("latency_s") is not None else "") + ")")
    return ExitCode.OK


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``manisplat-calibrate`` and its commands."""
    p = argparse.ArgumentParser(prog="manisplat-calibrate", description=DESCRIPTION, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-v", "--verbose", action="store_true", help="log progress (default: warnings only)")
    sub = p.add_subparsers(dest="command", required=True)

    def command(name: str, summary: str, **kwargs: str) -> argparse.ArgumentParser:
        """A subcommand whose --help opens with its one-line summary (unless it has a description)."""
        kwargs.setdefault("description", summary[0].upper() + summary[1:] + ".")
        return sub.add_parser(name, help=summary, **kwargs)

    b = command("board", "write a printable ChArUco board (PNG, PDF at true scale) and board.json")
    b.add_argument("--out", default="board", help="output prefix: PREFIX.png, PREFIX.pdf, PREFIX.json (default board)")
    b.add_argument("--squares-x", type=bounded(2, kind=int), default=7,
                   help="squares along x (columns), at least 2 (default 7)")
    b.add_argument("--squares-y", type=bounded(2, kind=int), default=5,
                   help="squares along y (rows), at least 2 (default 5)")
    b.add_argument("--square-mm", type=positive(), default=30.0, help="square side, mm (default 30)")
    b.add_argument("--marker-mm", type=positive(), default=22.0,
                   help="marker side, mm, smaller than --square-mm (default 22)")
    b.add_argument("--dictionary", default="DICT_5X5_100", help="OpenCV ArUco dictionary (default DICT_5X5_100)")
    b.add_argument("--legacy", action="store_true",
                   help="OpenCV < 4.6 marker layout, for boards from calib.io (default: the current layout)")
    b.add_argument("--px-per-mm", type=positive(int), default=10,
                   help="raster resolution of the page (default 10 = 254 dpi)")
    b.add_argument("--paper", default="a4", choices=["a4", "letter", "a3"],
                   help="page size of the PDF, printed at 100 %% (default a4)")
    b.set_defaults(fn=cmd_board)

    i = command("intrinsics", "intrinsics from the OAK factory calibration or from board images")
    i.add_argument("--oak", action="store_true", help="read the connected OAK's factory calibration")
    i.add_argument("--oak-json", type=Path, help="an OAK calibration dump (CalibrationHandler.eepromToJsonFile)")
    i.add_argument("--device", help="OAK device id (default: the first found)")
    i.add_argument("--resize", default="crop", choices=["crop", "stretch"],
                   help="--oak/--oak-json: how the stream was resized from the sensor: crop (keep the aspect "
                        "ratio, depthai's default) or stretch (default crop)")
    i.add_argument("--width", type=positive(int), help="recording width, px (required with --oak/--oak-json)")
    i.add_argument("--height", type=positive(int), help="recording height, px (required with --oak/--oak-json)")
    i.add_argument("--board", type=Path, help="board.json (required to solve from images)")
    i.add_argument("--images", nargs="+", help="image files or glob patterns with the board")
    i.add_argument("--episode", type=Path, help="an episode whose frames show the board")
    i.add_argument("--step", type=positive(int), default=1, help="use every STEP-th episode frame (default 1: all)")
    i.add_argument("--model", default="k1k2k3", choices=["none", "k1k2", "k1k2k3", "rational"],
                   help="distortion coefficients solved for: none, k1k2 (k1 k2 p1 p2), k1k2k3 (k1 k2 p1 p2 k3) "
                        "or rational (OpenCV's 8) (default k1k2k3)")
    i.add_argument("--min-coverage", type=bounded(0.0, 1.0), default=0.6,
                   help="refuse unless this fraction (0..1) of the cells of an 8x6 image grid hold corners "
                        "(default 0.6)")
    i.add_argument("--out", required=True, type=Path, help="intrinsics JSON to write (required)")
    i.set_defaults(fn=cmd_intrinsics)

    c = command("capture", "record (joint state, image) pairs at still poses; says which poses add information")
    c.add_argument("--can", default="can0", help="CAN channel of the PiPER (read only; default can0)")
    c.add_argument("--interface", default="socketcan", help="python-can interface (default socketcan)")
    c.add_argument("--replay", type=Path, help="dry run: read arm and camera from this episode instead of devices")
    _board_args(c)
    c.add_argument("--out", required=True, type=Path, help="episode folder to write (required)")
    c.add_argument("--mount", default="base",
                   help="where the camera is: base (fixed, eye-to-hand; the board is on --link) or the link "
                        "holding it, e.g. link6 (eye-in-hand) (default base)")
    c.add_argument("--link", default="link6", help="link holding the board (eye-to-hand; default link6)")
    c.add_argument("--description", default="builtin:agilex_piper",
                   help="robot description the joints follow (default builtin:agilex_piper)")
    c.add_argument("--auto", action="store_true",
                   help="record still poses that add information without asking (default: on Enter)")
    c.add_argument("--settle", type=positive(), default=1.0, help="seconds the arm must be still (default 1)")
    c.add_argument("--frames-per-pose", type=positive(int), default=3, help="frames kept per still pose (default 3)")
    c.add_argument("--max-poses", type=positive(int), default=25, help="stop after this many poses (default 25)")
    c.add_argument("--width", type=positive(int), default=1280, help="camera width, px (default 1280)")
    c.add_argument("--height", type=positive(int), default=720, help="camera height, px (default 720)")
    c.add_argument("--fps", type=positive(), default=15.0, help="camera frame rate, Hz (default 15)")
    c.add_argument("--overwrite", action="store_true",
                   help="replace an episode already at --out (default: refuse to touch it)")
    c.set_defaults(fn=cmd_capture)

    s = command("solve", "camera-to-base / camera-to-flange from a calibration episode")
    s.add_argument("episode", type=Path, help="the calibration episode (as `capture` writes it)")
    _board_args(s)
    s.add_argument("--out", required=True, type=Path, help="calibration.json to write (required)")
    s.add_argument("--mount", default="base",
                   help="base (eye-to-hand) or the camera's link, e.g. link6 (eye-in-hand) (default base)")
    s.add_argument("--link", default="link6", help="link holding the board for eye-to-hand (default link6)")
    s.add_argument("--intrinsics", type=Path, help="intrinsics JSON (default: the episode's K and dist)")
    _solve_args(s, "skip frames taken while a joint moves faster than this, rad/s, from joints.csv")
    s.add_argument("--latency-from", type=Path,
                   help="also estimate the camera latency from this (moving) episode (default: no latency)")
    s.add_argument("--max-offset", type=positive(), default=0.25,
                   help="--latency-from: latency search range +- s (default 0.25)")
    s.add_argument("--report", type=Path,
                   help="write report.html, report.png and overlays into this folder (default: no report)")
    s.set_defaults(fn=cmd_solve)

    t = command("latency", "camera-vs-joint timestamp offset of a moving episode",
                       description="Estimate latency_s = t_frame - t_exposure (positive: the camera stamps "
                                   "late) by aligning optical flow with the robot's motion from joints.csv. "
                                   "Record 10-30 s of brisk moves with pauses, the arm well in view; with a "
                                   "calibrated camera (after `apply`) the robot signal is in pixels. Prints "
                                   "the estimate with a bootstrap 1-sigma; exit 5 when nothing moves.")
    t.add_argument("episode", type=Path, help="a recorded episode in which the arm moves")
    t.add_argument("--max-offset", type=positive(), default=0.25, help="search range +- s (default 0.25)")
    t.add_argument("--uncalibrated", action="store_true",
                   help="ignore the episode's camera calibration: the robot signal in metres (default: pixels "
                        "when calibrated)")
    t.add_argument("--max-span", type=positive(), default=30.0, metavar="S",
                   help="analyse at most this many seconds: the stretch with the most image motion (default 30)")
    t.add_argument("--json", type=Path, help="also write the estimate here (default: print only)")
    t.set_defaults(fn=cmd_latency)

    r = command("solve-rig", "every camera and arm base of a two-arm rig from one episode with a still board",
                description="Calibrate a version 2 rig (Cobot Magic: arms left and right, a head camera fixed "
                            "in the world, a camera on each link6) from one episode in which a ChArUco board "
                            "lies still on the table and each arm shows it to its wrist camera from still "
                            "poses: eye-in-hand for each wrist camera (its T_link_cam and the board in its "
                            "arm's base), one PnP over all views for each world camera, and every base and "
                            "world camera placed in one world. The episode's K, dist and mounts are used.")
    r.add_argument("episode", type=Path, help="the version 2 calibration episode (mounts declared, K known)")
    _board_args(r)
    r.add_argument("--out", required=True, type=Path, help="rig.json to write (required)")
    r.add_argument("--world", default="bases",
                   help="the world frame: bases (the midpoint of the arm bases, their mean z up and x forward, "
                        "as Cobot Magic's calibration), an arm's name (its base) or a world camera's name "
                        "(default bases)")
    _solve_args(r, "skip a wrist camera's frames taken while its arm moves faster than this, rad/s, from "
                   "joints_<arm>.csv")
    r.set_defaults(fn=cmd_solve_rig)

    ap = command("apply", "write calibration.json or rig.json into episodes (atomically, keeps the rest)")
    ap.add_argument("calibration", type=Path,
                    help="calibration.json (as `solve` writes it; version 1 episodes) or rig.json (as `solve-rig` "
                         "writes it; version 2 episodes)")
    ap.add_argument("episodes", type=Path, nargs="+",
                    help="episode folders whose episode.json gets the camera K, dist, mount, T_mount_cam and "
                         "latency_s (the image size must match); with rig.json every camera's and every arm's "
                         "T_world_base")
    ap.set_defaults(fn=cmd_apply)
    return add_version(p)


def main(argv: list[str] | None = None) -> int:
    """Run ``manisplat-calibrate`` with ``argv``; returns the exit status (:data:`EPILOG`)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "board" and args.marker_mm >= args.square_mm:
        parser.error(f"--marker-mm ({args.marker_mm:g}) must be smaller than --square-mm ({args.square_mm:g})")
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    from manisplat.drivers.base import DriverError
    from manisplat.episode import EpisodeFormatError
    try:
        return args.fn(args)
    except DegenerateMotionError as exc:
        print(f"error: degenerate motion: {exc}", file=sys.stderr)
        return ExitCode.INSUFFICIENT_DATA
    except NotEnoughDataError as exc:
        print(f"error: not enough data: {exc}", file=sys.stderr)
        return ExitCode.INSUFFICIENT_DATA
    except (InputError, EpisodeFormatError, DriverError, FileNotFoundError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except CalibrationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.FAILED


if __name__ == "__main__":
    sys.exit(main())
