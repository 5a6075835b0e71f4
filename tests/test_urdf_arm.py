"""Real robot descriptions (example-robot-data's, unedited) through URDFArm: loading, FK against
pytorch-kinematics, sphere covers against the meshes, self pairs, the exact-engine check, scenes of
several boxes, and the main job on a URDF given on the command line."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp.geometry import CollisionReason
from torchrl_silp.models import URDFReach, check_task_model
from torchrl_silp.robots import URDFArm, load_description
from torchrl_silp.robots.covers import cache_dir, cached_mesh_cover, mesh_sphere_cover
from torchrl_silp.robots.exact_check import exact_collision_check
from torchrl_silp.robots.self_collision import find_self_collision_pairs, link_collision_objects
from torchrl_silp.robots.urdf import _cmeel_shares, serial_chain

REPO = Path(__file__).resolve().parents[1]
SHARE = _cmeel_shares()[0]
ROBOTS = SHARE / "example-robot-data" / "robots"
UR10 = "package://example-robot-data/robots/ur_description/urdf/ur10_robot.urdf"
XARM7 = "package://example-robot-data/robots/xarm_description/urdf/xarm7.urdf"
UR_ARM = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]
XARM_JOINTS = [f"joint{i}" for i in range(1, 8)]

# every arm URDF of the ur, panda and xarm descriptions (but ur3.urdf, an empty <robot>: refused below), with
# the link its TCP rides on
ARM_FILES = sorted(p for d in ("ur", "panda", "xarm") for p in (ROBOTS / f"{d}_description" / "urdf").glob("*.urdf")
                   if p.name != "ur3.urdf")
TIP = {"ur": "tool0", "panda": "panda_hand", "xarm": "link_eef"}


@pytest.fixture(scope="module")
def ur10():
    return URDFArm(UR10, joints=UR_ARM, ee_link="tool0", dtype=torch.float64)


@pytest.fixture(scope="module")
def xarm7():
    return URDFArm(XARM7, joints=XARM_JOINTS, ee_link="link_eef", dtype=torch.float64)


def _random_q(arm, n, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return arm.joint_low + torch.rand(n, arm.config_dim, generator=gen, dtype=arm.dtype) * (arm.joint_high - arm.joint_low)


def _surface_gap(arm, q, points_per_element=3000):
    """The largest distance (m) from a point sampled on any collision element's surface to the cover."""
    rot, pos = arm.frames(q)  # (N, F, 3, 3), (N, F, 3)
    centres, _ = arm.spheres_and_tcp(q)  # (N, S, 3)
    worst = -np.inf
    for k, prim in enumerate(arm.primitives):
        pts = torch.as_tensor(prim.trimesh().sample(points_per_element, seed=k))
        f = arm.frame_names.index(prim.link)
        world = pts @ rot[:, f].transpose(-1, -2) + pos[:, f, None]  # (N, P, 3)
        gap = (torch.cdist(world, centres) - arm.sphere_radii).amin(-1)
        worst = max(worst, float(gap.max()))
    return worst


# ------------------------------------------------------------------ loading every description
def test_the_description_list_holds_the_arms():
    names = {p.name for p in ARM_FILES}
    assert {"ur10_robot.urdf", "ur5_robot.urdf", "ur3_robot.urdf", "panda.urdf", "xarm7.urdf"} <= names


@pytest.mark.parametrize("path", ARM_FILES, ids=lambda p: p.name)
def test_every_arm_description_loads_with_fk_equal_to_pytorch_kinematics(path):
    desc = load_description(path)
    tip = TIP[path.parent.parent.name.split("_")[0]]
    chain = serial_chain(desc.joints, desc.root, tip)
    joints = [j.name for j in chain if j.type in ("revolute",)]
    arm = URDFArm(path, joints=joints, ee_link=tip, self_collision_samples=500, dtype=torch.float64)
    assert arm.n_spheres >= len({p.link for p in desc.collisions if p.link in arm.frame_names})
    q = _random_q(arm, 64)
    err = (arm.fk(q) - arm.reference_fk(q)).norm(dim=-1).max().item()
    assert err < 1e-6  # pytorch-kinematics rounds origins to float32: ~3e-8 m
    assert _surface_gap(arm, q[:2], 500) <= 1e-9


def test_an_empty_robot_is_refused_naming_the_file():  # ur3.urdf: a <robot> with no name and no link
    empty = ROBOTS / "ur_description" / "urdf" / "ur3.urdf"
    with pytest.raises(ValueError, match=r"^urdf_path: .*ur3.urdf.* is not a URDF"):
        URDFArm(empty, joints=UR_ARM, ee_link="tool0")


# ------------------------------------------------------------------ the tree: transmissions, mimic, held joints
def test_transmissions_are_not_joints_and_the_panda_fingers_ride_on_the_hand():
    ur = load_description(ROBOTS / "ur_description" / "urdf" / "ur10_robot.urdf")
    assert len({j.name for j in ur.joints}) == len(ur.joints)  # the <transmission>'s <joint> is not read as one
    panda = URDFArm(ROBOTS / "panda_description" / "urdf" / "panda.urdf", joints=[f"panda_joint{i}" for i in range(1, 8)],
                    ee_link="panda_hand", held={"panda_finger_joint1": 0.03}, self_collision_samples=200,
                    dtype=torch.float64)
    finger2 = next(j for j in panda.description.joints if j.name == "panda_finger_joint2")
    assert finger2.mimic[0] == "panda_finger_joint1"
    q = _random_q(panda, 5)
    rot, pos = panda.frames(q)
    hand, left, right = (panda.frame_names.index(n) for n in ("panda_hand", "panda_leftfinger", "panda_rightfinger"))
    # both fingers open by the held 0.03 m (finger 2 through its <mimic>), along +-y of the hand, 0.0584 m below it
    local_left = (rot[:, hand].transpose(-1, -2) @ (pos[:, left] - pos[:, hand]).unsqueeze(-1)).squeeze(-1)
    local_right = (rot[:, hand].transpose(-1, -2) @ (pos[:, right] - pos[:, hand]).unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(local_left, torch.tensor([0.0, 0.03, 0.0584], dtype=torch.float64).expand(5, 3))
    torch.testing.assert_close(local_right, torch.tensor([0.0, -0.03, 0.0584], dtype=torch.float64).expand(5, 3))


def test_ee_offset_moves_the_tcp_in_the_link_frame(ur10):
    offset = URDFArm(UR10, joints=UR_ARM, ee_link="tool0", ee_offset=(0.0, 0.0, 0.15), dtype=torch.float64)
    q = _random_q(ur10, 16)
    rot, pos = ur10.tcp_pose(q)
    torch.testing.assert_close(offset.fk(q), pos + 0.15 * rot[..., :, 2])
    torch.testing.assert_close(offset.fk(q), offset.reference_fk(q), atol=1e-6, rtol=0)


@pytest.mark.parametrize("kwargs, key", [
    (dict(joints=["shoulder_pan_joint", "no_such_joint"], ee_link="tool0"), "joints"),
    (dict(joints=UR_ARM, ee_link="no_such_link"), "ee_link"),
    (dict(joints=UR_ARM, ee_link="tool0", root="nowhere"), "root"),
    (dict(joints=UR_ARM, ee_link="tool0", held={"nope": 1.0}), "held"),
    (dict(joints=UR_ARM, ee_link="tool0", ee_offset=(0, 0)), "ee_offset"),
])
def test_wrong_arguments_name_their_key(kwargs, key):
    with pytest.raises(ValueError, match=rf"^{key}"):
        URDFArm(UR10, **kwargs)


def test_a_mesh_that_cannot_be_found_names_package_dirs(tmp_path):
    # the UR10 description under a package name nothing on this machine holds
    moved = tmp_path / "ur10.urdf"
    text = (ROBOTS / "ur_description" / "urdf" / "ur10_robot.urdf").read_text()
    moved.write_text(text.replace("package://example-robot-data/", "package://my_cell/"))
    with pytest.raises(ValueError, match=r"^package_dirs: .*package://my_cell/.*base.stl"):
        URDFArm(moved, joints=UR_ARM, ee_link="tool0")
    by_name = URDFArm(moved, joints=UR_ARM, ee_link="tool0", package_dirs={"my_cell": SHARE / "example-robot-data"},
                      self_collision_samples=200)
    (tmp_path / "ws").mkdir()
    (tmp_path / "ws" / "my_cell").symlink_to(SHARE / "example-robot-data")
    in_folder = URDFArm(moved, joints=UR_ARM, ee_link="tool0", package_dirs=[tmp_path / "ws"], self_collision_samples=200)
    original = URDFArm(UR10, joints=UR_ARM, ee_link="tool0", self_collision_samples=200)
    torch.testing.assert_close(by_name.sphere_radii, original.sphere_radii)
    torch.testing.assert_close(in_folder.sphere_radii, original.sphere_radii)


# ------------------------------------------------------------------ covers
@settings(max_examples=15, deadline=None)
@given(kind=st.sampled_from(["box", "cylinder", "capsule", "icosphere"]), scale=st.tuples(*[st.floats(0.02, 0.4)] * 3),
       angles=st.tuples(*[st.floats(-3.2, 3.2)] * 3), max_spheres=st.integers(1, 8))
def test_a_fitted_cover_holds_every_point_of_the_surface(kind, scale, angles, max_spheres):
    mesh = {"box": lambda: trimesh.creation.box(extents=(1, 1, 1)),
            "cylinder": lambda: trimesh.creation.cylinder(radius=0.5, height=1.0, sections=24),
            "capsule": lambda: trimesh.creation.capsule(radius=0.3, height=1.0),
            "icosphere": lambda: trimesh.creation.icosphere(subdivisions=2)}[kind]()
    mesh.apply_scale(scale)
    mesh.apply_transform(trimesh.transformations.euler_matrix(*angles))
    centres, radii = mesh_sphere_cover(mesh, max_spheres=max_spheres, volume_ratio=2.5)
    assert 1 <= len(radii) <= max_spheres
    points = np.concatenate([mesh.sample(4000, seed=1), mesh.vertices])
    gap = (np.linalg.norm(points[:, None] - centres[None], axis=-1) - radii).min(1)
    assert gap.max() <= 1e-9


def test_the_real_links_are_inside_their_covers(ur10, xarm7):
    for arm in (ur10, xarm7):
        assert _surface_gap(arm, _random_q(arm, 3, seed=1)) <= 1e-9


def test_covers_are_cached_by_the_mesh_contents(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_SILP_CACHE", str(tmp_path))
    rod = trimesh.creation.cylinder(radius=0.05, height=0.5)
    first = cached_mesh_cover(rod)
    files = list(cache_dir().glob("*.npz"))
    assert len(files) == 1
    with np.load(files[0]) as saved:
        np.savez(files[0], centres=saved["centres"] + 1.0, radii=saved["radii"])  # a marked entry: is it read?
    again = cached_mesh_cover(rod)
    np.testing.assert_allclose(again[0], first[0] + 1.0)
    longer = trimesh.creation.cylinder(radius=0.05, height=0.6)
    cached_mesh_cover(longer)
    assert len(list(cache_dir().glob("*.npz"))) == 2


def test_the_cover_report_measures_volumes_independently():
    # one box link: its cover is the analytic box cover, its volume by the same Monte Carlo as a direct count
    arm = URDFArm(ROBOTS / "ur_description" / "urdf" / "ur10_robot.urdf", joints=UR_ARM, ee_link="tool0",
                  self_collision_samples=200)
    report = {r.link: r for r in arm.cover_report()}
    ee = report["ee_link"]
    assert ee.geometry_volume == pytest.approx(0.01**3, rel=0.05)
    # the box cover is one sphere through the corners: radius sqrt(3) * 0.005
    assert ee.cover_volume == pytest.approx(4 / 3 * np.pi * (np.sqrt(3) * 0.005) ** 3, rel=0.05)


# ------------------------------------------------------------------ self pairs
def test_self_pairs_are_sorted_by_exact_contacts(ur10):
    acm = ur10.self_collision_matrix
    all_pairs = {frozenset(p) for p in itertools.combinations(dict.fromkeys(ur10.sphere_link_names), 2)}
    sorted_pairs = [frozenset(p) for p in acm.kept] + [frozenset(p) for v in acm.dropped.values() for p in v]
    assert len(sorted_pairs) == len(all_pairs) and set(sorted_pairs) == all_pairs
    # the wrist is held: its links ride on the forearm's body
    assert ("wrist_1_link", "wrist_2_link") in acm.dropped["rigid"]
    assert ("base_link", "shoulder_link") in acm.dropped["adjacent"]
    # the covers of the base and the upper arm overlap often, their meshes never: dropped, not checked
    assert ("base_link", "upper_arm_link") in acm.dropped["never"]
    q = _random_q(ur10, 2000, seed=5)
    centres, _ = ur10.spheres_and_tcp(q)
    names = np.asarray(ur10.sphere_link_names)
    ia, ib = np.flatnonzero(names == "base_link"), np.flatnonzero(names == "upper_arm_link")
    overlap = (torch.cdist(centres[:, ia], centres[:, ib]) < ur10.sphere_radii[ia, None] + ur10.sphere_radii[None, ib])
    assert overlap.flatten(1).any(-1).float().mean() > 0.3
    # a kept pair touches in some sampled configurations and not in most: the fractions say so
    assert all(0 < acm.contact_fraction[p] < 0.95 for p in acm.kept)


def test_kept_pairs_collide_in_fcl_where_the_self_test_says(xarm7):
    import fcl

    objects = link_collision_objects(xarm7)
    q = _random_q(xarm7, 400, seed=3)
    rot, pos = xarm7.frames(q)
    centres, _ = xarm7.spheres_and_tcp(q)
    flagged = xarm7.self_collision(centres)
    index = {n: i for i, n in enumerate(xarm7.frame_names)}
    exact = torch.zeros(400, dtype=torch.bool)
    for n in range(400):
        for link in objects:
            objects[link].setTransform(fcl.Transform(rot[n, index[link]].numpy(), pos[n, index[link]].numpy()))
        exact[n] = any(fcl.collide(objects[a], objects[b], fcl.CollisionRequest(), fcl.CollisionResult()) > 0
                       for a, b in xarm7.self_collision_matrix.kept)
    assert exact.sum() > 5
    assert not (exact & ~flagged).any()


def test_given_self_pairs_replace_the_found_ones():
    arm = URDFArm(UR10, joints=UR_ARM, ee_link="tool0", self_collision_pairs=[("base_link", "forearm_link")])
    assert arm.self_collision_matrix is None
    names = arm.sphere_link_names
    assert {(names[a], names[b]) for a, b in zip(arm.self_pair_a.tolist(), arm.self_pair_b.tolist())} == {
        ("base_link", "forearm_link")}


def test_found_pairs_on_a_small_sample_are_reproducible(ur10):
    a = find_self_collision_pairs(ur10, samples=300, seed=1)
    b = find_self_collision_pairs(ur10, samples=300, seed=1)
    assert a.kept == b.kept and a.dropped == b.dropped


# ------------------------------------------------------------------ exact engine
@pytest.mark.parametrize("which", ["ur10", "xarm7"])
def test_the_cover_misses_no_contact_of_the_exact_engine(which, ur10, xarm7):
    arm = {"ur10": ur10, "xarm7": xarm7}[which]
    report = exact_collision_check(arm, configs=300, boxes_per_config=4, seed=11)
    assert report["box"]["contacts"] > 300 and report["self"]["contacts"] > 5
    assert report["box"]["missed"] == 0 and report["self"]["missed"] == 0


def test_the_committed_full_scale_check_found_no_missed_contact():
    for robot in ("ur10", "xarm7"):
        result = json.loads((REPO / "results" / "robots" / f"{robot}.json").read_text())
        assert result["exact"]["configs"] >= 10_000
        assert result["exact"]["box"]["missed"] == 0 and result["exact"]["self"]["missed"] == 0


# ------------------------------------------------------------------ scenes of several boxes
@pytest.fixture(scope="module")
def xarm_task(xarm7):
    boxes = [dict(size_low=(0.1, 0.1, 0.15), size_high=(0.25, 0.25, 0.35), center_low=(0.3, -0.25, 0.0),
                  center_high=(0.6, 0.25, 0.0), on_table=True),
             dict(size_low=(0.05, 0.05, 0.05), size_high=(0.15, 0.15, 0.2), center_low=(0.2, -0.5, 0.0),
                  center_high=(0.7, 0.5, 0.0), on_table=True),
             dict(size=(0.1, 0.2, 0.05), center_low=(0.2, -0.5, 0.4), center_high=(0.7, 0.5, 0.6))]
    return URDFReach(
        xarm7.to(torch.float32), workspace_low=(0.1, -0.5, 0.0), workspace_high=(0.75, 0.5, 0.7), boxes=boxes,
        task_joint_low=(-1.5708, -1.0, -1.5708, 0.2, -1.5708, -1.0, -1.5708),
        task_joint_high=(1.5708, 1.5, 1.5708, 2.9, 1.5708, 1.6, 1.5708), motion_resolution=0.005)


def test_several_boxes_of_sampled_sizes_keep_the_task_rules(xarm_task):
    tasks = xarm_task.sample_tasks(64, torch.Generator().manual_seed(0))
    boxes = tasks["obstacle"].reshape(64, 3, 6)
    size = boxes[..., 1::2] - boxes[..., 0::2]
    centre = (boxes[..., 1::2] + boxes[..., 0::2]) / 2
    for k, spec in enumerate(xarm_task.boxes):
        assert (size[:, k] >= torch.tensor(spec["size_low"]) - 1e-6).all()
        assert (size[:, k] <= torch.tensor(spec["size_high"]) + 1e-6).all()
        assert (centre[:, k, :2] >= torch.tensor(spec["center_low"][:2]) - 1e-6).all()
        assert (centre[:, k, :2] <= torch.tensor(spec["center_high"][:2]) + 1e-6).all()
    torch.testing.assert_close(boxes[:, :2, 4], torch.zeros(64, 2))  # on_table: the boxes stand on z = 0
    assert (boxes[:, 2, 4] > 0.3).all()  # the third floats where its region says
    assert size[:, 0].std(0).min() > 0.01  # sizes are drawn, not fixed
    first = centre[:, 0]
    d1 = (tasks["achieved_goal"] - first).norm(dim=-1)
    d2 = (tasks["achieved_goal"] - tasks["desired_goal"]).norm(dim=-1)
    d3 = (first - tasks["desired_goal"]).norm(dim=-1)
    assert ((d2 > d1) & (d1 > d3)).all()
    for key in ("joint_position", "goal_joint_position"):
        flags, _ = xarm_task.collision_flags(tasks[key], tasks["obstacle"])
        assert (flags == 0).all()


def test_each_box_of_the_scene_counts_in_the_collision_test(xarm_task):
    tasks = xarm_task.sample_tasks(8, torch.Generator().manual_seed(1))
    q = tasks["joint_position"]
    _, tcp = xarm_task.robot.spheres_and_tcp(q)
    for k in range(3):  # a box moved onto the TCP collides, whichever slot it fills
        boxes = tasks["obstacle"].clone().reshape(8, 3, 6)
        boxes[:, k, 0::2], boxes[:, k, 1::2] = tcp - 0.02, tcp + 0.02
        flags, _ = xarm_task.collision_flags(q, boxes.reshape(8, 18))
        assert (flags.squeeze(-1) & CollisionReason.OBSTACLE).all()


def test_check_task_model_passes_on_urdf_tasks(xarm_task):
    check_task_model(xarm_task)
    check_task_model(URDFReach(dict(urdf_path=UR10, joints=UR_ARM, ee_link="tool0", self_collision_samples=1000)))




# ------------------------------------------------------------------ the main job on a URDF, no file changed
def test_the_main_job_trains_on_a_urdf_given_on_the_command_line(tmp_path):
    run = tmp_path / "run"
    command = [sys.executable, str(REPO / "recipes" / "sac_silp.py"), "env=urdf_reach",
               f"env.robot.urdf_path={ROBOTS / 'ur_description' / 'urdf' / 'ur10_robot.urdf'}",
               f"env.robot.joints=[{','.join(UR_ARM)}]", "env.robot.ee_link=tool0", "env.robot.self_collision_samples=2000",
               "env.num_envs=8", "collector.frames_per_batch=200", "collector.total_frames=400",
               "collector.init_random_frames=200", "eval.n_tasks=8", "eval.every_frames=200", "progress=false",
               "compile.compile=false", "threads=1", f"run_dir={run}"]
    before = subprocess.run(["git", "status", "--porcelain"], cwd=REPO, capture_output=True, text=True).stdout
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env"] == "urdf_reach" and summary["frames"] == 400
    assert (run / "test_rollouts.png").stat().st_size > 10_000
    assert subprocess.run(["git", "status", "--porcelain"], cwd=REPO, capture_output=True, text=True).stdout == before


@pytest.mark.parametrize("override, key", [
    ("env.robot.joints=[shoulder_pan_joint,elbow_joint,no_such_joint]", "env.robot.joints"),
    ("env.robot.ee_link=no_such_link", "env.robot.ee_link"),
    ("env.model.boxes=[{size:[0.1,0.1]}]", "env.model.boxes"),
    ("env.robot.colour=red", "env.robot.colour"),
])
def test_wrong_urdf_settings_are_refused_naming_the_key_before_anything_is_written(tiny_config, tmp_path, override, key):
    from torchrl_silp.recipes.schema import ConfigError
    from torchrl_silp.recipes.sac_silp import train

    cfg = tiny_config("env=urdf_reach", f"env.robot.urdf_path={UR10}", f"env.robot.joints=[{','.join(UR_ARM)}]",
                      "env.robot.ee_link=tool0", override)
    with pytest.raises(ConfigError, match=rf"^{key.replace('.', '[.]')}") as err:
        train(cfg)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run").exists()


def test_a_file_that_is_not_a_urdf_is_refused(tiny_config, tmp_path):
    from torchrl_silp.recipes.schema import ConfigError
    from torchrl_silp.recipes.sac_silp import train

    text = tmp_path / "notes.urdf"
    text.write_text("this is not xml")
    cfg = tiny_config("env=urdf_reach", f"env.robot.urdf_path={text}", "env.robot.joints=[a]", "env.robot.ee_link=b")
    with pytest.raises(ConfigError, match=r"^env[.]robot[.]urdf_path: .*is not a URDF"):
        train(cfg)
    assert not (tmp_path / "run").exists()


# the figures the UR5e and Panda tasks gave before their robots became URDFArms (computed with the
# hand-written parser's code, commit b3ef949): the same tasks, collision flags and Lipschitz bounds
BEFORE_URDF_ARM = {
    "UR5eReach": ([402.709084386006, 436.67798634432256, -14.465706331189722, -118.82028849981725, 875.5546322390437],
                  187510, 160, 2.7021512389183044),
    "PandaReach": ([400.48407595884055, 384.6082300134003, 395.7510215640068, 304.0316360592842, 642.1776847466826],
                   148545, 800, 4.2017874121665955),
}


@pytest.mark.parametrize("name", sorted(BEFORE_URDF_ARM))
def test_the_paper_task_and_the_panda_task_are_those_of_before(name):
    from torchrl_silp import models

    m = getattr(models, name)()
    g = torch.Generator().manual_seed(0)
    tasks = m.sample_tasks(500, g)
    q = m.config_low + torch.rand(20000, m.config_dim, generator=g) * (m.config_high - m.config_low)
    flags, _ = m.collision_flags(q, tasks["obstacle"][:1].expand(20000, -1))
    sums, n_flags, n_pairs, lipschitz = BEFORE_URDF_ARM[name]
    assert [float(tasks[k].double().sum()) for k in sorted(tasks.keys())] == pytest.approx(sums, rel=1e-6)
    assert int(flags.long().sum()) == n_flags
    assert m.robot.self_pair_a.numel() == n_pairs
    assert m.lipschitz()["obstacle"] == pytest.approx(lipschitz, rel=1e-6)


def test_found_pairs_are_moveits_for_the_xarm7(xarm7):
    # MoveIt's setup assistant's allowed-collision matrix, shipped with the description: the same reason per pair
    from torchrl_silp.recipes.robot_check import moveit_agreement

    agreement = moveit_agreement(xarm7, "package://example-robot-data/robots/xarm_description/srdf/xarm7.srdf")
    assert agreement["pairs"] == 28 and agreement["differ"] == []


def test_fcl_and_coal_agree_on_the_ur10s_meshes(ur10):
    # the exact engine of the checks (python-fcl) against a second one (coal), on the same meshes and boxes
    import coal
    import fcl

    objects = link_collision_objects(ur10)
    models = {}
    for link in objects:
        meshes = [p.trimesh() for p in ur10.primitives if p.link == link]
        mesh = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        bvh = coal.BVHModelOBBRSS()
        bvh.beginModel(len(mesh.faces), len(mesh.vertices))
        bvh.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
        bvh.addTriangles(np.asarray(mesh.faces, dtype=np.int32))
        bvh.endModel()
        models[link] = bvh
    rng = np.random.default_rng(4)
    q = _random_q(ur10, 100, seed=4)
    rot, pos = ur10.frames(q)
    index = {n: i for i, n in enumerate(ur10.frame_names)}
    verdicts = []
    for n in range(100):
        centre = pos[n, index["forearm_link"]].numpy() + rng.uniform(-0.3, 0.3, 3)
        size = rng.uniform(0.05, 0.3, 3)
        for link in objects:
            r, p = rot[n, index[link]].numpy(), pos[n, index[link]].numpy()
            objects[link].setTransform(fcl.Transform(r, p))
            by_fcl = fcl.collide(objects[link], fcl.CollisionObject(fcl.Box(*size), fcl.Transform(centre)),
                                 fcl.CollisionRequest(), fcl.CollisionResult()) > 0
            by_coal = coal.collide(models[link], coal.Transform3s(r, p), coal.Box(*size),
                                   coal.Transform3s(np.eye(3), centre), coal.CollisionRequest(), coal.CollisionResult()) > 0
            verdicts.append((by_fcl, by_coal))
    verdicts = np.array(verdicts)
    assert verdicts[:, 0].sum() > 20
    assert (verdicts[:, 0] != verdicts[:, 1]).sum() <= 1  # a box grazing a mesh may go either way
