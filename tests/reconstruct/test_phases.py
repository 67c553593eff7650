"""Motion/Skill segmentation on synthetic TCP and gripper tracks."""

from __future__ import annotations

import logging

import numpy as np

from manisplat.align.phases import gripper_events, phase_of_frames, segment_phases


def pick_and_place(T=120):
    """TCP: home (0.4 m away) -> down to the object at frame 40 -> carried 0.25 m away -> released -> up."""
    obj0, obj1 = np.array([0.30, -0.10, 0.02]), np.array([0.30, 0.15, 0.02])
    tcp = np.zeros((T, 3))
    keys = [(0, obj0 + [0, 0, 0.4]), (35, obj0), (45, obj0), (55, obj0 + [0, 0, 0.1]), (75, obj1 + [0, 0, 0.1]),
            (85, obj1), (95, obj1), (110, obj1 + [0, 0, 0.2]), (T - 1, obj1 + [0, 0, 0.2])]
    for (a, pa), (b, pb) in zip(keys[:-1], keys[1:]):
        s = np.linspace(0, 1, b - a + 1)[:, None]
        tcp[a:b + 1] = (1 - s) * pa + s * pb
    grip = np.full(T, 0.07)
    grip[40:46] = np.linspace(0.07, 0.04, 6)
    grip[46:92] = 0.04
    grip[92:98] = np.linspace(0.04, 0.07, 6)
    return tcp, grip, obj0


def test_gripper_events():
    _, grip, _ = pick_and_place()
    (event,) = gripper_events(grip)
    assert 40 <= event.grasp <= 43 and 92 <= event.release <= 95
    assert gripper_events(np.full(50, 0.07)) == []


def squeeze(T=120, hold=-0.9):
    """The effort of pick_and_place's gripper: squeezing from frame 40, easing off as its command
    opens from frame 88 (under a quarter of the hold from 91), the pads parting from 92."""
    effort = np.zeros(T)
    effort[40:46] = np.linspace(0.0, hold, 6)
    effort[46:88] = hold
    effort[88:92] = hold * np.array([0.8, 0.5, 0.3, 0.1])
    effort[92:95] = [0.05, -0.01, 0.0]
    return effort


def test_the_release_is_where_the_pads_stop_squeezing(caplog):
    _, grip, _ = pick_and_place()
    (by_opening,) = gripper_events(grip)
    with caplog.at_level(logging.INFO):
        (by_effort,) = gripper_events(grip, effort=squeeze())
    assert by_effort.grasp == by_opening.grasp and by_opening.release == 93
    assert by_effort.release == 91, "the first frame whose effort is under a quarter of the hold's"
    assert "stopped squeezing at frame 91" in caplog.text
    (by_size,) = gripper_events(grip, effort=-2 * squeeze())  # the sign and the units do not matter
    assert by_size.release == 91


def test_an_effort_that_shows_no_squeeze_leaves_the_opening_s_release(caplog):
    _, grip, _ = pick_and_place()
    with caplog.at_level(logging.INFO):
        assert gripper_events(grip, effort=np.zeros(120))[0].release == 93
        assert "shows no squeeze" in caplog.text
        gaps = squeeze()
        gaps[60] = np.nan
        assert gripper_events(grip, effort=gaps)[0].release == 93
    late = squeeze()
    late[88:95] = -0.9  # still squeezing while the pads part: the opening's release stands
    assert gripper_events(grip, effort=late)[0].release == 93
    relaxed = squeeze()
    relaxed[70:95] = -0.1  # the grip relaxed mid-carry, 23 frames before the pads opened: not the release
    with caplog.at_level(logging.INFO):
        assert gripper_events(grip, effort=relaxed)[0].release == 93
    assert "a grip that relaxed while holding" in caplog.text


def test_pick_and_place_gives_the_five_phases_in_order():
    tcp, grip, obj0 = pick_and_place()
    segments = segment_phases(tcp, gripper_events(grip), obj0, tau=0.08)
    assert [s.name for s in segments] == ["M_approach", "S_pick", "M_transfer", "S_place", "M_return"]
    assert segments[0].start == 0 and segments[-1].end == 120
    assert all(a.end == b.start for a, b in zip(segments, segments[1:]))  # contiguous
    pick, place = segments[1], segments[3]
    assert pick.start <= 40 < pick.end and place.start <= 93 < place.end
    names = phase_of_frames(segments, 120)
    assert names[0] == "M_approach" and names[-1] == "M_return"


def test_too_large_tau_merges_the_skills_and_warns(caplog):
    tcp, grip, obj0 = pick_and_place()
    with caplog.at_level(logging.WARNING):
        segments = segment_phases(tcp, gripper_events(grip), obj0, tau=0.3)
    assert "S_pick+S_place" in [s.name for s in segments]
    assert "smaller tau" in caplog.text


def test_reach_without_grasp():
    tcp, _, obj0 = pick_and_place()
    segments = segment_phases(tcp[:60], gripper_events(np.full(60, 0.07)), obj0, tau=0.08)
    assert [s.name for s in segments] == ["M_approach", "S_reach", "M_return"]


def test_short_segments_are_absorbed():
    tcp, grip, obj0 = pick_and_place()
    segments = segment_phases(tcp, gripper_events(grip), obj0, tau=0.08, min_duration=200)
    assert len(segments) == 1 and segments[0].start == 0 and segments[0].end == 120
