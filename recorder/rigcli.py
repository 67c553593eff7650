"""``manisplat-record`` with named arms and cameras (``--arm NAME=CHANNEL``, ``--camera NAME=SPEC``):
the options checked, the devices opened, a :class:`~.rig.RigRecorder` made, and the per-camera
and per-arm lines of the summary.

Each camera needs a mount (``world`` or ``<arm>/<link>``): from ``--mount NAME=MOUNT`` or from a
Cobot Magic calibration file (``--calib``, the format of ``docs/cobot-magic.md``, read by
:func:`manisplat.episode.importers.cobot_magic.load_calibration`), which also gives the cameras'
K, distortion, ``T_mount_cam`` and latency and the arms' ``T_world_base`` and robot descriptions.
"""

from __future__ import annotations

import argparse
import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from manisplat.episode.infos import ArmInfo, CameraInfo, mount_problem, name_problems
from manisplat.recorder.clock import Clock
from manisplat.recorder.config import RecorderConfig
from manisplat.recorder.layout import opencv_dist
from manisplat.recorder.replaycam import ReplayEpoch, ReplayInputError
from manisplat.recorder.result import EpisodeResult
from manisplat.recorder.rig import RigArm, RigCamera, RigRecorder

log = logging.getLogger("manisplat.recorder")


class RigUsageError(ValueError):
    """Options that do not describe a rig (exit 2, said with the option named)."""


@dataclass
class RigDevices:
    """The arms, cameras and simulators of a rig, closed together."""

    arms: list[RigArm] = field(default_factory=list)
    cameras: list[RigCamera] = field(default_factory=list)
    rigs: list[Any] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    nominal_fps: float | None = None

    def close(self) -> None:
        things = ([(f"camera {c.name}", c.camera.close) for c in self.cameras]
                  + [(f"arm {a.name}", a.arm.close) for a in self.arms]
                  + [("a simulator", rig.stop) for rig in self.rigs])
        for name, close in things:
            try:
                close()
            except Exception as exc:  # closing must not hide the real outcome
                log.warning("closing %s failed: %s", name, exc)


def _pairs(option: str, values: list[str]) -> dict[str, str]:
    """``NAME=VALUE`` items of a repeated option, names distinct."""
    out: dict[str, str] = {}
    for text in values:
        name, sep, value = text.partition("=")
        if not sep or not name or not value:
            raise RigUsageError(f"{option} {text!r}: expected NAME=VALUE")
        if name in out:
            raise RigUsageError(f"{option}: {name!r} given twice")
        out[name] = value
    return out


def _arm_channels(args: argparse.Namespace) -> dict[str, str | None]:
    """Arm name -> CAN channel (None with --sim)."""
    channels: dict[str, str | None] = {}
    for text in args.arm:
        name, sep, channel = text.partition("=")
        if not name or name in channels:
            raise RigUsageError(f"--arm {text!r}: expected NAME=CHANNEL with a name not given before")
        if args.sim and sep:
            raise RigUsageError(f"--arm {text!r}: --sim simulates every arm on its own private virtual bus; "
                                f"give --arm {name} without a channel")
        if not args.sim and not channel:
            raise RigUsageError(f"--arm {text!r}: give the arm's CAN channel, e.g. --arm {name}=can_{name} "
                                "(or --sim for simulated arms)")
        channels[name] = channel or None
    return channels


def _camera_specs(args: argparse.Namespace) -> dict[str, str]:
    """Camera name -> ``oak``, ``oak:<device id>`` or ``replay:PATH``, every camera named."""
    unnamed = [c for c in args.camera if "=" not in c]
    if unnamed:
        raise RigUsageError(f"--camera {unnamed[0]!r}: with --arm NAME=... every camera needs a name: "
                            "--camera NAME=oak:<device id> or --camera NAME=replay:PATH")
    specs = _pairs("--camera", args.camera)
    plain = [name for name, spec in specs.items() if spec == "oak"]
    if len(plain) > 1:
        raise RigUsageError(f"--camera: {', '.join(plain)} all say 'oak' (the first OAK found); name each "
                            "OAK's device id: --camera NAME=oak:<id>")
    return specs


@dataclass
class _Placement:
    """What ``episode.json`` says of a camera beyond the device: mount, T_mount_cam, K, dist, latency."""

    mount: str
    T_mount_cam: Any = None
    K: Any = None
    dist: Any = None
    size: tuple[int, int] | None = None
    latency_s: float | None = None


def _placements(args: argparse.Namespace, cameras: list[str], arms: list[str]
                ) -> tuple[dict[str, _Placement], dict[str, ArmInfo]]:
    """Every camera's placement and every arm's info, from --calib and --mount."""
    mounts = _pairs("--mount", args.mount)
    unknown = [name for name in mounts if name not in cameras]
    if unknown:
        raise RigUsageError(f"--mount {unknown[0]}=...: no --camera {unknown[0]} (cameras: {', '.join(cameras)})")
    places: dict[str, _Placement] = {}
    arm_infos = {name: ArmInfo(name=name) for name in arms}
    if args.calib is not None:
        from manisplat.episode.importers.cobot_magic import load_calibration

        calib = load_calibration(args.calib)  # EpisodeFormatError names the file and every problem
        for name, entry in calib.cameras.items():
            if name not in cameras:
                log.warning("%s: camera %s is not recorded (no --camera %s=...); its entry is ignored",
                            args.calib, name, name)
                continue
            if name in mounts:
                raise RigUsageError(f"--mount {name}=...: camera {name} is placed by {args.calib} already; "
                                    "give its mount in one place")
            places[name] = _Placement(entry["mount"], entry["T_mount_cam"], entry["K"], entry.get("dist", []),
                                      calib.sizes.get(name), entry.get("latency_s"))
        for name, info in calib.arms.items():
            if name not in arms:
                log.warning("%s: arm %s is not recorded (no --arm %s=...); its entry is ignored", args.calib, name, name)
                continue
            arm_infos[name] = info
    places.update((name, _Placement(mount)) for name, mount in mounts.items())
    missing = [name for name in cameras if name not in places]
    if missing:
        raise RigUsageError(f"camera {', '.join(missing)} has no mount: give --mount NAME=world for a fixed camera "
                            f"or --mount NAME=<arm>/link6 for a wrist camera (arms: {', '.join(arms)}), or a "
                            "calibration file with --calib (docs/cobot-magic.md)")
    return places, arm_infos


def check_rig(args: argparse.Namespace) -> None:
    """Check the rig options before any device is opened (RigUsageError naming the problem)."""
    if args.can is not None:
        raise RigUsageError("--can names the one arm of a version 1 recording; with --arm give each arm's "
                            "channel: --arm NAME=CHANNEL")
    arms = list(_arm_channels(args))
    cameras = list(_camera_specs(args))
    clash = sorted(set(arms) & set(cameras))
    if clash:
        raise RigUsageError(f"{clash[0]!r} names an arm and a camera; give them distinct names")
    problems = [p for name in arms for p in name_problems(name, "arm")]
    problems += [p for name in cameras for p in name_problems(name, "camera")]
    places, arm_infos = _placements(args, cameras, arms)
    problems += [p for name, place in places.items() if (p := mount_problem(place.mount, arms, f"camera {name}"))]
    if not problems:  # a wrist camera's link must be a link of its arm's robot description
        from manisplat.episode.validation import check_mount_links

        problems = [p.message for p in check_mount_links(
            Path.cwd(), {name: info.to_v2_dict() for name, info in arm_infos.items()},
            {name: {"mount": place.mount} for name, place in places.items()})]
    if problems:
        raise RigUsageError("; ".join(problems))


def open_rig(args: argparse.Namespace, clock: Clock, stop: threading.Event) -> RigDevices:
    """Open every arm (or simulator) and camera the options name (checked by :func:`check_rig`);
    DriverError when one fails, ReplayInputError when a replayed recording does not fit."""
    from manisplat.drivers.piper import PiperArm

    channels = _arm_channels(args)
    specs = _camera_specs(args)
    places, arm_infos = _placements(args, list(specs), list(channels))
    dev = RigDevices()
    try:
        for name, channel in channels.items():
            if channel is None:
                from manisplat.recorder.simrig import SimRig

                rig = SimRig(clock, motion=args.sim_motion, keep_states=False).start()
                dev.rigs.append(rig)
                arm = PiperArm(rig.open_bus(), read_only=True, own_bus=True)
                dev.info[f"arm {name}"] = f"simulated PiPER ({args.sim_motion}) on a virtual bus"
            else:
                arm = PiperArm.open(channel, args.interface, read_only=True)
                dev.info[f"arm {name}"] = f"PiPER on {args.interface} {channel}"
            dev.arms.append(RigArm(name, arm, arm_infos[name]))
        epoch = ReplayEpoch()  # replayed cameras start together, however late their reader threads start
        for name, spec in specs.items():
            dev.cameras.append(_open_camera(args, name, spec, places[name], clock, stop, dev, epoch))
    except BaseException:
        dev.close()
        raise
    return dev


def _open_camera(args: argparse.Namespace, name: str, spec: str, place: _Placement, clock: Clock,
                 stop: threading.Event, dev: RigDevices, epoch: ReplayEpoch) -> RigCamera:
    from manisplat.recorder.cli import open_camera

    camera, depth, nominal_fps, info = open_camera(args, spec, clock, stop, name, epoch)
    dev.info[f"camera {name}"] = info
    if dev.nominal_fps is None:
        dev.nominal_fps = nominal_fps
    size = (camera.width, camera.height)
    if place.size is not None and tuple(place.size) != size:
        camera.close()
        raise ReplayInputError(f"camera {name}: {args.calib} calibrates it at {place.size[0]}x{place.size[1]} but it "
                               f"gives {size[0]}x{size[1]} images; record at that size (--size) or calibrate again")
    K = camera.K if place.K is None else place.K
    dist = camera.dist if place.dist is None else place.dist
    extra = {} if place.latency_s is None else {"latency_s": place.latency_s}
    cam_info = CameraInfo(name, size[0], size[1], K, opencv_dist(dist), mount=place.mount,
                          T_mount_cam=place.T_mount_cam, extra=extra)
    latency = place.latency_s if place.latency_s is not None else args.latency_ms / 1e3
    return RigCamera(name, camera, cam_info, latency_s=latency, depth=depth)


def make_recorder(args: argparse.Namespace, dev: RigDevices, clock: Clock) -> RigRecorder:
    """The recorder of the rig, with the options' settings."""
    config = RecorderConfig(fps=args.fps, max_gap_s=args.max_gap_ms / 1e3, image_format=args.image_format,
                            task=args.task, actions=args.actions,
                            max_skew_s=None if args.max_skew_ms is None else args.max_skew_ms / 1e3)
    return RigRecorder(dev.arms, dev.cameras, clock, config, source_info=dev.info, nominal_fps=dev.nominal_fps)


def rig_summary(results: list[EpisodeResult]) -> str:
    """Per episode, one line per camera and per arm: what each lost, skipped and flagged."""
    lines = []
    for r in results:
        s = r.stats
        for name, c in s.cameras.items():
            lines.append(f"{r.path.name}  camera {name}: {c.frames} frames, dropped by the camera {c.dropped_camera}, "
                         f"unmatched {c.unmatched}, unused {c.unused}, stale {c.stale}, out of order {c.out_of_order}, "
                         f"stalls {c.stalls}, max skew {c.max_skew_s * 1e3:.1f} ms")
        for name, a in s.arms.items():
            lines.append(f"{r.path.name}  arm {name}: {a.joint_samples} joint samples, CAN frames {a.can_frames_logged} "
                         f"(dropped {a.can_frames_dropped}), flagged {a.flagged}, max gap {a.max_sync_gap_s * 1e3:.1f} ms")
        if s.skipped or s.dropped_queue:
            lines.append(f"{r.path.name}  skipped {s.skipped} frames without every camera's image, the writer "
                         f"dropped {s.dropped_queue}")
    return "\n".join(lines)

