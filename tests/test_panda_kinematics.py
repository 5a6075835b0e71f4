"""Panda kinematics against an independent closed-form modified-DH computation."""

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from torchrl_silp.robots.panda import Panda, panda_urdf_path

# Franka's published modified (Craig) DH table (Franka Control Interface
# documentation, robot and interface specifications), written out here
# independently of the URDF: (a_{i-1}, d_i, alpha_{i-1}) of joints 1-7.
DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
]
FLANGE = (0.0, 0.107, 0.0)
HAND_YAW = -math.pi / 4  # Franka Hand mounted on the flange
TCP_OFFSET = 0.1034  # Franka Hand TCP along the hand's z axis
LOW = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
HIGH = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
# Upper arm leaning forward, elbow folded to its limit, wrist bent back: the hand
# ends up on the base column (found by a grid search over q2, q4, q6).
FOLDED = np.array([0.0, 0.32, 0.0, -3.07, 0.0, 1.345, 0.0])


def mdh(a: float, d: float, alpha: float, theta: np.ndarray) -> np.ndarray:
    """Craig's RotX(alpha) TransX(a) RotZ(theta) TransZ(d), closed form, batched over theta."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    A = np.zeros(theta.shape + (4, 4))
    A[..., 0, 0], A[..., 0, 1], A[..., 0, 3] = ct, -st, a
    A[..., 1, 0], A[..., 1, 1], A[..., 1, 2], A[..., 1, 3] = st * ca, ct * ca, -sa, -sa * d
    A[..., 2, 0], A[..., 2, 1], A[..., 2, 2], A[..., 2, 3] = st * sa, ct * sa, ca, ca * d
    A[..., 3, 3] = 1.0
    return A


def dh_frames(q: np.ndarray) -> dict[str, np.ndarray]:
    """World poses (n, 4, 4) of joint frames 1-7, the flange, the hand and the TCP."""
    n = q.shape[0]
    T = np.tile(np.eye(4), (n, 1, 1))
    out = {}
    for i, (a, d, alpha) in enumerate(DH):
        T = T @ mdh(a, d, alpha, q[:, i])
        out[f"panda_link{i + 1}"] = T
    out["panda_link8"] = T = T @ mdh(*FLANGE, np.zeros(n))
    out["panda_hand"] = T = T @ mdh(0.0, 0.0, 0.0, np.full(n, HAND_YAW))
    out["tcp"] = T @ mdh(0.0, TCP_OFFSET, 0.0, np.zeros(n))
    return out


def random_q(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 7, generator=g, dtype=torch.float64)
    return torch.as_tensor(LOW) + u * torch.as_tensor(HIGH - LOW)


@pytest.fixture(scope="module")
def robot64():
    return Panda(dtype=torch.float64)


@pytest.fixture(scope="module")
def robot32():
    return Panda()


# ------------------------------------------------------------------ the URDF
def _rpy(r: float, p: float, y: float) -> np.ndarray:
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def test_urdf_joint_origins_realise_the_dh_table():
    """origin(xyz, rpy) @ RotZ(theta) of each URDF joint equals the DH transform."""
    root = ET.parse(panda_urdf_path()).getroot()
    joints = {j.get("name"): j for j in root.iter("joint")}
    theta = np.linspace(-3.0, 3.0, 13)
    for i, (a, d, alpha) in enumerate([*DH, FLANGE]):
        joint = joints[f"panda_joint{i + 1}"]
        assert joint.get("type") == ("revolute" if i < 7 else "fixed")
        origin = joint.find("origin")
        O = np.eye(4)
        O[:3, :3] = _rpy(*[float(v) for v in origin.get("rpy").split()])
        O[:3, 3] = [float(v) for v in origin.get("xyz").split()]
        th = theta if i < 7 else np.zeros(1)
        rz = mdh(0.0, 0.0, 0.0, th)
        np.testing.assert_allclose(O @ rz, mdh(a, d, alpha, th), atol=1e-12)
        if i < 7:
            assert joint.find("axis").get("xyz").split() == ["0", "0", "1"]
            limit = joint.find("limit")
            assert (float(limit.get("lower")), float(limit.get("upper"))) == (LOW[i], HIGH[i])


def test_joint_limits_buffers(robot64, robot32):
    np.testing.assert_array_equal(robot64.joint_low.numpy(), LOW)
    np.testing.assert_array_equal(robot64.joint_high.numpy(), HIGH)
    assert robot32.joint_low.dtype == torch.float32 and robot32.joint_low.shape == (7,)
    assert robot64.frame_names == [f"panda_link{i}" for i in range(9)] + ["panda_hand", "tcp"]


# ---------------------------------------------------------------- kinematics
def test_fk_matches_closed_form_dh(robot64):
    q = random_q(5000)
    expected = dh_frames(q.numpy())
    err = np.abs(robot64.fk(q).numpy() - expected["tcp"][:, :3, 3]).max()
    assert err < 1e-6, err
    rot, pos = robot64.frames(q)
    for name, T in expected.items():
        f = robot64.frame_names.index(name)
        assert np.abs(pos[:, f].numpy() - T[:, :3, 3]).max() < 1e-6, name
        assert np.abs(rot[:, f].numpy() - T[:, :3, :3]).max() < 1e-6, name
    # the base frame is the world frame
    assert torch.equal(rot[:, 0], torch.eye(3, dtype=torch.float64).expand(len(q), 3, 3))
    assert torch.equal(pos[:, 0], torch.zeros(len(q), 3, dtype=torch.float64))


def test_home_tcp_is_franka_ready_pose(robot64):
    # Franka's "ready" pose puts the hand's TCP 0.307 m ahead of the base, 0.487 m up
    tcp = robot64.fk(torch.as_tensor(HOME))
    np.testing.assert_allclose(tcp.numpy(), dh_frames(HOME[None])["tcp"][0, :3, 3], atol=1e-9)
    np.testing.assert_allclose(tcp.numpy(), [0.307, 0.0, 0.487], atol=1e-3)


def test_fk_agrees_with_pytorch_kinematics_chain(robot32):
    q = random_q(1000, seed=1).float()
    err = (robot32.fk(q) - robot32.reference_fk(q)).abs().max().item()
    assert err < 1e-5, err
    assert robot32.fk(q).dtype == torch.float32


def test_default_dtype_is_float32(robot32):
    assert robot32.dtype == torch.float32
    assert robot32.fk(torch.zeros(7, dtype=torch.float64)).dtype == torch.float32


@pytest.mark.parametrize("batch", [(), (5,), (2, 3), (0,)])
def test_batched_shapes(robot64, batch):
    n = math.prod(batch)
    q = random_q(n, seed=2).reshape(*batch, 7)
    flat = q.reshape(-1, 7)
    S, F = robot64.n_spheres, len(robot64.frame_names)

    tcp = robot64.fk(q)
    assert tcp.shape == (*batch, 3)
    torch.testing.assert_close(tcp.reshape(-1, 3), robot64.fk(flat))

    rot, pos = robot64.frames(q)
    assert rot.shape == (*batch, F, 3, 3) and pos.shape == (*batch, F, 3)
    torch.testing.assert_close(pos[..., -1, :], tcp)

    centres, tcp2 = robot64.spheres_and_tcp(q)
    assert centres.shape == (*batch, S, 3) and tcp2.shape == (*batch, 3)
    torch.testing.assert_close(tcp2, tcp)
    torch.testing.assert_close(centres.reshape(-1, S, 3), robot64.spheres_and_tcp(flat)[0])
    c3, radii = robot64.link_spheres(q)
    assert torch.equal(c3, centres) and radii.shape == (S,)

    hit = robot64.self_collision(centres)
    assert hit.shape == batch and hit.dtype == torch.bool
    assert robot64.reference_fk(q).shape == (*batch, 3)


def test_spheres_ride_on_their_frames(robot64):
    q = random_q(200, seed=3)
    rot, pos = robot64.frames(q)
    centres, _ = robot64.spheres_and_tcp(q)
    f = robot64.sphere_frame
    expected = (rot[:, f] @ robot64.sphere_local.unsqueeze(-1)).squeeze(-1) + pos[:, f]
    assert (centres - expected).abs().max() < 1e-12


# ----------------------------------------------------------------- collision
def _sample_inside(prim, n: int, g: torch.Generator) -> np.ndarray:
    """n points inside the primitive plus its extreme points, in the primitive's frame."""
    u = torch.rand(n, 3, generator=g, dtype=torch.float64).numpy()
    if prim.kind == "cylinder":
        r, length = prim.size
        rho, phi = r * np.sqrt(u[:, 0]), 2 * math.pi * u[:, 1]
        pts = np.stack([rho * np.cos(phi), rho * np.sin(phi), (u[:, 2] - 0.5) * length], axis=1)
        ang = np.linspace(0, 2 * math.pi, 16, endpoint=False)
        rim = [np.stack([r * np.cos(ang), r * np.sin(ang), np.full(16, z)], 1) for z in (-length / 2, length / 2)]
        return np.concatenate([pts, *rim])
    if prim.kind == "box":
        half = np.asarray(prim.size) / 2
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        return np.concatenate([(2 * u - 1) * half, corners])
    r = prim.size[0]
    v = torch.randn(n, 3, generator=g, dtype=torch.float64).numpy()
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.concatenate([v * r * np.cbrt(u[:, :1]), v[:8] * r])


def test_sphere_cover_is_conservative(robot64):
    g = torch.Generator().manual_seed(4)
    q = random_q(3, seed=4)
    rot, pos = robot64.frames(q)
    centres, radii = robot64.link_spheres(q)
    links = np.asarray(robot64.sphere_link_names)
    for prim in robot64.primitives:
        local = _sample_inside(prim, 300, g)
        in_link = local @ prim.transform[:3, :3].T + prim.transform[:3, 3]
        f = robot64.frame_names.index(prim.link)
        mine = torch.as_tensor(links == prim.link)
        for k in range(len(q)):
            world = torch.as_tensor(in_link) @ rot[k, f].T + pos[k, f]
            d = (world[:, None, :] - centres[k, mine][None]).norm(dim=-1) - radii[mine]
            assert (d.min(dim=1).values <= 1e-9).all(), f"{prim} not covered"


def test_every_link_but_tcp_has_geometry(robot64):
    assert set(robot64.sphere_link_names) == set(robot64.frame_names) - {"tcp"}
    assert robot64.n_spheres == len(robot64.sphere_radii) == len(robot64.sphere_local) == len(robot64.sphere_frame)
    assert (robot64.sphere_radii > 0.02).all() and (robot64.sphere_radii < 0.12).all()


def test_table_mask(robot64):
    on_table = {"panda_link0", "panda_link1"}
    expected = [name not in on_table for name in robot64.sphere_link_names]
    assert robot64.table_mask.dtype == torch.bool
    assert robot64.table_mask.tolist() == expected


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_home_is_free(dtype):
    robot = Panda(dtype=dtype)
    centres, radii = robot.link_spheres(torch.as_tensor(HOME, dtype=dtype))
    assert not robot.self_collision(centres)
    low = centres[robot.table_mask, 2] - radii[robot.table_mask]
    assert (low > 0.1).all(), low.min()


def test_self_collision_pair_rule(robot64):
    a, b = robot64.self_pair_a, robot64.self_pair_b
    assert a.dtype == b.dtype == torch.long and len(a) == len(b) > 0
    assert (a < b).all()
    body = {f"panda_link{i}": i for i in range(8)} | {"panda_link8": 7, "panda_hand": 7}
    names = robot64.sphere_link_names
    pairs = {(names[i], names[j]) for i, j in zip(a.tolist(), b.tolist())}
    assert all(abs(body[x] - body[y]) >= 3 for x, y in pairs)
    # every link pair 3 or more joints apart is checked (none overlap at home)
    wanted = {(x, y) for x in body for y in body if body[y] - body[x] >= 3}
    assert pairs == wanted
    assert robot64.home_overlap_pairs == []
    # and no checked pair overlaps at home
    centres, radii = robot64.link_spheres(torch.as_tensor(HOME))
    assert ((centres[a] - centres[b]).norm(dim=-1) > radii[a] + radii[b]).all()


def test_self_collision_matches_pairwise_check(robot64, robot32):
    q = random_q(3000, seed=5)
    centres, radii = robot64.link_spheres(q)
    a, b = robot64.self_pair_a, robot64.self_pair_b
    brute = ((centres[:, a] - centres[:, b]).norm(dim=-1) < radii[a] + radii[b]).any(-1)
    assert 0.02 < brute.double().mean() < 0.5  # both outcomes occur
    assert torch.equal(robot64.self_collision(centres), brute)
    # float32 away from the boundary
    c32, _ = robot32.link_spheres(q.float())
    margin = ((centres[:, a] - centres[:, b]).norm(dim=-1) - radii[a] - radii[b]).min(-1).values
    clear = margin.abs() > 1e-5
    assert torch.equal(robot32.self_collision(c32)[clear], brute[clear])


def test_folded_pose_self_collides(robot64):
    assert np.all(FOLDED >= LOW) and np.all(FOLDED <= HIGH)
    # independently of the sphere model: the centre of the hand body (0.033 m
    # along the flange axis) sits on the base column's axis, between the base
    # (0.14 m) and the shoulder (0.333 m), i.e. inside the arm's own link 1
    hand = dh_frames(FOLDED[None])["panda_hand"][0]
    centre = hand[:3, 3] + 0.033 * hand[:3, 2]
    assert np.linalg.norm(centre[:2]) < 0.03 and 0.15 < centre[2] < 0.3, centre
    centres, radii = robot64.link_spheres(torch.as_tensor(FOLDED))
    assert robot64.self_collision(centres)
    # ... and it is the hand against the base column that is flagged
    names = np.asarray(robot64.sphere_link_names)
    hand_s = torch.as_tensor(names == "panda_hand")
    base_s = torch.as_tensor(np.isin(names, ["panda_link0", "panda_link1"]))
    d = (centres[hand_s][:, None] - centres[base_s][None]).norm(dim=-1)
    assert (d < radii[hand_s][:, None] + radii[base_s][None]).any()
    # and the folded pose stays above the table: the self check alone catches it
    assert (centres[robot64.table_mask, 2] > radii[robot64.table_mask]).all()


# ------------------------------------------------------------ differentiable
def test_fk_gradient_matches_finite_differences(robot64):
    q = random_q(4, seed=6).requires_grad_(True)
    assert torch.autograd.gradcheck(robot64.fk, (q,), eps=1e-6, atol=1e-7)
    centres, _ = robot64.spheres_and_tcp(q)
    (grad,) = torch.autograd.grad(centres.sum(), q)
    assert torch.isfinite(grad).all()
    # an explicit central difference of the TCP along every joint
    q0 = random_q(1, seed=7)[0]
    jac = torch.autograd.functional.jacobian(robot64.fk, q0)
    h = 1e-6
    for j in range(7):
        e = torch.zeros(7, dtype=torch.float64)
        e[j] = h
        fd = (robot64.fk(q0 + e) - robot64.fk(q0 - e)) / (2 * h)
        torch.testing.assert_close(jac[:, j], fd, atol=1e-8, rtol=0)


def test_float32_gradients_are_finite(robot32):
    q = random_q(16, seed=8).float().requires_grad_(True)
    rot, pos = robot32.frames(q)
    (rot.sum() + pos.sum() + robot32.fk(q).sum()).backward()
    assert torch.isfinite(q.grad).all()


# ---------------------------------------------------------------- module api
def test_to_casts_and_moves_buffers(robot64):
    robot = Panda().to(torch.float64)
    assert robot.dtype == torch.float64 and robot.device == torch.device("cpu")
    q = random_q(50, seed=9)
    torch.testing.assert_close(robot.fk(q), robot64.fk(q), atol=1e-6, rtol=0)
    meta = Panda().to("meta")
    assert meta.device.type == "meta"
    out = meta.spheres_and_tcp(torch.zeros(3, 7, device="meta"))[0]
    assert out.device.type == "meta" and out.shape == (3, meta.n_spheres, 3)


def test_argument_errors(robot32):
    with pytest.raises(ValueError, match="q"):
        robot32.fk(torch.zeros(6))
    with pytest.raises(ValueError, match="q"):
        robot32.frames(torch.zeros(2, 3))
    with pytest.raises(TypeError, match="q"):
        robot32.fk(torch.zeros(7, dtype=torch.long))
    with pytest.raises(TypeError, match="q"):
        robot32.spheres_and_tcp([0.0] * 7)
    with pytest.raises(ValueError, match="centres"):
        robot32.self_collision(torch.zeros(4, 3))
    with pytest.raises(TypeError, match="dtype"):
        Panda(dtype=torch.float16)
    with pytest.raises(ValueError, match="urdf_path"):
        Panda(urdf_path="/nonexistent/panda.urdf")
