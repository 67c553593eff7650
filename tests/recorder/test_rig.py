"""manisplat-record with two named arms and three cameras (a Cobot Magic): two simulated PiPERs on
their own virtual buses and three replayed cameras, into one version 2 episode: killed with
SIGKILL and recovered with every written frame of every camera, drops counted per camera and
per arm, options that do not describe a rig refused."""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from manisplat.drivers.piper import PiperArm
from manisplat.drivers.replay import EpisodeCamera
from manisplat.episode import Episode, validate
from manisplat.episode.infos import ArmInfo, CameraInfo
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.recorder.armfeed import JOINT_TAIL_S
from manisplat.recorder.cli import main
from manisplat.recorder.clock import ManualClock
from manisplat.recorder.replaycam import ReplayCamera, ReplayEpoch
from manisplat.recorder.layout import VersionTwo
from manisplat.recorder.loop import EpisodeLoop
from manisplat.recorder.result import EpisodeResult
from manisplat.recorder.rig import RigArm, RigCamera, RigRecorder
from manisplat.recorder.session import RecorderConfig
from manisplat.recorder.simrig import SimRig, wave_gripper_effort
from tests.recorder.helpers import K, source_frame, write_source

RECORD = [sys.executable, "-m", "manisplat.recorder.cli"]
EPISODE = [sys.executable, "-m", "manisplat.episode.cli"]
CAMERAS = {"cam_high": ("world", 0), "cam_left_wrist": ("left/link6", 1), "cam_right_wrist": ("right/link6", 2)}
"""Camera -> (mount, source number: each camera replays its own images)."""
ARMS = ("left", "right")
MAX_SYNC_ERROR_DEG = 0.05  # as for one arm (test_session)


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Each camera's own 2 s recording (60 frames, 64x48, 30 fps)."""
    folder = tmp_path_factory.mktemp("rig_sources")
    return {name: write_source(folder / name, camera=k) for name, (_, k) in CAMERAS.items()}


@pytest.fixture(scope="module")
def calib(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A calibration file in the format of docs/cobot-magic.md: the cameras' K and mounts, the arms' bases."""
    T = np.eye(4)
    arms = {name: {"T_world_base": T.tolist(), "description": "builtin:agilex_piper"} for name in ARMS}
    arms["right"]["T_world_base"][1][3] = -0.6
    cameras = {name: {"K": K.tolist(), "mount": mount, "T_mount_cam": T.tolist(), "width": 64, "height": 48,
                      "latency_s": 0.0} for name, (mount, _) in CAMERAS.items()}
    path = tmp_path_factory.mktemp("rig_calib") / "rig.calib.json"
    path.write_text(json.dumps({"fps": 30, "arms": arms, "cameras": cameras}))
    return path


def rig_args(sources: dict[str, Path], calib: Path, out: Path, *extra: str) -> list[str]:
    cameras = [a for name, path in sources.items() for a in ("--camera", f"{name}=replay:{path}")]
    return ["--sim", "--arm", "left", "--arm", "right", *cameras, "--calib", str(calib), "--out", str(out),
            "--start", "now", *extra]


def whole_rows(frames_csv: Path) -> list[str]:
    """The rows of ``frames.csv`` ended by a line break (each one a frame the writer reported
    written: its images of every camera are written before its row)."""
    return frames_csv.read_text().split("\n")[1:-1] if frames_csv.is_file() else []


def wait_for_whole_rows(frames_csv: Path, rows: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Wait until the CSV file has ``rows`` whole rows (the recorder still running)."""
    deadline = time.monotonic() + timeout
    while len(whole_rows(frames_csv)) < rows:
        if proc.poll() is not None:
            raise AssertionError(f"the recorder exited early ({proc.returncode}): {proc.communicate()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"{frames_csv} did not reach {rows} rows in {timeout} s")
        time.sleep(0.05)


def test_two_arms_three_cameras_killed_with_sigkill_are_recovered_with_every_written_frame(
        tmp_path: Path, sources: dict[str, Path], calib: Path) -> None:
    out = tmp_path / "out"
    proc = subprocess.Popen(RECORD + rig_args(sources, calib, out, "--loop", "--duration", "300"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    episode = out / "episode_0000"
    try:
        wait_for_whole_rows(episode / "frames.csv", 40, proc)  # past the first fsync (30 rows)
        for arm in ARMS:  # and each arm's joint stream begun (its writer may lag on a loaded machine)
            wait_for_whole_rows(episode / f"joints_{arm}.csv", 1, proc)
    finally:
        proc.kill()
        proc.communicate(timeout=60)
    assert proc.returncode == -9
    written = whole_rows(episode / "frames.csv")
    assert len(written) >= 40 and not Episode.open(episode).meta.complete
    copy = tmp_path / "copy"
    shutil.copytree(episode, copy)

    done = subprocess.run(EPISODE + ["recover", str(episode)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    report = validate(episode)
    assert report.ok, report
    ep = Episode.open(episode)
    assert ep.meta.version == 2 and ep.meta.complete
    assert list(ep.arms) == list(ARMS) and list(ep.cameras) == list(CAMERAS)
    assert whole_rows(episode / "frames.csv")[:len(written)] == written  # every written row, unchanged
    assert len(ep) == len(written)
    seq = {name: ep.arm_frames("left").extra[f"{name}.seq"].astype(int) for name in CAMERAS}
    for i in range(len(ep)):
        for name, (_, k) in CAMERAS.items():  # every camera's image of every frame, its own
            np.testing.assert_array_equal(ep.rgb(i, name), source_frame(seq[name][i] % 60, k))
    assert ep.cameras["cam_left_wrist"].mount == "left/link6" and ep.cameras["cam_high"].mount == "world"
    assert ep.arms["right"].T_world_base[1, 3] == -0.6
    for arm in ARMS:
        assert len(ep.joints(arm)) > 0 and (episode / f"can_{arm}.asc").stat().st_size > 0
    t = ep.arm_frames("left").t
    for name in ("cam_left_wrist", "cam_right_wrist"):  # each image within half a frame period of its frame
        assert np.abs(ep.camera_times(name) - t).max() <= 0.5 / 30 + 1e-9

    # manisplat-record --recover (and every start) does the same and cuts every arm's torn CAN log line
    assert main(["--recover", str(copy)]) == 0
    assert whole_rows(copy / "frames.csv") == whole_rows(episode / "frames.csv")
    for arm in ARMS:
        assert (copy / f"can_{arm}.asc").read_bytes().endswith(b"\n")
        assert len(list(can.LogReader(copy / f"can_{arm}.asc"))) > 0


def _keep_pace(me: SimRig, other: SimRig) -> None:
    """Lock-step: ``me`` waits until ``other`` has run as many cycles (real-time bound 30 s)."""
    deadline = time.monotonic() + 30.0
    while other.cycles < me.cycles and not (other.error or other._thread is None):
        if time.monotonic() > deadline:
            raise TimeoutError("the other simulated arm stopped cycling")
        time.sleep(0.0002)


LATE = {"cam_high": 0.0, "cam_left_wrist": 0.010, "cam_right_wrist": 0.020}
"""Each replayed camera's stamp latency, s."""


@dataclass
class LockstepRig:
    """Two simulated arms that keep pace with each other and three replayed cameras on a ManualClock
    (independent of the machine's speed), recorded by one RigRecorder."""

    sims: dict[str, SimRig]
    arms: dict[str, PiperArm]
    cams: dict[str, ReplayCamera]
    recorder: RigRecorder

    def record(self, path: Path, duration: float | None, **options: Any) -> EpisodeResult:
        try:
            for sim in self.sims.values():
                sim.start()
            self.recorder.wait_for_arms(timeout=30.0)
            return self.recorder.record_episode(path, duration=duration, **options)
        finally:
            for cam in self.cams.values():
                cam.close()
            for name in ARMS:
                self.sims[name].stop()
                self.arms[name].close()


def lockstep_rig(sources: dict[str, Path]) -> LockstepRig:
    clock = ManualClock()
    sims = {name: SimRig(clock, motion="wave") for name in ARMS}
    arms = {name: PiperArm(sim.open_bus(), read_only=True, own_bus=True) for name, sim in sims.items()}
    epoch = ReplayEpoch()
    cams = {name: ReplayCamera(lambda p=sources[name]: EpisodeCamera(p), clock, loop=True, stamp_latency_s=LATE[name],
                               epoch=epoch) for name in CAMERAS}
    for name, sim in sims.items():
        sim.add_consumer(lambda n, arm=arms[name]: arm.wait_for_frames(n, timeout=30.0))
        sim.add_consumer(lambda _n, me=sim, other=sims["right" if name == "left" else "left"]: _keep_pace(me, other))
        sim.follow(lambda: min(cam.consumed_until for cam in cams.values()))
    recorder = RigRecorder([RigArm(name, arm, ArmInfo(name=name)) for name, arm in arms.items()],
                           [RigCamera(name, cam, CameraInfo(name, 64, 48, K, mount=CAMERAS[name][0]),
                                      latency_s=LATE[name]) for name, cam in cams.items()],
                           clock, RecorderConfig(queue_frames=10_000, flush_grace_s=30.0), nominal_fps=30.0)
    return LockstepRig(sims, arms, cams, recorder)


def test_two_arms_are_synced_to_their_true_state_and_each_camera_keeps_its_own_time(
        tmp_path: Path, sources: dict[str, Path]) -> None:
    """Lock-step: the cameras stamped 0, 10 and 20 ms late (the end waits for every camera
    thread to catch up: on the manual clock, however loaded the machine)."""
    rig = lockstep_rig(sources)
    result = rig.record(tmp_path / "ep", duration=2.0)
    sims, cams = rig.sims, rig.cams
    assert result.valid and result.error is None
    ep = Episode.open(tmp_path / "ep")
    t0 = ep.meta.extra["clock"]["t0_monotonic"]
    assert len(ep) >= 55 and result.stats.frames_lost == 0 and result.stats.flagged == 0
    for name in ARMS:
        frames = ep.arm_frames(name)
        truth = sims[name].truth(frames.t + t0)  # the reference camera's true exposure times
        assert np.degrees(np.abs(frames.q - truth[:, :6])).max() < MAX_SYNC_ERROR_DEG
        assert np.abs(frames.gripper - truth[:, 6]).max() < 1e-4
        effort = frames.extra["gripper_effort"]  # <arm>.gripper_effort, from the arm's own gripper frames
        assert np.abs(effort - wave_gripper_effort(frames.t + t0 - sims[name].m0)).max() < 3e-3
        assert not frames.extra["sync_flags"].any()
    for name in ("cam_left_wrist", "cam_right_wrist"):  # its own time is its true exposure (latency corrected)
        exposure = dict(cams[name].exposures)
        seq = ep.arm_frames("left").extra[f"{name}.seq"].astype(int)
        np.testing.assert_allclose(ep.camera_times(name) + t0, [exposure[k] for k in seq], atol=1e-9)
        assert result.stats.cameras[name].unmatched == 0


@pytest.mark.parametrize("shared", [True, False])
def test_replayed_cameras_start_together_however_late_a_reader_asks(sources: dict[str, Path], shared: bool) -> None:
    """The second camera's reader asks 50 ms (1.5 frames) after the first's: sharing the rig's
    epoch, frame k of both is exposed at the same time; each on its own start, 50 ms apart."""
    clock = ManualClock()
    epoch = ReplayEpoch() if shared else None
    cams = [ReplayCamera(lambda p=sources[name]: EpisodeCamera(p), clock, epoch=epoch)
            for name in ("cam_high", "cam_left_wrist")]
    for cam in cams:
        with contextlib.suppress(TimeoutError):  # it asks for its first frame: its start is fixed
            cam.read(timeout=0.01)
        clock.advance_to(clock.monotonic() + 0.05)
    clock.advance_to(clock.monotonic() + 1.0)
    for cam in cams:
        while len(cam.exposures) < 5:
            cam.read(timeout=1.0)
        cam.close()
    first, second = (dict(cam.exposures) for cam in cams)
    np.testing.assert_allclose([second[k] - first[k] for k in range(5)], 0.0 if shared else 0.05, rtol=0, atol=1e-9)


def test_drops_are_counted_per_camera_and_per_arm(tmp_path: Path, sources: dict[str, Path], calib: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    gappy = dict(sources)  # the left wrist camera loses frames 20-24 (a stall: their seq and time skipped)
    gappy["cam_left_wrist"] = write_source(tmp_path / "gappy", missing=range(20, 25), camera=1)
    out = tmp_path / "out"
    assert main(rig_args(gappy, calib, out, "--duration", "30")) == 0  # ends with the 2 s recordings
    captured = capsys.readouterr().out
    ep = Episode.open(out / "episode_0000")
    stats = ep.meta.extra["stats"]
    cams, arms = stats["cameras"], stats["arms"]
    assert cams["cam_left_wrist"]["dropped_camera"] == 5
    assert cams["cam_high"]["dropped_camera"] == cams["cam_right_wrist"]["dropped_camera"] == 0
    # the 5 head frames around the lost ones had no partner (more only if a camera's reader fell
    # behind by more than the recorder waits, on a loaded machine)
    assert cams["cam_left_wrist"]["unmatched"] >= 5 and stats["skipped"] >= 5
    assert stats["skipped"] <= cams["cam_left_wrist"]["unmatched"] + cams["cam_right_wrist"]["unmatched"]
    assert len(ep) + stats["skipped"] + stats["dropped_queue"] == 60  # every head frame written or counted
    assert all(c["frames"] == len(ep) for c in cams.values())
    seq = ep.arm_frames("left").extra["cam_left_wrist.seq"]
    assert not np.isin(seq, np.arange(20, 25)).any()
    for name in ("cam_left_wrist", "cam_right_wrist"):  # the replays started together: each image is its frame's
        np.testing.assert_allclose(ep.camera_times(name), ep.arm_frames("left").t, rtol=0, atol=1e-6)
    for arm in ARMS:
        assert arms[arm]["joint_samples"] == len(ep.joints(arm)) > 0
        assert arms[arm]["can_frames_logged"] > 0 and arms[arm]["can_frames_dropped"] == 0
    assert "camera cam_left_wrist: " in captured and "dropped by the camera 5, unmatched " in captured
    assert "arm right: " in captured


@pytest.mark.parametrize("argv, message", [
    (["--sim", "--arm", "left", "--camera", "cam=replay:{src}"], "camera cam has no mount"),
    (["--sim", "--arm", "left=can0", "--camera", "cam=replay:{src}", "--mount", "cam=world"], "without a channel"),
    (["--arm", "left", "--camera", "cam=replay:{src}", "--mount", "cam=world"], "give the arm's CAN channel"),
    (["--sim", "--arm", "left", "--camera", "replay:{src}"], "every camera needs a name"),
    (["--sim", "--arm", "left", "--camera", "left=replay:{src}", "--mount", "left=world"], "names an arm and a camera"),
    (["--sim", "--arm", "left", "--camera", "cam=replay:{src}", "--mount", "other=world"], "no --camera other"),
    (["--sim", "--arm", "left", "--camera", "a=oak", "--camera", "b=oak", "--mount", "a=world", "--mount", "b=world"],
     "name each OAK's device id"),
    (["--sim", "--arm", "left", "--camera", "cam=replay:{src}", "--mount", "cam=right/link6"],
     "names the arm 'right', which is not in arms"),
    (["--sim", "--arm", "left", "--camera", "cam high=replay:{src}", "--mount", "cam high=world"], "camera name"),
    (["--sim", "--arm", "left", "--camera", "cam=replay:{src}", "--mount", "cam=left/link9"], "has no link 'link9'"),
    (["--sim", "--camera", "replay:{src}", "--mount", "cam=world"], "--mount is for several named arms"),
    (["--sim", "--camera", "replay:{src}", "--camera", "replay:{src}"], "several cameras record into one episode"),
])
def test_options_that_do_not_describe_a_rig_are_refused_naming_the_problem(
        argv: list[str], message: str, tmp_path: Path, sources: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main([a.replace("{src}", str(sources["cam_high"])) for a in argv] + ["--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()



def test_each_camera_replays_its_own_camera_of_a_recorded_two_arm_episode(tmp_path: Path, calib: Path,
                                                                          capsys: pytest.CaptureFixture) -> None:
    source = tmp_path / "cobot"
    cameras = [CameraInfo(name, 64, 48, K, mount=mount) for name, (mount, _) in CAMERAS.items()]
    with EpisodeWriterV2(source, [ArmInfo(name=a) for a in ARMS], cameras, 30.0) as writer:
        for i in range(45):
            writer.add_frame(i / 30, {a: np.zeros(7) for a in ARMS},
                             {name: source_frame(i, k) for name, (_, k) in CAMERAS.items()})
    out = tmp_path / "out"
    assert main(rig_args({name: source for name in CAMERAS}, calib, out, "--duration", "30")) == 0
    ep = Episode.open(out / "episode_0000")
    assert len(ep) >= 40
    for name, (_, k) in CAMERAS.items():
        seq = ep.arm_frames("left").extra[f"{name}.seq"].astype(int)
        for i in range(len(ep)):
            np.testing.assert_array_equal(ep.rgb(i, name), source_frame(seq[i], k))
    capsys.readouterr()
    argv = ["--sim", "--arm", "left", "--camera", f"cam=replay:{source}", "--mount", "cam=world",
            "--out", str(tmp_path / "o"), "--start", "now", "--duration", "1"]
    assert main(argv) == 2
    assert "has the cameras cam_high, cam_left_wrist, cam_right_wrist" in capsys.readouterr().err


def test_an_episode_ends_at_its_duration_when_frames_are_matched_slower_than_the_cameras_deliver(
        tmp_path: Path, sources: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """On a lock-step clock nothing holds the cameras back to real time: while the matching loop
    is stalled at its first frame (a loaded machine), the clock runs 4 s ahead. The episode
    still holds only the frames exposed within its 2 s, every arm state interpolated (none
    flagged: before, the loop wrote on past the end until the joint history had dropped the
    samples its frames needed), and its joints.csv ends with it."""
    write = VersionTwo.frame_item
    rig = lockstep_rig(sources)
    clock = rig.recorder.clock
    stalled = {"until": None}

    def stalled_frame_item(*args: Any, **kwargs: Any) -> Any:
        """The first frame's write waits until the clock has run 4 s past it (real-time bound 60 s)."""
        if stalled["until"] is None:
            stalled["until"] = clock.monotonic() + 4.0
            deadline = time.monotonic() + 60.0
            while clock.monotonic() < stalled["until"] and time.monotonic() < deadline:
                time.sleep(0.01)
        return write(*args, **kwargs)

    monkeypatch.setattr(VersionTwo, "frame_item", stalled_frame_item)
    result = rig.record(tmp_path / "ep", duration=2.0)
    assert result.valid and result.error is None
    assert clock.monotonic() >= stalled["until"]  # the clock did run ahead of the loop
    ep = Episode.open(tmp_path / "ep")
    assert 55 <= len(ep) <= 61 and ep.arm_frames("left").t.max() < 2.0
    assert result.stats.duration_s == pytest.approx(2.0) and result.stats.flagged == 0
    for arm in ARMS:  # the joints too end with the episode, however long the loop took to get there
        joints = ep.joints(arm)
        assert ep.arm_frames(arm).t.max() < joints.t[-1] <= 2.0 + JOINT_TAIL_S + 1e-9


def test_a_stopped_episode_s_joints_end_with_it_while_its_last_frames_are_matched(
        tmp_path: Path, sources: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """Stopped at 1.5 s; matching its last frames then stalls while the clock runs 2 s on (a
    loaded machine): joints.csv still ends JOINT_TAIL_S after the stop."""
    resolve = EpisodeLoop.resolve
    rig = lockstep_rig(sources)
    clock = rig.recorder.clock
    stalled: dict[str, float | None] = {"until": None}

    def stalled_resolve(self: EpisodeLoop, force: bool, until: float) -> None:
        """The first matching after the end waits until the clock has run 2 s on (real-time bound 60 s)."""
        if self.end is not None and not force and stalled["until"] is None:
            stalled["until"] = clock.monotonic() + 2.0
            deadline = time.monotonic() + 60.0
            while clock.monotonic() < stalled["until"] and time.monotonic() < deadline:
                time.sleep(0.01)
        resolve(self, force, until)

    monkeypatch.setattr(EpisodeLoop, "resolve", stalled_resolve)
    stop = threading.Event()
    result = rig.record(tmp_path / "ep", None, stop=stop,
                        on_status=lambda status: stop.set() if status.elapsed_s >= 1.5 else None)
    assert result.valid and result.error is None and result.stats.stop_reason == "stopped"
    assert clock.monotonic() >= stalled["until"]  # the clock did run on
    ep = Episode.open(tmp_path / "ep")
    for arm in ARMS:
        joints = ep.joints(arm)
        assert ep.arm_frames(arm).t.max() < joints.t[-1] <= result.stats.duration_s + JOINT_TAIL_S + 1e-9
