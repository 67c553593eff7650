"""``manisplat-record``: record episodes from a PiPER on CAN and an OAK (or replayed) camera, or
from named arms and cameras into one version 2 episode (:mod:`.rigcli`, :mod:`.rig`).

See ``manisplat-record --help``; the pieces are :mod:`.rig` and :mod:`.session` (one episode), :mod:`.clock`,
:mod:`.sync`, :mod:`.writer`, :mod:`.canlog`, :mod:`.actions`, :mod:`.recovery`, and for
``--sim`` / ``--camera replay:`` :mod:`.simrig` and :mod:`.replaycam`. Nothing beyond the
standard library and :mod:`manisplat.cli_args` is imported before the arguments are parsed, so
``--help`` and usage errors answer at once.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, TextIO

from manisplat.cli_args import add_version, bounded, positive
from manisplat.exit_codes import ExitCode, exit_status_help

if TYPE_CHECKING:
    from manisplat.drivers.base import Camera
    from manisplat.drivers.piper import PiperArm
    from manisplat.recorder.clock import Clock
    from manisplat.recorder.replaycam import ReplayEpoch
    from manisplat.recorder.rig import RigRecorder
    from manisplat.recorder.result import EpisodeResult, Status
    from manisplat.recorder.session import Recorder

log = logging.getLogger("manisplat.recorder")

MAX_LATENCY_MS = 1000.0  # RecorderConfig accepts camera latencies within +-1 s

EPILOG = """\
Start and stop:
  Each episode starts when you press Enter or space (--start key, the default on a terminal) or at
  once (--start now), and stops after --duration seconds, on Enter/space, or on Ctrl-C / SIGTERM
  (which also end the session after the current episode has been closed cleanly). Press q to quit.

What is written (one folder per episode, --out/episode_NNNN, format v1 of docs/episode-format.md):
  episode.json   complete:false while recording; the clock mapping, sync settings, task, stats
  frames.csv     index,t,q1..q6,gripper,seq,sync_gap,sync_flags[,a1..a6,a_gripper]
                 sync_flags: 1 interpolated across a gap > --max-gap-ms, 2 no joint sample after
                 the frame (last state held, never extrapolated), 4 before the first sample,
                 8 no fresh leader command (action = measured state)
  joints.csv     every joint sample (200 Hz on a PiPER) on the same clock
  rgb/ depth/    images; depth/ (uint16 millimetres, depth_scale 0.001) with --depth on an OAK, and
                 from a replayed recording that has depth unless --no-depth
  can.asc        every CAN frame as received (python-can ASC; time 0 = the episode's t 0)
  An episode that ends before its first frame is written is removed (it holds no frame), and so
  is an --out folder this run created and left empty.

Named arms and cameras (--arm NAME=CHANNEL, --camera NAME=SPEC; format v2, docs/record.md):
  one episode with every arm and camera; the first camera's frames are the episode's frames, each
  other camera gives its image nearest in time (within --max-skew-ms; its time in <camera>.t)
  frames.csv     index,t,<arm>.q1..<arm>.gripper per arm,<camera>.t,<camera>.seq,<arm>.sync_gap,
                 <arm>.sync_flags[,<arm>.a1..<arm>.a_gripper]
  joints_<arm>.csv, can_<arm>.asc, rgb/<camera>/, depth/<camera>/; every camera needs a mount
  (--mount or --calib); episode.json stats count drops per camera and per arm

""" + exit_status_help({
    ExitCode.OK: "every episode was recorded completely and validates",
    ExitCode.FAILED: "an episode ended with an error (disk full, write error, camera failure, no frame\n"
                     "recorded), or --recover (or the recovery at start) could not make an episode valid;\n"
                     "every frame written is kept: after a storage error the episode is left incomplete and\n"
                     "the message says what to do (free space, run --recover)",
    ExitCode.BAD_INPUT: "bad arguments: a replay:PATH that is not a recording (or lacks the depth or size\n"
                        "asked for), a --recover folder that does not exist",
    ExitCode.DEVICE: "the arm or the camera could not be opened, or the arm sends no feedback",
})


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)[xX](\d+)", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x400; got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _camera(text: str) -> str:
    """``SPEC`` or ``NAME=SPEC``, SPEC one of ``oak``, ``oak:<device id>``, ``replay:PATH`` (existing)."""
    spec = text.partition("=")[2] if "=" in text else text
    if spec != "oak" and not spec.startswith(("oak:", "replay:")) or spec in ("oak:", "replay:"):
        raise argparse.ArgumentTypeError(f"expected 'oak', 'oak:<device id>' or 'replay:PATH' (optionally NAME= "
                                         f"before it); got {text!r}")
    if spec.startswith("replay:") and not Path(spec[len("replay:"):]).exists():
        raise argparse.ArgumentTypeError(f"{spec[len('replay:'):]} does not exist")
    return text


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``manisplat-record``."""
    p = argparse.ArgumentParser(
        prog="manisplat-record", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Record episodes (camera frames with the PiPER's joint state at each frame, the raw joint "
                    "stream, the raw CAN stream) from a PiPER on CAN and an OAK camera, or from several named arms and cameras (a Cobot "
                    "Magic: --arm, --camera NAME=...) into one episode, without ROS.")
    arm = p.add_argument_group("arm")
    arm.add_argument("--can", default=None, metavar="CHANNEL",
                     help="CAN channel of the arm: can0 (socketcan), /dev/ttyACM0 (slcan), ... (default can0)")
    arm.add_argument("--arm", action="append", default=None, metavar="NAME=CHANNEL",
                     help="record several named arms into one version 2 episode (repeat: --arm left=can_left --arm "
                          "right=can_right); every --camera is then named too. With --sim: --arm NAME (each arm "
                          "simulated on its own virtual bus). Default: the one arm on --can (version 1)")
    arm.add_argument("--interface", default="socketcan", metavar="NAME",
                     help="python-can interface: socketcan, slcan, gs_usb, pcan, kvaser, virtual, ... "
                          "(default socketcan; the bus runs at 1 Mbit/s, the PiPER's rate)")
    arm.add_argument("--sim", action="store_true",
                     help="use a simulated PiPER on a private virtual bus instead of a real arm (no hardware; "
                          "default: the arm on --can)")
    arm.add_argument("--sim-motion", choices=("wave", "teleop", "still"), default="wave",
                     help="--sim: the arm waves (default wave), follows a simulated leader arm that sends "
                          "0x155-0x157 (teleop: actions are recorded), or stands still (still)")
    cam = p.add_argument_group("camera")
    cam.add_argument("--camera", type=_camera, action="append", default=None, metavar="[NAME=]SPEC",
                     help="oak: the first OAK found (depthai); oak:ID: the OAK with that device id or IP; "
                          "replay:PATH: replay an episode folder or a depthai recording (.mkv/.avi/.mp4 with its "
                          ".mcap and calibration.json or K.json) live (default oak). With --arm, repeat it with "
                          "names: --camera cam_high=oak:ID --camera cam_left_wrist=oak:ID2 ...; the first camera's "
                          "frames are the episode's frames; a replayed episode with several cameras replays the "
                          "camera of the same name")
    cam.add_argument("--mount", action="append", default=None, metavar="CAMERA=MOUNT",
                     help="with --arm: where a camera is fixed: world, or ARM/LINK for a wrist camera "
                          "(cam_left_wrist=left/link6); every camera needs one, here or from --calib")
    cam.add_argument("--calib", type=Path, default=None, metavar="FILE.calib.json",
                     help="with --arm: a Cobot Magic calibration file (docs/cobot-magic.md): per camera K, dist, "
                          "mount, T_mount_cam, latency_s; per arm T_world_base and its robot description "
                          "(default: none; mounts from --mount, K from the cameras)")
    cam.add_argument("--max-skew-ms", type=positive(float), default=None, metavar="MS",
                     help="with several cameras: the most another camera's image may be from the first camera's "
                          "frame time; a frame without one is not written (counted) (default: half a frame period)")
    cam.add_argument("--loop", action="store_true",
                     help="replay camera: repeat the recording without end (default: stop the episode at its end)")
    cam.add_argument("--fps", type=positive(float), default=None,
                     help="camera rate in Hz (oak: its rate, default 30; replay: keep at most this many frames "
                          "per second, default all)")
    cam.add_argument("--size", type=_size, default=None, metavar="WxH",
                     help="image size (oak: output size, default 640x400; replay: must match the recording, "
                          "default its size)")
    depth = cam.add_mutually_exclusive_group()
    depth.add_argument("--depth", action="store_const", const=True, default=None,
                       help="record depth aligned to the colour image (oak: turns stereo depth on; replay: the "
                            "recording must have depth). Default: an OAK records no depth, a replay records its "
                            "depth when it has any")
    depth.add_argument("--no-depth", dest="depth", action="store_const", const=False,
                       help="record no depth, dropping a replayed recording's depth (the default for an OAK)")
    cam.add_argument("--latency-ms", type=bounded(-MAX_LATENCY_MS, MAX_LATENCY_MS), default=0.0, metavar="MS",
                     help=f"camera latency from calibration, ms, within +-{MAX_LATENCY_MS:g}: a frame's true time "
                          "is its stamp minus this (default 0; depthai stamps are already mid-exposure times; with "
                          "--calib a camera's latency_s there wins)")
    out = p.add_argument_group("episodes")
    out.add_argument("--out", type=Path, default=Path("episodes"), metavar="DIR",
                     help="folder for the episodes (episode_0000, episode_0001, ...; default ./episodes). "
                          "Incomplete episodes found there are recovered first")
    out.add_argument("--episodes", type=positive(int), default=1, metavar="N", help="episodes to record (default 1)")
    out.add_argument("--duration", type=positive(float), default=None, metavar="S",
                     help="stop each episode after S seconds (default: stop by key or Ctrl-C)")
    out.add_argument("--start", choices=("key", "now"), default=None,
                     help="start each episode on Enter/space (key) or at once (now); default key on a terminal, "
                          "now otherwise")
    out.add_argument("--image-format", choices=("png", "jpg"), default="png",
                     help="rgb image format: png (lossless, default png) or jpg (smaller, lossy)")
    out.add_argument("--task", default=None, metavar="TEXT",
                     help="task description stored in episode.json (default: none)")
    out.add_argument("--actions", choices=("auto", "on", "off"), default="auto",
                     help="record leader-arm commands (0x155-0x157, 0x159) as a1..a6,a_gripper: on, off, or auto "
                          "= when seen on the bus before the episode starts (default auto)")
    out.add_argument("--max-gap-ms", type=positive(float), default=15.0, metavar="MS",
                     help="flag frames interpolated across a longer gap between joint samples (default 15 ms: "
                          "three PiPER samples)")
    out.add_argument("--recover", type=Path, default=None, metavar="DIR",
                     help="only recover the incomplete episode DIR (or every incomplete episode in DIR) and exit "
                          "(default: record)")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more log output: -v info, -vv debug (default: warnings and the recorder's progress)")
    return add_version(p)


# -- devices ------------------------------------------------------------------------------------

class Devices:
    """The arm, the camera and (with --sim) the simulator, closed together; ``depth``: whether
    the camera's depth is recorded (--depth / --no-depth, else what the camera gives)."""

    def __init__(self) -> None:
        self.arm: PiperArm | None = None
        self.camera: Camera | None = None
        self.rig: Any = None
        self.info: dict[str, Any] = {}
        self.nominal_fps: float | None = None
        self.depth = False

    def close(self) -> None:
        for name, thing in (("camera", self.camera), ("arm", self.arm), ("simulator", self.rig)):
            if thing is None:
                continue
            try:
                thing.close() if name != "simulator" else thing.stop()
            except Exception as exc:  # closing must not hide the real outcome
                log.warning("closing the %s failed: %s", name, exc)


def open_devices(args: argparse.Namespace, clock: Clock, stop: threading.Event) -> Devices:
    """Open the arm (or simulator) and the camera the arguments name; DriverError when one fails
    (ReplayInputError when a replayed recording does not fit the arguments)."""
    from manisplat.drivers.piper import PiperArm

    dev = Devices()
    try:
        if args.sim:
            from manisplat.recorder.simrig import SimRig

            dev.rig = SimRig(clock, motion=args.sim_motion, keep_states=False).start()
            dev.arm = PiperArm(dev.rig.open_bus(), read_only=True, own_bus=True)
            dev.info["arm"] = f"simulated PiPER ({args.sim_motion}) on a virtual bus"
        else:
            can = args.can or "can0"
            dev.arm = PiperArm.open(can, args.interface, read_only=True)
            dev.info["arm"] = f"PiPER on {args.interface} {can}"
        spec = args.camera[0] if args.camera else "oak"
        dev.camera, dev.depth, dev.nominal_fps, dev.info["camera"] = open_camera(args, spec, clock, stop)
    except BaseException:
        dev.close()
        raise
    return dev


def open_camera(args: argparse.Namespace, spec: str, clock: Clock, stop: threading.Event, name: str | None = None,
                epoch: ReplayEpoch | None = None) -> tuple[Camera, bool, float | None, str]:
    """Open the camera ``spec`` names (``oak``, ``oak:<id>``, ``replay:PATH``; a replayed episode
    with several cameras replays the one called ``name``, starting with the rig's other replays
    that share ``epoch``) with the options' size, rate, depth and loop; returns it, whether its
    depth is recorded, its nominal rate and a description. An OAK streams depth only with --depth;
    a replay's depth is recorded when it has any, unless --no-depth. A replay that is not a
    recording, or lacks the depth or size asked for, is a ReplayInputError."""
    if spec == "oak" or spec.startswith("oak:"):
        from manisplat.drivers.oak import OakCamera, OakConfig

        width, height = args.size or (640, 400)
        fps = args.fps or 30.0
        depth = bool(args.depth)
        device = spec[len("oak:"):] or None
        camera = OakCamera(OakConfig(width=width, height=height, fps=fps, depth=depth, device=device))
        return camera, depth, fps, (f"OAK{f' {device}' if device else ''} {width}x{height} @ {fps:g} fps"
                                    f"{' + depth' if depth else ''}")
    from manisplat.recorder.replaycam import ReplayCamera, ReplayInputError, open_replay_source

    path = Path(spec[len("replay:"):])
    camera = ReplayCamera(open_replay_source(path, name), clock, loop=args.loop, fps=args.fps, stop=stop, epoch=epoch,
                          timeline=path.resolve())
    if args.size is not None and args.size != (camera.width, camera.height):
        camera.close()
        raise ReplayInputError(f"--size {args.size[0]}x{args.size[1]} does not match the replayed recording "
                          f"({camera.width}x{camera.height}); leave --size out or pick that size")
    if args.depth and not camera.has_depth:
        camera.close()
        raise ReplayInputError(f"--depth: the replayed recording {path} has no depth; leave --depth out")
    depth = camera.has_depth if args.depth is None else args.depth
    dropped = " (its depth dropped: --no-depth)" if camera.has_depth and not depth else ""
    return camera, depth, args.fps or _source_fps(path), (f"replay of {path}{' (looped)' if args.loop else ''}"
                                                          f"{' + depth' if depth else ''}{dropped}")


def _source_fps(path: Path) -> float | None:
    if (path / "episode.json").is_file():
        from manisplat.episode import Episode

        return Episode.open(path).meta.fps
    return None


# -- keys and status ----------------------------------------------------------------------------

class Keys:
    """Start/stop by key: Enter or space toggles, q quits (single keys on a terminal, lines otherwise)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.toggle = threading.Event()
        self.quit = threading.Event()
        self._thread = threading.Thread(target=self._run, name="keys", daemon=True)

    def start(self) -> Keys:
        self._thread.start()
        return self

    def _run(self) -> None:
        with _cbreak(self.stream):
            while not self.quit.is_set():
                ch = self.stream.read(1)
                if ch == "":
                    return  # end of input: keys can no longer stop anything
                if ch in ("q", "Q"):
                    self.quit.set()
                    self.toggle.set()
                elif ch in ("\n", "\r", " "):
                    self.toggle.set()


@contextlib.contextmanager
def _cbreak(stream: TextIO) -> Iterator[None]:
    """Single-key input on a terminal (restored afterwards); nothing otherwise."""
    try:
        import termios
        import tty

        fd = stream.fileno()
        if not os.isatty(fd):
            raise OSError
        saved = termios.tcgetattr(fd)
    except (ImportError, OSError, ValueError, AttributeError):
        yield
        return
    try:
        tty.setcbreak(fd)
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


class StatusLine:
    """The live status line on stderr (rewritten in place on a terminal, a log line every 5 s otherwise)."""

    def __init__(self, stream: TextIO, label: str) -> None:
        self.stream = stream
        self.label = label
        self.tty = stream.isatty()
        self._last_log = -1e9
        self.width = 0

    def __call__(self, s: Status) -> None:
        text = (f"{self.label} {s.elapsed_s:6.1f} s | {s.fps:4.1f} fps | CAN {s.can_fps:5.0f}/s | frames {s.frames} | "
                f"lost {s.lost} | sync gap {s.sync_gap_ms:4.1f} ms | flagged {s.flagged} | queue {s.queue} | "
                f"arm {s.arm}" + (f" | CAMERA SILENT {s.camera_silent_s:.1f} s" if s.camera_silent_s > 0.5 else ""))
        if self.tty:
            self.stream.write("\r" + text.ljust(self.width))
            self.stream.flush()
            self.width = len(text)
        elif s.elapsed_s - self._last_log >= 5.0:
            self._last_log = s.elapsed_s
            log.info("%s", text)

    def end(self) -> None:
        if self.tty and self.width:
            self.stream.write("\n")
            self.stream.flush()


def next_episode_path(out: Path) -> Path:
    """``out/episode_NNNN`` after the highest number there."""
    numbers = [int(m.group(1)) for p in out.glob("episode_*") if (m := re.fullmatch(r"episode_(\d+)", p.name))]
    return out / f"episode_{max(numbers, default=-1) + 1:04d}"


def summary(results: list[EpisodeResult]) -> str:
    """The table printed at the end."""
    rows = [("episode", "frames", "s", "fps", "lost", "flagged", "max gap ms", "joints", "CAN frames", "result")]
    for r in results:
        s = r.stats
        fps = s.frames / s.duration_s if s.duration_s > 0 else 0.0
        outcome = ("removed: no frame (see above)" if r.removed else "valid" if r.valid and not r.error
                   else "ERROR (see above)" if r.error else "invalid")
        rows.append((r.path.name, str(s.frames), f"{s.duration_s:.1f}", f"{fps:.1f}", str(s.frames_lost),
                     str(s.flagged), f"{s.max_sync_gap_s * 1e3:.1f}", str(s.joint_samples),
                     str(s.can_frames_logged), outcome))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows)


# -- main ---------------------------------------------------------------------------------------

def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("manisplat.recorder").setLevel(min(level, logging.INFO))


def _recover(folder: Path) -> int:
    from manisplat.recorder.recovery import recover_all

    results = recover_all(folder)
    if not results:
        print(f"{folder}: no incomplete episode")
    for r in results:
        print(r)
    return ExitCode.FAILED if any(r.error for r in results) else ExitCode.OK


def _make_folder(path: Path) -> list[Path]:
    """Create ``path`` with its missing parents; returns the folders created, outermost first."""
    missing = [folder for folder in (path, *path.parents) if not folder.exists()][::-1]
    path.mkdir(parents=True, exist_ok=True)
    return missing


def _remove_if_empty(created: list[Path]) -> None:
    """Remove the folders of ``created`` (outermost first) that were left empty, innermost first."""
    for folder in reversed(created):
        try:
            folder.rmdir()  # refuses a folder that holds anything
        except OSError:
            return


def main(argv: list[str] | None = None) -> int:
    """Run ``manisplat-record`` with ``argv``; returns the exit status (``--help`` lists them)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    args.arm, args.camera, args.mount = args.arm or [], args.camera or [], args.mount or []
    args.rig = bool(args.arm) or any("=" in c for c in args.camera)
    if args.rig and args.recover is None:
        _check_rig(parser, args)
    elif args.recover is None:
        for flag, given in (("--mount", args.mount), ("--calib", args.calib), ("--max-skew-ms", args.max_skew_ms)):
            if given:
                parser.error(f"{flag} is for several named arms and cameras (--arm NAME=CHANNEL)")
        if len(args.camera) > 1:
            parser.error("several cameras record into one episode with named arms and cameras: --arm NAME=CHANNEL "
                         "... --camera NAME=SPEC ...")
    if args.recover is not None:
        if not args.recover.exists():
            parser.error(f"--recover: {args.recover} does not exist")
        return _recover(args.recover)
    try:
        created = _make_folder(args.out)
    except OSError as exc:
        parser.error(f"--out {args.out}: cannot create the folder: {exc}")
    try:
        return _session(args)
    finally:
        _remove_if_empty(created)


def _check_rig(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse rig options that do not fit together (usage error, exit 2), before any device opens."""
    from manisplat.episode.format import EpisodeFormatError
    from manisplat.recorder.rigcli import RigUsageError, check_rig

    try:
        check_rig(args)
    except (RigUsageError, EpisodeFormatError) as exc:
        parser.error(str(exc))


def _open(args: argparse.Namespace, clock: Clock, camera_stop: threading.Event) -> tuple[Any, Any]:
    """The devices and the recorder the options name (one arm and camera, or a rig of named ones),
    waited for the arms' first joint samples (DriverError otherwise, the devices closed)."""
    from manisplat.drivers.base import DriverError
    from manisplat.recorder.config import RecorderConfig
    from manisplat.recorder.session import Recorder

    if args.rig:
        from manisplat.recorder.rigcli import make_recorder, open_rig

        devices = open_rig(args, clock, camera_stop)
    else:
        devices = open_devices(args, clock, camera_stop)
    try:
        if args.rig:
            recorder = make_recorder(args, devices, clock)
            recorder.wait_for_arms()
        else:
            config = RecorderConfig(fps=args.fps, latency_s=args.latency_ms / 1e3, max_gap_s=args.max_gap_ms / 1e3,
                                    image_format=args.image_format, depth=devices.depth, task=args.task,
                                    actions=args.actions)
            recorder = Recorder(devices.arm, devices.camera, clock, config, source_info=devices.info,
                                nominal_fps=devices.nominal_fps)
            recorder.wait_for_arm()
    except DriverError:
        devices.close()
        raise
    return devices, recorder


def _session(args: argparse.Namespace) -> int:
    """Recover what a crash left in --out, open the devices, record the episodes, print the summary."""
    from manisplat.drivers.base import DriverError
    from manisplat.recorder.clock import SystemClock
    from manisplat.recorder.recovery import recover_all
    from manisplat.recorder.replaycam import ReplayInputError

    if any(r.error for r in recover_all(args.out)):
        print(f"an incomplete episode in {args.out} could not be recovered (see above); fix it or move it away",
              file=sys.stderr)
        return ExitCode.FAILED
    start = args.start or ("key" if sys.stdin.isatty() else "now")
    stop = threading.Event()      # ends the session
    episode_stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        if stop.is_set():
            log.warning("already stopping (closing the episode cleanly)")
        stop.set()
        episode_stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    clock = SystemClock()
    camera_stop = threading.Event()
    try:
        try:
            devices, recorder = _open(args, clock, camera_stop)
        except ReplayInputError as exc:
            print(f"manisplat-record: {exc}", file=sys.stderr)
            return ExitCode.BAD_INPUT
        except (DriverError, OSError) as exc:
            print(f"manisplat-record: {exc}", file=sys.stderr)
            return ExitCode.DEVICE
        try:
            results = _record(args, recorder, start, stop, episode_stop)
        finally:
            camera_stop.set()
            devices.close()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    print(summary(results))
    if args.rig and results:
        from manisplat.recorder.rigcli import rig_summary

        print(rig_summary(results))
    return ExitCode.OK if results and all(r.valid and not r.error for r in results) else \
        (ExitCode.OK if not results else ExitCode.FAILED)


def _record(args: argparse.Namespace, recorder: Recorder | RigRecorder, start: str, stop: threading.Event,
            episode_stop: threading.Event) -> list[EpisodeResult]:
    keys = Keys(sys.stdin).start() if start == "key" or args.duration is None else None
    results: list[EpisodeResult] = []
    for k in range(args.episodes):
        if stop.is_set() or (keys is not None and keys.quit.is_set()):
            break
        path = next_episode_path(args.out)
        if start == "key":
            print(f"episode {k + 1}/{args.episodes} -> {path}: press Enter or space to start (q quits)",
                  file=sys.stderr)
            while not keys.toggle.wait(0.1):
                if stop.is_set():
                    return results
            keys.toggle.clear()
            if keys.quit.is_set():
                break
        episode_stop.clear()
        if stop.is_set():
            break
        watcher = _KeyStop(keys, episode_stop) if keys is not None else None
        status = StatusLine(sys.stderr, f"[{path.name}]")
        try:
            result = recorder.record_episode(path, duration=args.duration, stop=episode_stop, on_status=status)
        finally:
            status.end()
            if watcher is not None:
                watcher.close()
        results.append(result)
        print(f"{path}: {result.stats.frames} frames, {result.stats.duration_s:.1f} s"
              + (f"; ERROR: {result.error}" if result.error else "; valid" if result.valid else ""), file=sys.stderr)
        if result.error or result.stats.stop_reason in ("camera ended", "camera error"):
            break
    return results


class _KeyStop:
    """Sets ``episode_stop`` when a key toggles (Enter/space) or quits during an episode."""

    def __init__(self, keys: Keys, episode_stop: threading.Event) -> None:
        self._done = threading.Event()
        keys.toggle.clear()

        def watch() -> None:
            while not self._done.is_set():
                if keys.toggle.wait(0.1):
                    keys.toggle.clear()
                    episode_stop.set()
                    return

        self._thread = threading.Thread(target=watch, name="key-stop", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._done.set()
        self._thread.join(1.0)


if __name__ == "__main__":
    sys.exit(main())
