"""The paper's pick-and-place pipeline (sec. 4.5, Fig. 8) on the MuJoCo twin, with a reaching policy doing the moves.

A trial: perceive the cube, the basket and the box (with noise); reach the pre-grasp pose
20 cm above the cube with the policy; go down until the fingertips are just above the cube,
grasp, go back up (straight vertical moves of the TCP, as the paper's scripted pick-up, whose
10 cm descent is for a gripper centre above the fingertips); carry the cube with the policy to
20 cm above the basket, past the box; release. The grasp is a weld: a MuJoCo equality
constraint that holds the cube just under the fingertips, switched on at the grasp (if the
fingertips ended within 2 cm of the grasp pose) and off at the release; there is no finger
model. Success means the cube rests inside the basket.
"""

from __future__ import annotations


import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp.sim.transfer import Perception
from torchrl_silp.sim.twin import MujocoTwin
from torchrl_silp.validation import check_positive_int

__all__ = ["PickPlaceTwin", "pick_place_tasks", "run_pick_place", "STAGES"]

STAGES = ("pre_grasp", "grasp", "carry", "place")
CUBE = 0.07  # the paper's cube (m)
BASKET = (0.15, 0.15, 0.10)  # the paper's basket (m): inner size, open at the top
WALL = 0.01
ABOVE = 0.20  # the pre-grasp and pre-place heights above the object's centre / the basket's floor (the paper: 20 cm)
GRIP = CUBE / 2 + 0.005  # the TCP (the fingertips' centre) above the cube's centre at the grasp


class PickPlaceTwin(MujocoTwin):
    """:class:`MujocoTwin` plus a free cube (0.07 m), an open basket (0.15 x 0.15 x 0.10 m) on the table and a
    weld from the gripper to the cube. The cube and the basket's walls count as obstacles of the arm (the gripper
    may touch the cube it grasps); the cube, once grasped, also counts as part of the arm against the box."""

    def _extend_spec(self, spec, mujoco) -> None:
        cube = spec.worldbody.add_body(name="cube", pos=[2.0, -2.0, CUBE / 2])
        cube.add_freejoint(name="cube_free")
        cube.add_geom(name="cube", type=mujoco.mjtGeom.mjGEOM_BOX, size=[CUBE / 2] * 3, mass=0.1, friction=[1, 0.05, 0.01])
        basket = spec.worldbody.add_body(name="basket", mocap=True, pos=[2.0, 2.5, 0.0])
        hx, hy, h = BASKET[0] / 2, BASKET[1] / 2, BASKET[2]
        walls = [([hx + WALL / 2, 0, h / 2], [WALL / 2, hy + WALL, h / 2]), ([-hx - WALL / 2, 0, h / 2], [WALL / 2, hy + WALL, h / 2]),
                 ([0, hy + WALL / 2, h / 2], [hx, WALL / 2, h / 2]), ([0, -hy - WALL / 2, h / 2], [hx, WALL / 2, h / 2])]
        for i, (pos, size) in enumerate(walls):
            basket.add_geom(name=f"basket{i}", type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos, size=size)
        spec.add_equality(type=mujoco.mjtEq.mjEQ_WELD, name1="tcp", name2="cube", objtype=mujoco.mjtObj.mjOBJ_BODY,
                          active=False, name="grasp")

    def _after_compile(self) -> None:
        m = self.mj_model
        self._cube = m.geom("cube").id
        self._basket = {m.geom(f"basket{i}").id for i in range(4)}
        self._basket_mocap = int(m.body("basket").mocapid[0])
        self._robot_geoms -= {self._cube} | self._basket
        self._cube_qadr = m.jnt_qposadr[m.joint("cube_free").id]
        self._cube_dadr = m.jnt_dofadr[m.joint("cube_free").id]
        self._grasp = m.equality("grasp").id
        self._gripper_bodies = {m.body("tool0").id, m.body("tcp").id}
        self.holding = np.zeros(self.n_envs, dtype=bool)
        # the weld's pose of the cube in the tcp frame (its z axis points along the tool, down)
        m.eq_data[self._grasp, :] = 0.0
        m.eq_data[self._grasp, 3:6] = [0.0, 0.0, GRIP]  # relpose: the cube's position in the tcp frame,
        m.eq_data[self._grasp, 6:10] = [1.0, 0.0, 0.0, 0.0]  # its orientation (unused: torque scale 0)

    def place_objects(self, cube: torch.Tensor, basket: torch.Tensor) -> None:
        """Set each world's cube centre ``[n_envs, 3]`` (at rest) and basket floor centre ``[n_envs, 3]``."""
        for i, d in enumerate(self.data):
            d.qpos[self._cube_qadr: self._cube_qadr + 3] = cube[i].double().numpy()
            d.qpos[self._cube_qadr + 3: self._cube_qadr + 7] = [1, 0, 0, 0]
            d.qvel[self._cube_dadr: self._cube_dadr + 6] = 0
            d.mocap_pos[self._basket_mocap] = basket[i].double().numpy()
            d.eq_active[self._grasp] = 0
            self.mujoco.mj_forward(self.mj_model, d)
        self.holding[:] = False

    def grasp(self, which: torch.Tensor) -> None:
        """Switch the weld on in these worlds: it holds the cube's centre at :data:`GRIP` below the TCP
        (just under the fingertips), free to turn (torque scale 0)."""
        for i in which.nonzero().squeeze(-1).tolist():
            self.data[i].eq_active[self._grasp] = 1
            self.holding[i] = True

    def release(self, which: torch.Tensor) -> None:
        for i in which.nonzero().squeeze(-1).tolist():
            self.data[i].eq_active[self._grasp] = 0
            self.holding[i] = False

    def cube(self) -> torch.Tensor:
        return torch.from_numpy(np.stack([d.qpos[self._cube_qadr: self._cube_qadr + 3].copy() for d in self.data]))

    def cube_speed(self) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.linalg.norm(d.qvel[self._cube_dadr: self._cube_dadr + 3]) for d in self.data]))

    def _colliding_world(self, i: int, d) -> bool:
        m = self.mj_model
        for c in d.contact[: d.ncon]:
            if c.dist > 0:
                continue
            g = {int(c.geom1), int(c.geom2)}
            arm = g & self._robot_geoms
            if arm:
                other = (g - arm) or g
                # the gripper touching the cube it grasps is the grasp, not a collision
                if other <= {self._cube} and {m.geom_bodyid[a] for a in arm} <= self._gripper_bodies:
                    continue
                return True
            if self.holding[i] and self._cube in g and g & self._boxes:
                return True  # the carried cube meets the box
        return False


def _ik(model, q0: torch.Tensor, target: torch.Tensor, iters: int = 50) -> torch.Tensor:
    """Configurations near ``q0`` whose TCP is at ``target`` (damped least squares on the model's FK)."""
    with torch.enable_grad():  # the FK's Jacobian, also when called under no_grad
        return _ik_steps(model, q0.detach().double().clone(), target.detach().double(), iters).to(q0.dtype)


def _ik_steps(model, q: torch.Tensor, target: torch.Tensor, iters: int) -> torch.Tensor:
    for _ in range(iters):
        q.requires_grad_(True)
        tcp = model.robot.fk(q)
        err = target - tcp
        J = torch.stack([torch.autograd.grad(tcp[:, k].sum(), q, retain_graph=k < 2)[0] for k in range(3)], 1)
        q = q.detach()
        JJt = J @ J.transpose(1, 2) + 1e-6 * torch.eye(3, dtype=q.dtype)
        q = q + (J.transpose(1, 2) @ torch.linalg.solve(JJt, err.detach().unsqueeze(-1))).squeeze(-1)
    return q


def pick_place_tasks(model, n: int, seed: int) -> TensorDict:
    """``n`` seeded trials: the arm's start, the box (the model's task distribution), the cube and the basket
    on the table in the workspace, clear of the box and of each other, with the pre-grasp and pre-place
    TCP poses reachable and collision-free (the model's checks), and the arm's start touching neither the
    cube nor the basket (the twin's contacts)."""
    check_positive_int(n, name="n")
    gen = torch.Generator().manual_seed(seed)
    low, high = torch.tensor(model.WORKSPACE_LOW), torch.tensor(model.WORKSPACE_HIGH)
    picked, total = [], 0
    for _ in range(100):
        draw = model.sample_tasks(4 * n, gen)
        m = len(draw)
        box = draw["obstacle"].view(m, 3, 2)
        xy = lambda: low[:2] + 0.1 + torch.rand(m, 2, generator=gen) * (high[:2] - low[:2] - 0.2)  # noqa: E731
        cube = torch.cat([xy(), torch.full((m, 1), CUBE / 2)], -1)
        basket = torch.cat([xy(), torch.zeros(m, 1)], -1)
        pre_grasp = cube + torch.tensor([0.0, 0.0, ABOVE])
        pre_place = basket + torch.tensor([0.0, 0.0, ABOVE + CUBE / 2])

        def clear_of_box(p, r):
            return ((p[:, :2] < box[:, :2, 0] - r) | (p[:, :2] > box[:, :2, 1] + r)).any(-1)

        ok = clear_of_box(cube, 0.15) & clear_of_box(basket, 0.2) & ((cube[:, :2] - basket[:, :2]).norm(dim=-1) > 0.3)
        ok &= (cube[:, :2].norm(dim=-1) > 0.3) & (basket[:, :2].norm(dim=-1) > 0.3)  # clear of the base
        q_pick = _ik(model, draw["joint_position"], pre_grasp)
        q_place = _ik(model, draw["joint_position"], pre_place)
        q_down = _ik(model, q_pick, cube + torch.tensor([0.0, 0.0, ABOVE - 0.1]))
        scene = draw.select("obstacle")
        for q, p in ((q_pick, pre_grasp), (q_place, pre_place), (q_down, cube + torch.tensor([0.0, 0.0, ABOVE - 0.1]))):
            ok &= (model.robot.fk(q.double()).float() - p).norm(dim=-1) < 1e-3
            ok &= ~model.collides(q, scene)
            ok &= ((q >= model.config_low) & (q <= model.config_high)).all(-1)
        ok &= ~model.collides(draw["joint_position"], scene)
        # the arm's start must not touch the cube or the basket either: MuJoCo's contacts, on the twin
        twin = PickPlaceTwin(model, n_envs=m)
        twin.reset(draw["joint_position"], draw["obstacle"])
        twin.place_objects(cube, basket)
        ok &= ~twin.colliding()
        keep = draw[ok]
        keep.set("cube", cube[ok])
        keep.set("basket", basket[ok])
        keep.set("pre_grasp", pre_grasp[ok])
        keep.set("pre_place", pre_place[ok])
        picked.append(keep)
        total += len(keep)
        if total >= n:
            break
    else:
        raise RuntimeError(f"could not draw {n} pick-and-place trials (got {total})")
    return torch.cat(picked)[:n]


def run_pick_place(policy, model, tasks: TensorDict, *, observation_transform=None,
                   perception: Perception = Perception(), control_dt: float = 0.1, max_steps: int = 50,
                   seed: int = 0, on_step=None) -> dict:
    """Run the pipeline on every trial in lockstep; returns per-trial bool tensors, one per stage in
    :data:`STAGES` (each requires the ones before it), and ``collision`` (a contact ended the trial).
    ``on_step(twin, k)``, if given, is called after each control step and scripted move."""
    if not isinstance(perception, Perception):
        raise TypeError(f"perception must be a Perception, got {type(perception).__name__}")
    n = len(tasks)
    twin = PickPlaceTwin(model, n_envs=n)
    substeps = max(1, round(control_dt / twin.mj_model.opt.timestep))
    build = model.observation_transform() if observation_transform is None else observation_transform
    gen = torch.Generator().manual_seed(seed)
    dtype = model.dtype
    twin.reset(tasks["joint_position"], tasks["obstacle"])
    twin.place_objects(tasks["cube"], tasks["basket"])
    noise = lambda shape: perception.obstacle_noise * torch.randn(shape, generator=gen, dtype=dtype)  # noqa: E731
    # perception: one noisy look at the cube, the basket and the box at the start
    cube_seen = tasks["cube"].to(dtype) + noise((n, 3))
    basket_seen = tasks["basket"].to(dtype) + noise((n, 3))
    box_seen = tasks["obstacle"].to(dtype) + noise((n, 3)).repeat_interleave(2, -1)
    scene = TensorDict({"obstacle": box_seen}, batch_size=[n])
    collision = torch.zeros(n, dtype=torch.bool)
    count = [0]

    def tick() -> None:
        count[0] += 1
        if on_step is not None:
            on_step(twin, count[0])

    def reach(goal: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        """The policy drives the TCP to ``goal``; True where it got within the model's success distance."""
        nonlocal collision
        done = torch.zeros(n, dtype=torch.bool)
        for _ in range(max_steps):
            active = alive & ~done & ~collision
            if not bool(active.any()):
                break
            q = twin.config().to(dtype)
            q = q + perception.joint_noise * torch.randn(q.shape, generator=gen, dtype=dtype)
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                action = policy(build(model.state_at(q, scene, goal)))["action"]
            target = model.next_config(q, action.to(dtype))
            for c in range(10):
                twin.set_targets(q + (c + 1) / 10 * (target - q))
                collision |= twin.step(substeps // 10, active) & active
            done |= ((twin.tcp().to(dtype) - goal).norm(dim=-1) <= model.success_distance) & active & ~collision
            tick()
        return done & ~collision

    def straight(goal: torch.Tensor, alive: torch.Tensor, steps: int = 10) -> None:
        """A scripted straight vertical move of the TCP to ``goal`` (joint targets from IK, in ``steps`` pieces)."""
        nonlocal collision
        q0 = twin.config().to(dtype)
        q1 = _ik(model, q0, goal)
        for k in range(steps):
            twin.set_targets(q0 + (k + 1) / steps * (q1 - q0))
            collision |= twin.step(substeps, alive & ~collision) & alive
            tick()
        collision |= twin.step(3 * substeps, alive & ~collision) & alive  # settle

    up = torch.tensor([0.0, 0.0, ABOVE], dtype=dtype)
    pre_grasp = reach(cube_seen + up, torch.ones(n, dtype=torch.bool))
    straight(cube_seen + torch.tensor([0.0, 0.0, GRIP], dtype=dtype), pre_grasp)
    # the gripper closes on the cube if its fingertips ended within 2 cm of their grasp pose
    grip_pose = twin.cube().to(dtype) + torch.tensor([0.0, 0.0, GRIP], dtype=dtype)
    close = (twin.tcp().to(dtype) - grip_pose).norm(dim=-1) <= 0.02
    grasping = pre_grasp & ~collision & close
    twin.grasp(grasping)
    straight(cube_seen + up, grasping)
    grasp = grasping & ~collision & (twin.cube()[:, 2].to(dtype) > CUBE / 2 + 0.05)
    carry = reach(basket_seen + up + torch.tensor([0.0, 0.0, CUBE / 2], dtype=dtype), grasp)
    twin.release(carry)
    for _ in range(5):  # 1 s for the cube to fall and settle
        collision |= twin.step(int(0.2 / twin.mj_model.opt.timestep), carry & ~collision) & carry
        tick()
    inside = ((twin.cube()[:, :2] - tasks["basket"][:, :2].double()).abs() < torch.tensor(BASKET[:2]).double() / 2).all(-1)
    resting = (twin.cube()[:, 2] < BASKET[2]) & (twin.cube_speed() < 0.05)
    place = carry & ~collision & inside & resting
    return {"pre_grasp": pre_grasp, "grasp": grasp, "carry": carry, "place": place, "collision": collision}
