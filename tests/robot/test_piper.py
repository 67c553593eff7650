"""The built-in PiPER against piper_sdk's published kinematics, limits, TCP, gripper, Jacobian."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manisplat.geometry import rotation_error, rpy_to_matrix, matrix_to_rpy
from manisplat.robot import RobotModelError, builtin_piper, load_robot

# piper_sdk modified DH (reference/piper_can.md §1.9, dh_is_offset=1): alpha, a (mm), d (mm), offset (deg)
SDK_DH = [
    (0.0, 0.0, 123.0, 0.0),
    (-math.pi / 2, 0.0, 0.0, -172.22),
    (0.0, 285.03, 0.0, -102.78),
    (math.pi / 2, -21.98, 250.75, 0.0),
    (-math.pi / 2, 0.0, 0.0, 0.0),
    (math.pi / 2, 0.0, 91.0, 0.0),
]


def sdk_flange(q: np.ndarray) -> np.ndarray:
    """piper_sdk's FK written straight from the DH table: RotX(a) TransX(a) RotZ(th+off) TransZ(d), mm."""
    T = np.eye(4)
    for (alpha, a, d, off), theta in zip(SDK_DH, q):
        ca, sa = math.cos(alpha), math.sin(alpha)
        th = theta + math.radians(off)
        ct, st = math.cos(th), math.sin(th)
        T = T @ np.array(
            [[ct, -st, 0, a], [st * ca, ct * ca, -sa, -sa * d], [st * sa, ct * sa, ca, ca * d], [0, 0, 0, 1]]
        )
    return T


@pytest.fixture(scope="module")
def piper():
    return builtin_piper()


def test_matches_the_dh_table_everywhere(piper):
    q = piper.sample_configurations(300, generator=torch.Generator().manual_seed(0))
    ours = piper.link_pose(q, "link6").numpy()
    for qi, T in zip(q.numpy(), ours):
        ref = sdk_flange(qi)
        assert np.abs(T[:3, 3] * 1000 - ref[:3, 3]).max() < 1e-9  # mm
        assert np.abs(T[:3, :3] - ref[:3, :3]).max() < 1e-12


@pytest.mark.parametrize(
    "q, pose",
    [
        ([0, 0, 0, 0, 0, 0], (56.128, 0.0, 213.266, 0.0, 85.0, 0.0)),
        ([0.2, 0.5, -0.5, 0.3, -0.2, 0.5], (104.836, 15.8, 360.983, 68.511, 41.469, 83.347)),
    ],
)
def test_reproduces_piper_sdk_checked_poses(piper, q, pose):
    """The two poses piper_sdk printed (mm, deg; rounded to 0.001): < 0.01 mm and 0.001 deg."""
    T = piper.link_pose(torch.tensor(q, dtype=torch.float64), "link6")
    assert float((T[:3, 3] * 1000 - torch.tensor(pose[:3], dtype=torch.float64)).abs().max()) < 0.01
    R_sdk = rpy_to_matrix(torch.tensor(np.radians(pose[3:]), dtype=torch.float64))
    assert math.degrees(float(rotation_error(T[:3, :3], R_sdk))) < 0.001
    assert np.allclose(np.degrees(matrix_to_rpy(T[:3, :3]).numpy()), pose[3:], atol=0.001)


def test_limits_are_agilex_values(piper):
    assert np.allclose(np.degrees(piper.upper), [150, 179.9, 0, 100, 70, 120], atol=0.1)
    assert np.allclose(np.degrees(piper.lower), [-150, 0, -170, -100, -70, -120], atol=0.1)
    assert np.allclose(np.degrees(piper.velocity_limits), [180, 195, 180, 225, 225, 225])
    assert np.allclose(piper.acceleration_limits, 5.0)
    q = piper.sample_configurations(1000, generator=torch.Generator().manual_seed(1))
    assert bool(piper.within_limits(q).all())
    assert not bool(piper.within_limits(torch.tensor([0, -0.1, 0, 0, 0, 0.0], dtype=torch.float64)))


def test_tcp_is_twelve_centimetres_along_the_flange_axis(piper):
    q = piper.sample_configurations(50, generator=torch.Generator().manual_seed(2))
    flange, tcp = piper.link_pose(q, "link6"), piper.tcp_pose(q)
    assert torch.allclose(tcp[:, :3, :3], flange[:, :3, :3])
    assert torch.allclose(tcp[:, :3, 3], flange[:, :3, 3] + 0.12 * flange[:, :3, 2], atol=1e-15)


@pytest.mark.parametrize("width", [0.0, 0.03, 0.07])
def test_fingers_open_symmetrically_along_tcp_y(piper, width):
    q = torch.tensor([0.1, 1.0, -1.0, 0.2, 0.3, -0.4], dtype=torch.float64)
    poses = piper.forward_kinematics(q, torch.tensor(width, dtype=torch.float64))
    tcp = piper.tcp_pose(q)
    f7 = poses[piper.link_index("link7"), :3, 3]
    f8 = poses[piper.link_index("link8"), :3, 3]
    assert abs(float((f8 - f7).norm()) - width) < 1e-15
    assert torch.allclose((f8 - f7) @ tcp[:3, 1], torch.tensor(width, dtype=torch.float64))  # +y side = link8


def test_jacobian_matches_finite_differences(piper):
    q = piper.sample_configurations(20, generator=torch.Generator().manual_seed(3))
    J, T = piper.jacobian(q)
    h = 1e-6
    for k in range(6):
        dq = torch.zeros(6, dtype=torch.float64)
        dq[k] = h
        Tp, Tm = piper.tcp_pose(q + dq), piper.tcp_pose(q - dq)
        v = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * h)
        dR = (Tp[:, :3, :3] - Tm[:, :3, :3]) / (2 * h) @ T[:, :3, :3].transpose(-1, -2)  # = hat(omega)
        omega = torch.stack([dR[:, 2, 1], dR[:, 0, 2], dR[:, 1, 0]], -1)
        assert torch.allclose(J[:, :3, k], v, atol=1e-8)
        assert torch.allclose(J[:, 3:, k], omega, atol=1e-8)


def test_batches_dtypes_and_bad_input(piper):
    q = torch.zeros(2, 3, 6, dtype=torch.float64)
    assert piper.forward_kinematics(q).shape == (2, 3, 9, 4, 4)
    T32 = piper.tcp_pose(q.float())
    assert T32.dtype == torch.float32 and torch.allclose(T32.double(), piper.tcp_pose(q), atol=1e-6)
    assert piper.tcp_pose(np.zeros(6)).dtype == torch.float64
    with pytest.raises(RobotModelError, match="6 values"):
        piper.tcp_pose(torch.zeros(5))
    with pytest.raises(RobotModelError, match="NaN"):
        piper.tcp_pose(torch.tensor([0, 0, math.nan, 0, 0, 0]))
    with pytest.raises(RobotModelError, match="gripper"):
        piper.forward_kinematics(torch.zeros(6), gripper=math.inf)
    with pytest.raises(RobotModelError, match="no link named"):
        piper.link_pose(torch.zeros(6), "link9")


def test_every_link_has_primitive_geometry_near_its_kinematics(piper):
    """Each primitive sits where its link is: the geometry of links 2-5 spans to the next joint."""
    assert set(piper.visuals) == set(piper.link_names)
    for link in ("link2", "link3", "link5"):
        mesh = piper.visuals[link][0].mesh
        assert mesh.is_watertight and mesh.volume > 0
    # link2's capsule covers the 285 mm upper arm
    extent = piper.visuals["link2"][0].mesh.bounds
    assert extent[0, 0] < 0.0 and extent[1, 0] > 0.285


def test_load_robot_resolves_builtin_and_rejects_unknown(tmp_path):
    assert load_robot("builtin:agilex_piper").name == "builtin:agilex_piper"
    with pytest.raises(RobotModelError, match="unknown built-in"):
        load_robot("builtin:franka")
    with pytest.raises(FileNotFoundError, match="not found"):
        load_robot("robots/missing.urdf", base_dir=tmp_path)
