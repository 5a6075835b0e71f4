"""Collision geometry of the UR5e task model: conservative sphere cover (trimesh), exact sphere-box test,
the per-reason flags against brute force, and the swept motion check (subdivision with a Lipschitz margin)."""

import math

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from torchrl_silp import CollisionReason, UR5e, UR5eReach, sphere_box_distance
from torchrl_silp.geometry import aabb_from_center, point_box_signed_distance
from torchrl_silp.models.base import check_boxes

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
angles = st.tuples(
    st.floats(-math.pi, math.pi), st.floats(-math.pi, 0.3), st.floats(-math.pi, math.pi)
)


def flags_of(model, q, box):
    """The exact collision bit flags of configurations ``q`` against one box, shape ``q.shape[:-1]``."""
    flags, tcp = model.collision_flags(q, box)
    torch.testing.assert_close(tcp, model.robot.fk(q))
    return flags.squeeze(-1)


def scene(box, *batch):
    return TensorDict(obstacle=box.expand(*batch, 6), batch_size=list(batch))


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
def test_sphere_cover_contains_primitive_surfaces(model64, q, seed):
    robot = model64.robot
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
def test_obstacle_flag_agrees_with_brute_force(model64, q, cx, cy):
    q3 = torch.tensor(q, dtype=torch.float64)
    box = aabb_from_center(torch.tensor([cx, cy, 0.15], dtype=torch.float64), model64.obstacle_size)
    centres, radii = model64.robot.link_spheres(q3)
    margin = brute_force_obstacle_margin(centres, radii, box)
    flag = (flags_of(model64, q3, box) & CollisionReason.OBSTACLE).item() != 0
    exact = sphere_box_distance(centres, radii, box)
    # within the sampling resolution of the box surface they agree
    assert torch.allclose(exact, margin, atol=0.004 * math.sqrt(3))
    if (margin.abs() > 0.01).all():
        assert flag == bool((margin < 0).any())
    assert flag == bool((exact < 0).any())
    # the clearance is the exact distance (-radius for a centre inside the box),
    # and a margin inflates the spheres by that much
    clearance = model64.clearance(q3, box)[0].item()
    assert clearance == pytest.approx(torch.maximum(exact, -radii).min().item(), abs=1e-9)
    inflated, _ = model64.collision_flags(q3, box, {"obstacle": 0.02})
    assert bool(inflated.item() & CollisionReason.OBSTACLE) == (clearance < 0.02)


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


def test_table_and_workspace_and_self_flags(model64):
    robot = model64.robot
    far_box = torch.tensor([5.0, 6.0, 5.0, 6.0, 5.0, 6.0], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    q3 = (torch.rand(4000, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    flags = flags_of(model64, q3, far_box)
    centres, radii = robot.link_spheres(q3)
    names = np.array(robot.sphere_link_names)
    not_base = torch.as_tensor(names != "base_link")
    table = ((centres[..., 2] - radii) < 0)[:, not_base].any(-1)
    assert torch.equal((flags & CollisionReason.TABLE) != 0, table)
    tcp = robot.fk(q3)
    low, high = torch.tensor(UR5eReach.WORKSPACE_LOW), torch.tensor(UR5eReach.WORKSPACE_HIGH)
    out = ~((tcp >= low) & (tcp <= high)).all(-1)
    assert torch.equal((flags & CollisionReason.WORKSPACE) != 0, out)
    grip = torch.as_tensor(names == "tool0")
    others = torch.as_tensor(np.isin(names, ["base_link", "shoulder_link", "upper_arm_link"]))
    d = torch.cdist(centres[:, grip], centres[:, others])
    self_hit = (d < radii[grip][:, None] + radii[others][None, :]).flatten(1).any(-1)
    assert torch.equal((flags & CollisionReason.SELF) != 0, self_hit)
    assert self_hit.any() and table.any() and out.any() and (flags == 0).any()
    assert torch.equal(model64.collides(q3, far_box), flags != 0)
    assert torch.equal(model64.collides(q3, scene(far_box, 4000)), flags != 0)
    # the clearance per reason has the sign of the flags
    clearance = model64.clearance(q3, far_box)
    for bit, name in enumerate(model64.collision_reasons):
        assert torch.equal(clearance[:, bit] < 0, (flags & (1 << bit)) != 0), name


def test_home_pose_is_free(model64):
    # UR "home" with the tool down: TCP at (0.49, 0.13, 0.26); the box 0.17 m away in y
    box = aabb_from_center(torch.tensor([0.3, 0.4, 0.15], dtype=torch.float64), model64.obstacle_size)
    q = torch.tensor([0.0, -math.pi / 2, math.pi / 2], dtype=torch.float64)
    assert not model64.collides(q, box)
    # and free with the motion check's margin: a motion can start there
    assert model64.collision_flags(q, box, model64.motion_margin())[0].item() == 0


@SETTINGS
@given(
    q=angles,
    dq=st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(-0.6, 0.6)),
    cx=st.floats(0.3, 0.7),
    cy=st.floats(0.1, 0.4),
    step=st.sampled_from([0.01, 0.02, 0.05]),
    conservative=st.booleans(),
)
def test_motion_check_is_subdivision_with_the_lipschitz_margin(model64, q, dq, cx, cy, step, conservative):
    model64.conservative = conservative
    try:
        q_from = torch.tensor(q, dtype=torch.float64)
        q_to = q_from + torch.tensor(dq, dtype=torch.float64)
        box = aabb_from_center(torch.tensor([cx, cy, 0.15], dtype=torch.float64), model64.obstacle_size)
        free = model64.segment_collision_free(q_from[None], q_to[None], scene(box, 1), resolution=step).item()
        flags, _ = model64.motion_collision_flags(q_from, q_to, scene(box), resolution=step)
        assert free == (flags.item() == 0)
        n = max(math.ceil((q_to - q_from).abs().max().item() / step), 1) + 1
        pts = torch.stack([q_from + t * (q_to - q_from) for t in np.linspace(0, 1, n)])
        margin = model64.motion_margin(step)
        # samples no more than `step` apart, each with the margin L * step / 2 (none when not conservative)
        for name, bound in model64.lipschitz().items():
            assert margin[name] == (bound * step / 2 if conservative else 0.0)
        any_hit = (model64.collision_flags(pts, box, margin)[0] != 0).any().item()
        assert free == (not any_hit)
        if model64.collides(torch.stack([q_from, q_to]), box).any():
            assert not free
        if free and conservative:
            # sound: no colliding configuration between the samples either (4x finer, exact)
            fine = torch.stack([q_from + t * (q_to - q_from) for t in np.linspace(0, 1, 4 * (n - 1) + 1)])
            assert not model64.collides(fine, box).any()
    finally:
        model64.conservative = True


def test_subdivision_alone_misses_grazes_the_margin_catches():
    # why the margin: with exact samples 0.25 rad apart some passed segments collide in between
    exact = UR5eReach(conservative=False)
    g = torch.Generator().manual_seed(0)
    tasks = exact.sample_tasks(512, g)
    q_from = tasks["joint_position"]
    q_to = q_from + (torch.rand(512, 3, generator=g) * 2 - 1)
    sc = tasks.select("obstacle")
    coarse = exact.segment_collision_free(q_from, q_to, sc, resolution=0.25)
    n = 4 * 8 + 1  # 0.25 / 4 rad apart at most (the joint steps are below 1 rad)
    t = torch.linspace(0, 1, n).view(n, 1, 1)
    hit = exact.collides(q_from + t * (q_to - q_from), sc.unsqueeze(0).expand(n, 512)).any(0)
    missed = coarse & hit
    assert missed.any()
    # the conservative check at the same resolution rejects them all
    sound = UR5eReach().segment_collision_free(q_from, q_to, sc, resolution=0.25)
    assert not (sound & hit).any() and not sound[missed].any()


def test_motion_check_batched_equals_single(model64):
    g = torch.Generator().manual_seed(1)
    q_from = (torch.rand(64, 3, generator=g, dtype=torch.float64) * 2 - 1) * 2
    q_to = q_from + (torch.rand(64, 3, generator=g, dtype=torch.float64) - 0.5)
    box = aabb_from_center(torch.tensor([0.5, 0.25, 0.15], dtype=torch.float64), model64.obstacle_size)
    batched = model64.segment_collision_free(q_from, q_to, scene(box, 64), resolution=0.02)
    # each segment is sampled at its own count: the batch is the segments alone
    for i in range(64):
        alone = model64.segment_collision_free(q_from[i : i + 1], q_to[i : i + 1], scene(box, 1), resolution=0.02)
        assert bool(alone) == bool(batched[i])
    assert batched.any() and (~batched).any()
    # the padded batch check samples each motion at the longest one's count: at least as fine
    flags, _ = model64.motion_collision_flags(q_from, q_to, scene(box, 64), resolution=0.02)
    assert ((flags.squeeze(-1) != 0) | batched).all()


def test_lipschitz_bounds_the_geometry_speed(model64):
    # finite differences at random configurations stay below the bounds
    bounds = model64.lipschitz()
    assert set(bounds) == set(model64.collision_reasons)
    g = torch.Generator().manual_seed(2)
    q = (torch.rand(2000, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    dq = (torch.rand(2000, 3, generator=g, dtype=torch.float64) * 2 - 1) * 1e-3
    h = dq.abs().amax(-1, keepdim=True)
    c0, t0 = model64.robot.spheres_and_tcp(q)
    c1, t1 = model64.robot.spheres_and_tcp(q + dq)
    assert ((c1 - c0).norm(dim=-1) / h).max() <= bounds["obstacle"]
    assert ((t1 - t0).abs().amax(-1, keepdim=True) / h).max() <= bounds["workspace"]


def test_bad_collision_inputs(model64):
    with pytest.raises(ValueError, match="obstacle"):
        model64.collides(torch.zeros(3, dtype=torch.float64), torch.zeros(5, dtype=torch.float64))
    with pytest.raises(ValueError, match="config"):
        model64.collides(torch.zeros(2, dtype=torch.float64), torch.zeros(6, dtype=torch.float64))
    with pytest.raises(TypeError, match="config"):
        model64.collides([0.0, 0.0, 0.0], torch.zeros(6, dtype=torch.float64))
    with pytest.raises(ValueError, match="resolution"):
        model64.segment_collision_free(torch.zeros(1, 3), torch.ones(1, 3), scene(torch.zeros(6), 1), resolution=0)


_SPECIAL = st.sampled_from([0.0, -0.5, 0.5, 1e30, -1e30, float("nan"), float("inf"), -float("inf")])


@settings(max_examples=200, deadline=None)
@given(values=st.lists(st.one_of(st.floats(-2.0, 2.0, width=32), _SPECIAL), min_size=6, max_size=36).map(
    lambda v: v[: len(v) // 6 * 6]))
def test_box_check_accepts_exactly_the_finite_ordered_boxes(values):
    """check_boxes against an element-by-element reading of the rule, NaN and inf included."""
    boxes = torch.tensor(values, dtype=torch.float32).reshape(-1, 6)
    finite = all(math.isfinite(v) for v in values)
    ordered = all(values[i] <= values[i + 1] for i in range(0, len(values), 2))
    if finite and ordered:
        check_boxes("obstacle", boxes)
        return
    with pytest.raises(ValueError) as err:
        check_boxes("obstacle", boxes)
    expected = "obstacle must be finite" if not finite else "obstacle: a box has min > max"
    assert str(err.value).startswith(expected)


def test_compiled_kernel_equals_the_eager_one_at_padded_sizes(model64):
    """compile_collision=True: batches padded to a power of two, flags and TCP equal to the eager kernel's."""
    compiled = UR5eReach(model64.robot, compile_collision=True)
    gen = torch.Generator().manual_seed(3)
    for n in (5, 70):  # padded to 64 and 128: two compilations
        tasks = model64.sample_tasks(n, generator=gen)
        anywhere = model64.config_low + torch.rand(n, 3, generator=gen) * (model64.config_high - model64.config_low)
        q = torch.where(torch.arange(n).unsqueeze(-1) % 2 == 0, tasks["joint_position"], anywhere)  # free and not
        margin = model64.motion_margin()
        flags, tcp = compiled.collision_flags(q, tasks.select("obstacle"), margin)
        ref_flags, ref_tcp = model64.collision_flags(q, tasks.select("obstacle"), margin)
        assert flags.shape == (n, 1) and tcp.shape == (n, 3)
        assert torch.equal(flags, ref_flags) and bool((flags != 0).any()) and bool((flags == 0).any())
        torch.testing.assert_close(tcp, ref_tcp)
    empty = compiled.collision_flags(torch.zeros(0, 3), torch.zeros(0, 6))
    assert empty[0].shape == (0, 1)


def test_cover_points_from_trig_equal_per_sample_spheres_and_check_their_shapes(model64):
    q = model64.config_low + torch.rand(50, 3, generator=torch.Generator().manual_seed(5)) * (
        model64.config_high - model64.config_low)
    cos, sin = model64.robot.joint_trig(q)
    points = model64.robot.cover_points_from_trig(cos, sin)  # (3, N, S + 1)
    s = model64.robot.n_spheres
    for i in (0, 17, 49):  # one configuration at a time: the same products batched otherwise, float32's last bit
        centres, tcp = model64.robot.spheres_and_tcp(q[i])
        torch.testing.assert_close(points[:, i, :s].T, centres, atol=1e-7, rtol=0)
        torch.testing.assert_close(points[:, i, s], tcp, atol=1e-7, rtol=0)
    torch.testing.assert_close(points[:, :, s].T, model64.robot.reference_fk(q), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="cos and sin"):
        model64.robot.cover_points_from_trig(cos, sin[:3])


def test_compiled_kernel_follows_margins_and_layouts_at_one_size(model64):
    """One padded size met with other margins and a strided config: each result is the eager kernel's."""
    compiled = UR5eReach(model64.robot, compile_collision=True)
    gen = torch.Generator().manual_seed(4)
    tasks = model64.sample_tasks(64, generator=gen)
    anywhere = model64.config_low + torch.rand(64, 3, generator=gen) * (model64.config_high - model64.config_low)
    strided = torch.cat([anywhere, anywhere], -1)[:, :3]  # rows 6 floats apart: another layout, same values
    calls = [(anywhere, None), (anywhere, model64.motion_margin()), (strided, {"obstacle": 0.05}), (anywhere, None)]
    for i, (q, margin) in enumerate(calls):
        # the last call reuses the first one's compilation: it would raise if it compiled anew
        with torch.compiler.set_stance("fail_on_recompile" if i == len(calls) - 1 else "default"):
            flags, tcp = compiled.collision_flags(q, tasks.select("obstacle"), margin)
        ref_flags, ref_tcp = model64.collision_flags(q, tasks.select("obstacle"), margin)
        assert torch.equal(flags, ref_flags) and bool((flags != 0).any()) and bool((flags == 0).any())
        torch.testing.assert_close(tcp, ref_tcp)


def test_compiled_kernel_keeps_compiling_past_dynamo_s_default_limit(model64, monkeypatch):
    """Ten (size, margins) met: ten compilations, where dynamo's default limit of 8 would run the rest eagerly."""
    graphs = []

    def counting_backend(gm, example_inputs):  # compiles nothing: counts what dynamo hands the backend
        graphs.append(gm)
        return gm.forward

    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: compile_(fn, **{**kwargs, "backend": counting_backend}))
    compiled = UR5eReach(model64.robot, compile_collision=True)
    tasks = model64.sample_tasks(64, generator=torch.Generator().manual_seed(6))
    for i in range(10):
        margin = {"obstacle": 0.01 * i, "self": 0.001 * i}
        flags, tcp = compiled.collision_flags(tasks["joint_position"], tasks["obstacle"], margin)
        ref_flags, ref_tcp = model64.collision_flags(tasks["joint_position"], tasks["obstacle"], margin)
        assert torch.equal(flags, ref_flags)
        torch.testing.assert_close(tcp, ref_tcp)
    assert len(graphs) == 10


def test_a_ur5e_scene_of_several_boxes_is_tested_box_by_box():
    """Three boxes of sampled sizes: the generic test of every box, which must agree with the fused one-box
    kernel box by box (each box alone, the others far away) and flag the union of what each box flags."""
    boxes = [
        {"size": list(UR5eReach.OBSTACLE_SIZE), "center_low": list(UR5eReach.OBSTACLE_CENTER_LOW),
         "center_high": list(UR5eReach.OBSTACLE_CENTER_HIGH)},
        {"size_low": [0.05, 0.05, 0.05], "size_high": [0.15, 0.15, 0.25], "center_low": [0.1, -0.3, 0.0],
         "center_high": [0.8, 0.8, 0.0], "on_table": True},
        {"size_low": [0.05, 0.05, 0.05], "size_high": [0.15, 0.15, 0.25], "center_low": [0.1, -0.3, 0.0],
         "center_high": [0.8, 0.8, 0.0], "on_table": True},
    ]
    cluttered, one_box = UR5eReach(boxes=boxes), UR5eReach()
    gen = torch.Generator().manual_seed(0)
    tasks = cluttered.sample_tasks(500, gen)
    scene = tasks["obstacle"]
    assert scene.shape == (500, 18)
    sizes = scene[:, 6:].reshape(500, 2, 6)
    assert (sizes[..., 1::2] - sizes[..., 0::2]).std(0).min() > 0.01  # the extra boxes' sizes vary
    q = tasks["joint_position"] + 0.6 * torch.randn(500, 3, generator=gen)
    flags, tcp = cluttered.collision_flags(q, scene)
    union = torch.zeros_like(flags)
    for k in range(3):
        alone, tcp_alone = one_box.collision_flags(q, scene[:, 6 * k: 6 * k + 6])
        union |= alone
        assert torch.allclose(tcp, tcp_alone, atol=1e-6)
    assert torch.equal(flags, union)
    assert ((flags & CollisionReason.OBSTACLE) != 0).sum() > 50  # the test sees contacts, not only free space
    # the tasks' starts and goals touch no box
    for key in ("joint_position", "goal_joint_position"):
        start_flags, _ = cluttered.collision_flags(tasks[key], scene)
        assert not (start_flags & CollisionReason.OBSTACLE).any()
