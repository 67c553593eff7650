"""A new demonstration's commands keep the relation the source's commands had to its joints: the
source's lead in every frame, and in a skill the source's press (what its commands did beyond the
lead) at the source time the frame plays; the next frame's joints where the source had none."""

from __future__ import annotations

import numpy as np

from manisplat.augment.commands import command_lead, commanded

T = 40


def source(lead: float = 0.3, press: float = -0.01):
    """A source moving joint 0 by 0.02 rad a frame, its commands leading by ``lead`` of a frame and
    pressing ``press`` rad on joint 1 over frames 20-29 (a place pushing down)."""
    q = np.zeros((T, 2))
    q[:, 0] = 0.02 * np.arange(T)
    offset = np.zeros((T, 2))
    offset[:-1] = lead * np.diff(q, axis=0)
    offset[20:30, 1] += press
    return q, offset


def test_without_recorded_commands_the_command_is_the_next_frame():
    q = np.cumsum(np.full((10, 2), 0.01), axis=0)
    out = commanded(q, np.arange(10.0), np.ones(10, bool), q, None)
    np.testing.assert_array_equal(out, np.concatenate([q[1:], q[-1:]]))


def test_the_lead_is_fitted_to_the_source():
    q, offset = source(lead=0.3)
    assert abs(command_lead(q, offset) - 0.3) < 1e-9
    assert command_lead(q, None) == 1.0 and command_lead(np.zeros((T, 2)), offset) == 1.0


def test_motions_lead_by_the_source_s_lead_and_skills_add_its_press_at_their_source_time():
    """New joints at half the source's speed, the skill playing source frames 18-31 slowed 2x:
    every command leads by 0.3 of its own step; the skill's frames press where the source did."""
    q_src, offset = source(lead=0.3, press=-0.01)
    new = np.zeros((60, 2))
    new[:, 0] = 0.01 * np.arange(60)
    source_time = np.full(60, np.nan)
    in_skill = np.zeros(60, bool)
    in_skill[20:47] = True
    source_time[20:47] = np.linspace(18, 31, 27)
    out = commanded(new, source_time, in_skill, q_src, offset)
    led = new + 0.3 * (np.concatenate([new[1:], new[-1:]]) - new)
    np.testing.assert_allclose(out[~in_skill], led[~in_skill], atol=1e-12)
    pressing = in_skill & (source_time >= 20) & (source_time <= 29)
    np.testing.assert_allclose(out[pressing, 1] - led[pressing, 1], -0.01, atol=1e-12)
    np.testing.assert_allclose(out[in_skill, 0], led[in_skill, 0], atol=1e-12)  # no press on joint 0
    outside = in_skill & ((source_time < 19) | (source_time > 30))
    np.testing.assert_allclose(out[outside, 1], led[outside, 1], atol=1e-12)
