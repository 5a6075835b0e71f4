"""Collision geometry: conservative sphere cover, exact sphere-box test, edge subdivision."""

import math

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp import CollisionReason, UR5e, UR5eReachEnv, sphere_box_distance
from torchrl_silp.geometry import aabb_from_center, point_box_signed_distance

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
angles = st.tuples(
    st.floats(-math.pi, math.pi), st.floats(-math.pi, 0.3), st.floats(-math.pi, math.pi)
)


@pytest.fixture(scope="module")
def env():
    return UR5eReachEnv(dtype=torch.float64, seed=0)


def primitive_mesh(prim) -> trimesh.Trimesh:
    if prim.kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=prim.size[0], height=prim.size[1], sections=48)
    elif prim.kind == "box":
        mesh = trimesh.creation.box(extents=prim.size)
    else:
        mesh = trimesh.creation.icosphere(radius=prim.size[0])
    mesh.apply_transform(prim.transform)
    return mesh


@SETTINGS
@given(q=angles, seed=st.integers(0, 2**16))
def test_sphere_cover_contains_primitive_surfaces(env, q, seed):
    robot = env.robot
    q3 = torch.tensor(q, dtype=torch.float64)
    rot, pos = robot.frames(q3)
    centres, radii = robot.link_spheres(q3)
    for k, prim in enumerate(robot.primitives):
        pts, _ = trimesh.sample.sample_surface(primitive_mesh(prim), 400, seed=seed)
        pts = np.concatenate([pts, primitive_mesh(prim).vertices])
        f = robot.frame_names.index(prim.link)
        world = torch.as_tensor(pts) @ rot[f].T + pos[f]
        mine = robot.sphere_primitive == k
        d = (world[:, None, :] - centres[None, mine]).norm(dim=-1) - radii[mine]
        assert (d.min(dim=1).values <= 1e-9).all(), f"{prim} not covered"


def test_sphere_cover_is_not_wildly_loose():
    robot = UR5e(dtype=torch.float64)
    for k, prim in enumerate(robot.primitives):
        r = robot.sphere_radii[robot.sphere_primitive == k].max().item()
        thickness = min(prim.size) if prim.kind == "box" else prim.size[0]
        assert r < 2.0 * thickness + 1e-9, prim


def brute_force_obstacle_margin(centres, radii, box, spacing=0.004):
    """Min over sampled box points of (distance to centre - radius), per sphere."""
    lo, hi = box[0::2], box[1::2]
    axes = [torch.arange(float(lo[i]), float(hi[i]) + 1e-9, spacing, dtype=torch.float64) for i in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    on_surface = ((grid - lo).abs() < spacing / 2).any(-1) | ((grid - hi).abs() < spacing / 2).any(-1)
    grid = grid[on_surface]
    inside = ((centres >= lo) & (centres <= hi)).all(-1)
    to_surface = torch.cdist(centres, grid).min(dim=1).values
    return torch.where(inside, -to_surface, to_surface) - radii


@settings(max_examples=15, deadline=None, derandomize=True)
@given(q=angles, cx=st.floats(0.3, 0.7), cy=st.floats(0.1, 0.4))
def test_obstacle_flag_agrees_with_brute_force(env, q, cx, cy):
    q3 = torch.tensor(q, dtype=torch.float64)
    box = aabb_from_center(torch.tensor([cx, cy, 0.15], dtype=torch.float64), env.obstacle_size)
    centres, radii = env.robot.link_spheres(q3)
    margin = brute_force_obstacle_margin(centres, radii, box)
    flag = (env.collision_flags(q3, box) & CollisionReason.OBSTACLE).item() != 0
    exact = sphere_box_distance(centres, radii, box)
    # within the sampling resolution of the box surface they agree
    assert torch.allclose(exact, margin, atol=0.004 * math.sqrt(3))
    if (margin.abs() > 0.01).all():
        assert flag == bool((margin < 0).any())
    assert flag == bool((exact < 0).any())


@SETTINGS
@given(
    p=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
    c=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)),
    s=st.tuples(st.floats(0.01, 0.5), st.floats(0.01, 0.5), st.floats(0.01, 0.5)),
)
def test_point_box_signed_distance_matches_definition(p, c, s):
    p, c, s = (torch.tensor(v, dtype=torch.float64) for v in (p, c, s))
    box = aabb_from_center(c, s)
    d = point_box_signed_distance(p, box).item()
    lo, hi = c - s / 2, c + s / 2
    inside = bool(((p >= lo) & (p <= hi)).all())
    if inside:
        expected = -min((p - lo).min().item(), (hi - p).min().item())
    else:
        expected = (p - p.clamp(lo, hi)).norm().item()
    assert d == pytest.approx(expected, abs=1e-12)


def test_table_and_workspace_and_self_flags(env):
    robot = env.robot
    far_box = torch.tensor([5.0, 6.0, 5.0, 6.0, 5.0, 6.0], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    q3 = (torch.rand(4000, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    flags = env.collision_flags(q3, far_box).squeeze(-1)
    centres, radii = robot.link_spheres(q3)
    names = np.array(robot.sphere_link_names)
    not_base = torch.as_tensor(names != "base_link")
    table = ((centres[..., 2] - radii) < 0)[:, not_base].any(-1)
    assert torch.equal((flags & CollisionReason.TABLE) != 0, table)
    tcp = robot.fk(q3)
    low, high = torch.tensor(env.WORKSPACE_LOW), torch.tensor(env.WORKSPACE_HIGH)
    out = ~((tcp >= low) & (tcp <= high)).all(-1)
    assert torch.equal((flags & CollisionReason.WORKSPACE) != 0, out)
    grip = torch.as_tensor(names == "tool0")
    others = torch.as_tensor(np.isin(names, ["base_link", "shoulder_link", "upper_arm_link"]))
    d = torch.cdist(centres[:, grip], centres[:, others])
    self_hit = (d < radii[grip][:, None] + radii[others][None, :]).flatten(1).any(-1)
    assert torch.equal((flags & CollisionReason.SELF) != 0, self_hit)
    assert self_hit.any() and table.any() and out.any() and (flags == 0).any()
    assert torch.equal(env.collides(q3, far_box), flags != 0)


def test_home_pose_is_free(env):
    # UR "home" with the tool down: TCP at (0.49, 0.13, 0.26); the box 0.17 m away in y
    box = aabb_from_center(torch.tensor([0.3, 0.4, 0.15], dtype=torch.float64), env.obstacle_size)
    q = torch.tensor([0.0, -math.pi / 2, math.pi / 2], dtype=torch.float64)
    assert not env.collides(q, box)


@SETTINGS
@given(
    q=angles,
    dq=st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(-0.6, 0.6)),
    cx=st.floats(0.3, 0.7),
    cy=st.floats(0.1, 0.4),
    step=st.sampled_from([0.01, 0.02, 0.05]),
)
def test_edge_check_is_subdivision(env, q, dq, cx, cy, step):
    q_from = torch.tensor(q, dtype=torch.float64)
    q_to = q_from + torch.tensor(dq, dtype=torch.float64)
    box = aabb_from_center(torch.tensor([cx, cy, 0.15], dtype=torch.float64), env.obstacle_size)
    free = env.edge_collision_free(q_from, q_to, box, step_size=step).item()
    n = max(math.ceil((q_to - q_from).abs().max().item() / step), 1) + 1
    pts = torch.stack([q_from + t * (q_to - q_from) for t in np.linspace(0, 1, n)])
    any_hit = env.collides(pts, box).any().item()
    assert free == (not any_hit)
    if any(env.collides(torch.stack([q_from, q_to]), box)):
        assert not free


def test_edge_check_batched_equals_single(env):
    g = torch.Generator().manual_seed(1)
    q_from = (torch.rand(64, 3, generator=g, dtype=torch.float64) * 2 - 1) * 2
    q_to = q_from + (torch.rand(64, 3, generator=g, dtype=torch.float64) - 0.5)
    box = aabb_from_center(torch.tensor([0.5, 0.25, 0.15], dtype=torch.float64), env.obstacle_size)
    batched = env.edge_collision_free(q_from, q_to, box, step_size=0.02)
    # the batch uses the longest edge's count: at least as fine as each edge alone
    for i in range(64):
        alone = env.edge_collision_free(q_from[i], q_to[i], box, step_size=0.02)
        if not alone:
            assert not batched[i]
    assert batched.any() and (~batched).any()


def test_bad_collision_inputs(env):
    with pytest.raises(ValueError, match="obstacle"):
        env.collides(torch.zeros(3, dtype=torch.float64), torch.zeros(5, dtype=torch.float64))
    with pytest.raises(ValueError, match="q3"):
        env.collides(torch.zeros(2, dtype=torch.float64), torch.zeros(6, dtype=torch.float64))
    with pytest.raises(ValueError, match="step_size"):
        env.edge_collision_free(torch.zeros(3), torch.ones(3), torch.zeros(6), step_size=0)
