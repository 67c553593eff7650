"""A recording's commands as its joints led by a fraction of a frame plus a press per frame."""

from __future__ import annotations

import numpy as np
import pytest

from manisplat.twin.commands import CommandRelation, command_lead, command_relation, led

T = 40


def recording(lead: float = 0.3, press: float = -0.01):
    """Joint 0 moving 0.02 rad a frame, the commands leading by ``lead`` of a frame and pressing
    ``press`` rad on joint 1 over frames 10-29 (a place pushing down)."""
    q = np.zeros((T, 2))
    q[:, 0] = 0.02 * np.arange(T)
    commands = q.copy()
    commands[:-1] += lead * np.diff(q, axis=0)
    commands[10:30, 1] += press
    return q, commands


def test_the_lead_and_the_press_are_fitted_and_give_the_commands_back():
    q, commands = recording(lead=0.3, press=-0.01)
    relation = command_relation(q, commands)
    assert abs(relation.lead - 0.3) < 1e-9
    np.testing.assert_allclose(relation.press[10:30, 1], -0.01, atol=1e-12)
    np.testing.assert_allclose(relation.press[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(led(q, relation.lead) + relation.press, commands, atol=1e-12)


def test_a_still_or_one_frame_recording_leads_by_one_frame():
    q, commands = recording()
    assert command_lead(np.zeros((T, 2)), commands) == 1.0 and command_lead(q[:1], commands[:1]) == 1.0


def test_a_mix_of_two_frames_never_accelerates_more_than_the_joints():
    """Up to the last frame (a new demonstration ends at rest, its last command its own joints)."""
    rng = np.random.default_rng(0)
    q = np.cumsum(np.cumsum(rng.normal(size=(50, 3)), axis=0), axis=0)
    for lead in (0.0, 0.3, 1.0):
        commands = led(q, lead)[:-1]
        assert np.abs(np.diff(commands, 2, axis=0)).max() <= np.abs(np.diff(q, 2, axis=0)).max() + 1e-12


def test_bad_relations_are_refused():
    with pytest.raises(ValueError, match="differ in shape"):
        command_relation(np.zeros((5, 6)), np.zeros((5, 7)))
    with pytest.raises(ValueError, match="lead"):
        CommandRelation(1.5, np.zeros((5, 6)))
    with pytest.raises(ValueError, match="finite"):
        CommandRelation(0.5, np.full((5, 6), np.nan))
    with pytest.raises(ValueError, match="gripper commands of shape"):
        CommandRelation(0.5, np.zeros((5, 6)), np.zeros(4))
    with pytest.raises(ValueError, match="gripper commands"):
        CommandRelation(0.5, np.zeros((5, 6)), np.full(5, np.inf))
