"""A physics twin of an arm reach task in MuJoCo: the task model's URDF, position servos, the table and the box.

The twin is what a trained policy meets outside the kinematic env: the arm is a
dynamic system that follows joint targets through position servos (so it lags
and overshoots), and success and collisions are what MuJoCo's contacts and its
TCP say, not what the task model predicts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchrl_silp.validation import check_float, check_positive_float, check_positive_int

__all__ = ["MujocoTwin", "ServoGains", "mujoco_labels"]


@dataclass(frozen=True)
class ServoGains:
    """Position servo of each joint: torque ``kp (target - q) - kv dq`` (N m/rad, N m s/rad), and the
    joint's ``armature`` (the gearbox's reflected rotor inertia, kg m^2).

    With the defaults each joint follows a step of its target with a time constant of about
    kv / kp = 30 ms, overdamped: a step of one action unit (0.125 rad) is within 2 % after
    about a control period of 0.1 s, and the arm lags its targets while it moves.
    """

    kp: float = 5000.0
    kv: float = 150.0
    armature: float = 0.1

    def __post_init__(self):
        for name in ("kp", "kv", "armature"):
            check_positive_float(getattr(self, name), name=name)


class MujocoTwin:
    """The MuJoCo model of a reach task's arm, table and box(es), with ``n_envs`` independent worlds.

    Built from the task model's own URDF (``model.robot.urdf_path``, its collision
    primitives; MuJoCo infers each link's mass and inertia from them at the
    density of water, and every arm body is gravity-compensated, as the arm's
    controller does), with a position servo and a joint-position sensor on each
    joint, a table plane at z = 0 (the base rests on it; that contact is
    excluded) and each obstacle box as a mocap body, which a scenario can move.

    A collision is any contact between an arm link and the table, a box, or a
    link that is not its parent or child (MuJoCo's own filter). The TCP is a site
    at the URDF's ``tcp`` frame.

    Args:
        model: the task model (an :class:`~torchrl_silp.models.ArmReach`, e.g.
            :class:`~torchrl_silp.models.UR5eReach`); its robot gives the URDF and the
            map from the task's configuration to all joints (``full_joints``).
        n_envs: independent worlds (one ``MjData`` each), stepped in lockstep.
        timestep: MuJoCo's integration step (s).
        gains: the servos' :class:`ServoGains`.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> twin = MujocoTwin(model, n_envs=2)
        >>> q = torch.tensor([[0.0, -1.2, 1.5], [0.3, -1.0, 1.2]])
        >>> twin.reset(q, model.sample_tasks(2, torch.Generator().manual_seed(0))["obstacle"])
        >>> bool(torch.allclose(twin.tcp(), model.robot.fk(q.double()).float(), atol=1e-5))
        True
    """

    def __init__(self, model, n_envs: int = 1, *, timestep: float = 0.002, gains: ServoGains = ServoGains()):
        import mujoco

        check_positive_int(n_envs, name="n_envs")
        check_float(timestep, name="timestep", low=0, low_open=True, high=0.01, unit="seconds")
        if not isinstance(gains, ServoGains):
            raise TypeError(f"gains must be a ServoGains, got {type(gains).__name__}")
        robot = getattr(model, "robot", None)
        if robot is None or not hasattr(robot, "urdf_path"):
            raise TypeError("model must be an arm task model whose robot has a urdf_path (e.g. UR5eReach)")
        self.mujoco = mujoco
        self.task_model = model
        self.robot = robot
        self.gains = gains
        boxes = getattr(model, "boxes", None)
        if not boxes or any(b["size_low"] != b["size_high"] or b["size_low"] != boxes[0]["size_low"] for b in boxes):
            raise TypeError("model must be an ArmReach whose boxes all have one fixed size (the twin's boxes are "
                            "built once, at that size)")
        box_size = boxes[0]["size_low"]
        self.box_half = np.asarray(box_size, dtype=float) / 2
        self.num_boxes = int(getattr(model, "num_boxes", 1))

        spec = mujoco.MjSpec.from_file(robot.urdf_path)
        spec.compiler.fusestatic = False  # keep the tcp frame as a body
        spec.option.timestep = timestep
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST  # stiff servos on light wrist links
        spec.option.gravity = [0.0, 0.0, -9.81]
        arm_bodies = [b for b in spec.bodies if b.name not in ("world", "")]
        for body in arm_bodies:
            body.gravcomp = 1.0
        self.joint_names = [j.name for j in spec.joints]
        for joint in spec.joints:
            joint.armature = gains.armature
        for name in self.joint_names:
            actuator = spec.add_actuator(name=f"servo_{name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            actuator.set_to_position(kp=gains.kp, kv=gains.kv)
            spec.add_sensor(name=f"q_{name}", type=mujoco.mjtSensor.mjSENS_JOINTPOS, objtype=mujoco.mjtObj.mjOBJ_JOINT,
                            objname=name)
        tcp_body = spec.body("tcp")
        if tcp_body is None:
            raise ValueError(f"urdf_path: {robot.urdf_path!r} has no 'tcp' link")
        tcp_body.add_site(name="tcp")
        spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3.0, 3.0, 0.1],
                                rgba=[0.85, 0.85, 0.8, 1.0])
        spec.worldbody.add_light(pos=[0.4, 0.2, 2.5], dir=[0.0, 0.0, -1.0], diffuse=[0.7, 0.7, 0.7])  # for pictures
        for k in range(self.num_boxes):
            box = spec.worldbody.add_body(name=f"box{k}", mocap=True, pos=[2.0 + k, 2.0, -1.0])
            box.add_geom(name=f"box{k}", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(self.box_half),
                         rgba=[0.8, 0.55, 0.3, 1.0])  # cardboard
        base = arm_bodies[0].name
        spec.add_exclude(bodyname1="world", bodyname2=base)  # the base stands on the table
        # self-collision: only the link pairs the task model tests (the UR5e's gripper against the base,
        # shoulder and upper arm); the housings of other links overlap by construction
        self.self_collision_links = self._self_collision_links(model)
        with_geoms = [b.name for b in arm_bodies if b.geoms]
        for i, a in enumerate(with_geoms):
            for b in with_geoms[i + 1:]:
                if frozenset((a, b)) not in self.self_collision_links:
                    spec.add_exclude(bodyname1=a, bodyname2=b)
        self._extend_spec(spec, mujoco)
        self.mj_model = spec.compile()
        self.data = [mujoco.MjData(self.mj_model) for _ in range(n_envs)]
        m = self.mj_model
        self.n_envs = n_envs
        self._tcp_site = m.site("tcp").id
        self._table = m.geom("table").id
        self._boxes = {m.geom(f"box{k}").id for k in range(self.num_boxes)}
        self._box_mocap = [int(m.body(f"box{k}").mocapid[0]) for k in range(self.num_boxes)]
        self._robot_geoms = {g for g in range(m.ngeom) if g != self._table and g not in self._boxes}
        self._robot_bodies = {m.geom_bodyid[g] for g in self._robot_geoms}
        self._qadr = np.asarray([m.jnt_qposadr[m.joint(n).id] for n in self.joint_names])
        self._sensor_adr = np.asarray([m.sensor_adr[m.sensor(f"q_{n}").id] for n in self.joint_names])
        self._after_compile()

    def _extend_spec(self, spec, mujoco) -> None:
        """Add bodies to the spec before it compiles (a subclass's objects); nothing here."""

    def _after_compile(self) -> None:
        """Read what a subclass added from the compiled model; nothing here."""

    @staticmethod
    def _self_collision_links(model) -> set[frozenset]:
        names = getattr(model.robot, "sphere_link_names", None)
        if names is None:
            return set()
        a, b = model.self_pairs()
        return {frozenset((names[i], names[j])) for i, j in zip(a.tolist(), b.tolist()) if names[i] != names[j]}

    # ------------------------------------------------------------------ state
    def full_joints(self, config: torch.Tensor) -> torch.Tensor:
        """All joint angles for the task's configuration (the robot's own map; identity if it has none)."""
        full = getattr(self.robot, "full_joints", None)
        return full(config) if full is not None else config

    def reset(self, config: torch.Tensor, obstacle: torch.Tensor) -> None:
        """Place each world's arm at rest at ``config`` (``[n_envs, D]``, with its servo targets
        there) and its boxes at ``obstacle`` (``[n_envs, 6 * num_boxes]``, bounds as the task model's)."""
        config, obstacle = self._batch("config", config), self._batch("obstacle", obstacle)
        q = self.full_joints(config.double()).cpu().numpy()
        for i, d in enumerate(self.data):
            self.mujoco.mj_resetData(self.mj_model, d)
            d.qpos[self._qadr] = q[i]
            d.ctrl[:] = q[i]
        self.set_obstacle(obstacle)
        for d in self.data:
            self.mujoco.mj_forward(self.mj_model, d)

    def set_obstacle(self, obstacle: torch.Tensor) -> None:
        """Move the boxes to ``obstacle`` bounds ``[n_envs, 6 * num_boxes]`` (their size is the model's)."""
        bounds = self._batch("obstacle", obstacle).double().cpu().numpy().reshape(self.n_envs, self.num_boxes, 3, 2)
        size = bounds[..., 1] - bounds[..., 0]
        if not np.allclose(size, 2 * self.box_half, atol=1e-5):
            raise ValueError(f"obstacle: the twin's boxes have size {tuple(2 * self.box_half)}, got {size.reshape(-1, 3)[0]}")
        centre = bounds.mean(-1)
        for i, d in enumerate(self.data):
            d.mocap_pos[self._box_mocap] = centre[i]

    def obstacle_centres(self) -> torch.Tensor:
        """The boxes' centres in MuJoCo ``[n_envs, num_boxes, 3]`` (float64)."""
        return torch.from_numpy(np.stack([d.mocap_pos[self._box_mocap].copy() for d in self.data]))

    def joint_positions(self) -> torch.Tensor:
        """The joint encoders (MuJoCo's joint-position sensors) ``[n_envs, joints]``, float64."""
        return torch.from_numpy(np.stack([d.sensordata[self._sensor_adr] for d in self.data]))

    def config(self) -> torch.Tensor:
        """The task's configuration read from the encoders: the task model's joints ``[n_envs, D]``."""
        return self.joint_positions()[:, : self.task_model.config_dim]

    def tcp(self) -> torch.Tensor:
        """MuJoCo's TCP position ``[n_envs, 3]`` (float32, the task model's dtype)."""
        return torch.from_numpy(np.stack([d.site_xpos[self._tcp_site].copy() for d in self.data])).float()

    def set_targets(self, config: torch.Tensor) -> None:
        """The servos' targets: the joints of ``config`` ``[n_envs, D]`` (the fixed joints keep the robot's map)."""
        q = self.full_joints(self._batch("config", config).double()).cpu().numpy()
        for i, d in enumerate(self.data):
            d.ctrl[:] = q[i]

    # ----------------------------------------------------------------- physics
    def step(self, substeps: int, active: torch.Tensor | None = None) -> torch.Tensor:
        """Integrate ``substeps`` MuJoCo steps in every (``active``) world; bool ``[n_envs]``: a collision
        contact occurred during them."""
        collided = np.zeros(self.n_envs, dtype=bool)
        mask = np.ones(self.n_envs, dtype=bool) if active is None else active.cpu().numpy().astype(bool)
        for i, d in enumerate(self.data):
            if not mask[i]:
                continue
            for _ in range(substeps):
                self.mujoco.mj_step(self.mj_model, d)
                if d.ncon and self._colliding_world(i, d):
                    collided[i] = True
        return torch.from_numpy(collided)

    def colliding(self) -> torch.Tensor:
        """bool ``[n_envs]``: a collision contact now (after :meth:`reset` or :meth:`step`)."""
        return torch.tensor([bool(d.ncon) and self._colliding(d) for d in self.data])

    def _colliding_world(self, i: int, d) -> bool:
        return self._colliding(d)

    def _colliding(self, d) -> bool:
        for c in d.contact[: d.ncon]:
            if c.dist > 0:  # within the margin only: not touching
                continue
            g1, g2 = int(c.geom1), int(c.geom2)
            if g1 in self._robot_geoms or g2 in self._robot_geoms:
                return True
        return False

    def _batch(self, name: str, x: torch.Tensor) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if x.dim() != 2 or x.shape[0] != self.n_envs:
            raise ValueError(f"{name} must have shape [n_envs={self.n_envs}, ...], got {tuple(x.shape)}")
        return x


def mujoco_labels(model, config: torch.Tensor, scene, batch: int = 4096) -> torch.Tensor:
    """Whether MuJoCo finds a collision contact at each configuration in its scene: bool ``config.shape[:-1]``.

    The labeller of :func:`~torchrl_silp.models.learned_collision.collision_dataset` by the twin's own
    primitives (the URDF's cylinders and boxes, not the task model's sphere cover, and no workspace bound).
    """
    flat = config.reshape(-1, config.shape[-1])
    obstacle = scene["obstacle"].reshape(len(flat), -1)
    twin = MujocoTwin(model, n_envs=min(batch, len(flat)))
    out = torch.zeros(len(flat), dtype=torch.bool)
    for lo in range(0, len(flat), twin.n_envs):
        q, box = flat[lo: lo + twin.n_envs], obstacle[lo: lo + twin.n_envs]
        pad = twin.n_envs - len(q)
        if pad:  # the last batch: repeat its first row to the twin's size
            q, box = torch.cat([q, q[:1].expand(pad, -1)]), torch.cat([box, box[:1].expand(pad, -1)])
        twin.reset(q, box)
        out[lo: lo + twin.n_envs - pad] = twin.colliding()[: twin.n_envs - pad]
    return out.reshape(config.shape[:-1])
