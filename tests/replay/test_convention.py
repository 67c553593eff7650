"""An episode's joint convention mapped onto the arm's, explicitly, checked by forward kinematics;
anything unknown refused."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from manisplat.drivers.piper.convention import (AGILEX_URDF_NEW, AGILEX_URDF_OLD, IDENTITY, ConventionError,
                                               JointConvention, convention_for, tcp_discrepancy_mm)
from manisplat.robot import builtin_piper
from tests.replay.helpers import NEW_URDF, OLD_URDF, write_urdf


def random_arm_q(n: int = 300) -> np.ndarray:
    robot = builtin_piper(with_geometry=False)
    return np.random.default_rng(0).uniform(robot.lower, robot.upper, (n, 6))


def test_builtin_is_the_arm_convention() -> None:
    assert convention_for("builtin:agilex_piper") is IDENTITY and IDENTITY.identity
    with pytest.raises(ConventionError, match="unknown built-in"):
        convention_for("builtin:ur5")


def test_the_old_agilex_urdf_maps_with_signs_and_offsets_and_keeps_the_tcp(tmp_path: Path) -> None:
    urdf = write_urdf(tmp_path / "piper_description.urdf", OLD_URDF)
    conv = convention_for("piper_description.urdf", tmp_path)
    assert conv is AGILEX_URDF_OLD
    q_urdf = AGILEX_URDF_OLD.from_arm(random_arm_q())
    np.testing.assert_allclose(conv.to_arm(q_urdf), random_arm_q(), atol=1e-12)
    np.testing.assert_allclose(conv.to_arm(np.zeros(6)), np.radians([0, -2, 2, 0, 0, 0]) + [0, 0, 0, 0, 0.087266, 0])
    np.testing.assert_array_equal(conv.sign, [1, 1, 1, -1, 1, -1])
    assert tcp_discrepancy_mm(conv, str(urdf), None, q_urdf) < 1.6  # the two CAD versions differ by ~1.4 mm
    naive = JointConvention("as is", np.ones(6), np.zeros(6))
    assert tcp_discrepancy_mm(naive, str(urdf), None, q_urdf) > 100.0  # why the map matters


def test_the_new_agilex_urdf_is_the_sdk_convention(tmp_path: Path) -> None:
    urdf = write_urdf(tmp_path / "new.urdf", NEW_URDF)
    conv = convention_for(str(urdf))
    assert conv is AGILEX_URDF_NEW and conv.identity
    assert tcp_discrepancy_mm(conv, str(urdf), None, random_arm_q()) < 0.2


def test_an_unknown_description_is_refused(tmp_path: Path) -> None:
    changed = [list(j) for j in OLD_URDF]
    changed[1][1] = (1.5708, -0.2, -1.5708)  # another joint2 frame
    write_urdf(tmp_path / "other.urdf", changed)
    with pytest.raises(ConventionError, match="cannot map the joint angles of .*other.urdf"):
        convention_for("other.urdf", tmp_path)
    (tmp_path / "arm.urdf").write_text('<robot name="x"><link name="a"/></robot>')
    with pytest.raises(ConventionError, match="none of the known"):
        convention_for(str(tmp_path / "arm.urdf"))
    with pytest.raises(ConventionError, match="not found"):
        convention_for("missing.urdf", tmp_path)
    (tmp_path / "broken.urdf").write_text("<robot")
    with pytest.raises(ConventionError, match="cannot read"):
        convention_for(str(tmp_path / "broken.urdf"))


def test_offsets_are_the_documented_numbers() -> None:
    assert AGILEX_URDF_OLD.offset[1] == pytest.approx(-math.radians(2)) and AGILEX_URDF_OLD.offset[4] == 0.087266
