"""A new demonstration's commands: the new joints led by the source's lead, and in a skill the
source's press at the source time the frame plays, faded in and out inside the skill's ends; the
next frame's joints where the source had none."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from manisplat.augment.commands import CLEAR_FRAMES, FADE_S, SourceCommands
from manisplat.augment.source import source_demo
from manisplat.augment.trajectory import AugmentConfig, ObjectTarget, augment_trajectory
from manisplat.drivers.piper.trajectory import ReplayLimits, Trajectory, check_trajectory
from manisplat.robot import builtin_piper
from manisplat.twin.commands import CommandRelation, command_relation, led

T = 40
FPS = 20.0


def source(press: float = -0.01):
    """Joint 0 moving 0.02 rad a frame, commands leading by 0.3 of a frame and pressing ``press``
    rad on joint 1 over frames 10-29."""
    q = np.zeros((T, 2))
    q[:, 0] = 0.02 * np.arange(T)
    commands = q.copy()
    commands[:-1] += 0.3 * np.diff(q, axis=0)
    commands[10:30, 1] += press
    return command_relation(q, commands)


def test_without_recorded_commands_the_command_is_the_next_frame():
    q = np.cumsum(np.full((10, 2), 0.01), axis=0)
    commands = SourceCommands(None, 2, FPS)
    assert not commands.recorded
    np.testing.assert_array_equal(commands.press_at(np.arange(2.0, 8.0), 2, 7), 0.0)
    np.testing.assert_array_equal(commands.commanded(q, np.zeros_like(q)), np.concatenate([q[1:], q[-1:]]))


def test_new_joints_are_led_by_the_source_s_lead():
    q = np.cumsum(np.full((10, 2), 0.01), axis=0)
    out = SourceCommands(source(), 2, FPS).commanded(q, np.zeros_like(q))
    np.testing.assert_allclose(out[:-1], q[:-1] + 0.3 * 0.01, atol=1e-12)


def test_a_skill_presses_where_the_source_pressed_and_fades_in_and_out_inside_its_ends():
    """The skill on source frames 5-34 played slowed 2x: inside, the source's press at the same
    source time; none within CLEAR_FRAMES of its ends; half of it halfway through a fade, all of
    it after."""
    commands = SourceCommands(source(press=-0.01), 2, FPS)
    s = np.linspace(5, 34, 59)
    press = commands.press_at(s, 5, 34)
    fade, clear = FADE_S * FPS, CLEAR_FRAMES
    pressing = (s >= 11) & (s <= 28) & (s >= 5 + clear + fade) & (s <= 34 - clear - fade)
    np.testing.assert_allclose(press[pressing, 1], -0.01, atol=1e-3)
    np.testing.assert_allclose(press[:, 0], 0.0, atol=1e-12)  # joint 0 only leads
    ends = (s <= 5 + clear) | (s >= 34 - clear)
    assert ends.sum() >= 8 and np.all(press[ends] == 0.0)
    start = 10.0 + clear  # a skill starting inside the press
    at = np.array([start, start + fade / 2, start + fade])
    ramp = commands.press_at(at, 10, 34)[:, 1] / commands.press_at(at, 0, 39)[:, 1]
    np.testing.assert_allclose(ramp, [0.0, 0.5, 1.0], atol=1e-12)


def test_a_skill_is_slowed_until_its_commands_too_keep_the_limits(twin):
    """The source's commands pressing 0.03 rad back and forth on joint 2 every other frame: at the
    pace the joints alone allow they would accelerate past the limits, so the pick (long enough to
    press between its faded ends) is slowed further, until they do not, and the new commands
    (pressing) pass the replay's checks."""
    targets = {k: ObjectTarget(o.T_rest, o.T_placed) for k, o in source_demo(twin).objects.items() if o.manipulated}
    calm = augment_trajectory(twin, targets, AugmentConfig())
    press = np.zeros_like(twin.q)
    press[:, 1] = 0.03 * (-1.0) ** np.arange(len(twin.q))
    pressing = twin.with_demonstration(replace(twin.demonstration, commands=CommandRelation(1.0, press)))
    traj = augment_trajectory(pressing, targets, AugmentConfig())
    own, pressed = calm.planner["skills"][0], traj.planner["skills"][0]
    assert own["name"] == "S_pick" and pressed["slowed"] > 1.1 * own["slowed"], (own, pressed)
    robot = builtin_piper(with_geometry=False)
    plan = Trajectory(traj.t.copy(), traj.action_q, traj.action_gripper, "actions", 1.0)
    assert check_trajectory(plan, robot, ReplayLimits()) == []
    skill = next(s for s in traj.segments if s["kind"] == "skill")
    first, last = skill["frames"]
    assert np.abs(traj.action_q[first:last, 1] - led(traj.q, 1.0)[first:last, 1]).max() > 0.01
