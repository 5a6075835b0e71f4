"""UR5e kinematics against an independent closed-form DH computation."""

import math

import numpy as np
import pytest
import torch

from torchrl_silp import UR5e

# Official UR5e DH parameters (Universal Robots), written out independently of the URDF.
DH_D = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996]
DH_A = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0]
DH_ALPHA = [math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]
TCP_OFFSET = 0.2328  # Robotiq 2F-140 fingertip centre below the flange (assets/ur5e.urdf)


def dh_tcp(q6: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TCP position and tool z axis in ROS base_link (DH base turned pi about z)."""
    n = q6.shape[0]
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(6):
        th = q6[:, i]
        ct, st = np.cos(th), np.sin(th)
        ca, sa = math.cos(DH_ALPHA[i]), math.sin(DH_ALPHA[i])
        A = np.zeros((n, 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca, st * sa, DH_A[i] * ct
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca, -ct * sa, DH_A[i] * st
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa, ca, DH_D[i]
        A[:, 3, 3] = 1.0
        T = T @ A
    tcp = T[:, :3, 3] + TCP_OFFSET * T[:, :3, 2]
    rz_pi = np.diag([-1.0, -1.0, 1.0])
    return tcp @ rz_pi.T, T[:, :3, 2] @ rz_pi.T


@pytest.fixture(scope="module")
def robot64():
    return UR5e(dtype=torch.float64)


def random_q3(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi * torch.tensor(
        [2.0, 2.0, 1.0], dtype=torch.float64
    )


def test_fk_matches_closed_form_dh(robot64):
    q3 = random_q3(10_000)
    q6 = robot64.full_joints(q3)
    expected, _ = dh_tcp(q6.numpy())
    err = (robot64.fk(q3).numpy() - expected).__abs__().max()
    assert err < 1e-6, err
    # the single-configuration path too
    single = torch.stack([robot64.fk(q) for q in q3[:200]])
    assert (single.numpy() - expected[:200]).__abs__().max() < 1e-6


def test_tool_axis_points_down(robot64):
    q3 = random_q3(10_000, seed=1)
    rot, pos = robot64.tcp_pose(q3)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    assert (rot[..., :, 2] - down).abs().max() < 1e-6
    # and the closed form agrees that the coupled wrist does it
    _, z_axis = dh_tcp(robot64.full_joints(q3).numpy())
    assert np.abs(z_axis - down.numpy()).max() < 1e-6


def test_full_joints_coupling(robot64):
    q3 = random_q3(100, seed=2)
    q6 = robot64.full_joints(q3)
    torch.testing.assert_close(q6[:, :3], q3)
    torch.testing.assert_close(q6[:, 3], -math.pi / 2 - q3[:, 1] - q3[:, 2])
    assert torch.all(q6[:, 4] == -math.pi / 2) and torch.all(q6[:, 5] == 0)


def test_fk_agrees_with_pytorch_kinematics_chain(robot64):
    q3 = random_q3(500, seed=3)
    # the library keeps URDF origins float32-rounded: ~1e-7 m floor
    assert (robot64.fk(q3) - robot64.reference_fk(q3)).abs().max() < 1e-6


@pytest.mark.parametrize("n", [1, 4])  # the single-configuration path and the batched kernel
def test_fk_gradcheck(robot64, n):
    q3 = random_q3(n, seed=4).requires_grad_(True)
    assert torch.autograd.gradcheck(robot64.fk, (q3,))
    assert torch.autograd.gradcheck(lambda q: robot64.link_spheres(q)[0], (q3,))


def test_leading_dims_match_per_sample_loop(robot64):
    q3 = random_q3(24, seed=5).reshape(2, 3, 4, 3)
    batched = robot64.fk(q3)
    centres, _ = robot64.link_spheres(q3)
    assert batched.shape == (2, 3, 4, 3)
    for idx in np.ndindex(2, 3, 4):
        torch.testing.assert_close(batched[idx], robot64.fk(q3[idx]))
        torch.testing.assert_close(centres[idx], robot64.link_spheres(q3[idx])[0])


def test_frames_end_at_tcp(robot64):
    q3 = random_q3(50, seed=6)
    rot, pos = robot64.frames(q3)
    assert robot64.frame_names[-1] == "tcp"
    torch.testing.assert_close(pos[:, -1], robot64.fk(q3))


def test_float32_default_and_urdf_from_package():
    robot = UR5e()
    assert robot.dtype == torch.float32
    assert robot.urdf_path.endswith("ur5e.urdf")
    q = torch.zeros(3)
    assert robot.fk(q).dtype == torch.float32


def test_bad_inputs(robot64, tmp_path):
    with pytest.raises(ValueError, match="q3"):
        robot64.fk(torch.zeros(4, 2, dtype=torch.float64))
    with pytest.raises(TypeError, match="q3"):
        robot64.fk(torch.zeros(3, dtype=torch.long))
    with pytest.raises(TypeError, match="q3"):
        robot64.fk([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="urdf_path"):
        UR5e(urdf_path=tmp_path / "missing.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/></robot>")
    with pytest.raises(ValueError, match="urdf_path"):
        UR5e(urdf_path=bad)
    with pytest.raises(TypeError, match="dtype"):
        UR5e(dtype=torch.float16)
