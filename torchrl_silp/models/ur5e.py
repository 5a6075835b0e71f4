"""The UR5e reach task of the SILP+ paper (sec. 3.1, 4.1) as a task model."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_silp.geometry import CollisionReason, aabb_from_center, in_box
from torchrl_silp.models.base import TaskModel, _check_tensor
from torchrl_silp.robot import UR5e

__all__ = ["UR5eReach", "TASK_BRANCHES", "WORKSPACE_EXIT_MODES"]

WORKSPACE_EXIT_MODES = ("collision", "block")
TASK_BRANCHES = ("front", "any")
# Sampled Lipschitz maxima are scaled by this: the sampled maximum of a smooth
# function over the joint box sits within a few percent of its supremum.
_SAFETY = 1.25
_LIPSCHITZ: dict = {}


class UR5eReach(TaskModel):
    """Reach a goal with a UR5e around a box: the paper's task as a :class:`TaskModel`.

    Three active joints (shoulder_pan, shoulder_lift, elbow; the wrist keeps
    the gripper pointing down); one action unit is 0.125 rad per joint. The
    achieved goal is the TCP position; the scene is one axis-aligned box
    ``"obstacle"`` ``(xmin, xmax, ymin, ymax, zmin, zmax)``.

    A configuration collides when a collision sphere of the arm or gripper
    meets the box, reaches below the table (the base may rest on it), the
    gripper meets the base, shoulder or upper arm, or the TCP leaves the
    workspace (bits of :class:`~torchrl_silp.geometry.CollisionReason`).

    Args:
        robot: a :class:`~torchrl_silp.robot.UR5e` to share; built from the packaged URDF by default.
        success_distance: reach accuracy in metres (paper: 0.05).
        motion_resolution, conservative: the swept check of a motion (see :class:`TaskModel`).
        workspace_exit: ``"collision"`` (a step taking the TCP out of the workspace is a
            collision) or ``"block"`` (such a step is not taken: the configuration stays).
        task_branch: ``"front"`` (start and goal with the TCP in front of the shoulder, one
            inverse-kinematics branch) or ``"any"`` (the whole task joint box, which also holds
            the shoulder-flipped branch).
        compile_collision: ``torch.compile`` the collision kernel (FK, spheres, checks).
        device, dtype: of the model's tensors.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> tasks = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> nxt, reward, collision, success, flags = model.step(tasks, torch.zeros(4, 3))
        >>> bool((nxt["joint_position"] == tasks["joint_position"]).all()), reward.shape
        (True, torch.Size([4, 1]))
    """

    config_dim = 3
    goal_dim = 3
    scene_shapes = {"obstacle": (6,)}
    collision_reasons = ("obstacle", "table", "self", "workspace")
    action_scale = 0.125  # rad per action unit
    WORKSPACE_LOW = (0.0, -0.3, 0.0)
    WORKSPACE_HIGH = (0.8, 0.8, 0.6)
    OBSTACLE_SIZE = (0.2, 0.2, 0.3)
    OBSTACLE_CENTER_LOW = (0.3, 0.1, 0.15)
    OBSTACLE_CENTER_HIGH = (0.7, 0.4, 0.15)
    # Joint box of start and goal configurations (then rejected unless collision-free,
    # in the workspace and d2 > d1 > d3): the arm stays "elbow up". With a lift below
    # -pi/2 it also holds the shoulder-flipped branch, which task_branch="front" rejects.
    TASK_JOINT_LOW = (-math.pi / 2, -math.pi, 0.0)
    TASK_JOINT_HIGH = (math.pi, 0.0, math.pi)

    def __init__(
        self,
        robot: UR5e | None = None,
        *,
        success_distance: float = 0.05,
        motion_resolution: float = 0.01,
        conservative: bool = True,
        workspace_exit: str = "collision",
        task_branch: str = "front",
        compile_collision: bool = False,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__(
            success_distance=success_distance, motion_resolution=motion_resolution,
            conservative=conservative, device=device, dtype=dtype,
        )
        if workspace_exit not in WORKSPACE_EXIT_MODES:
            raise ValueError(f"workspace_exit must be one of {WORKSPACE_EXIT_MODES}, got {workspace_exit!r}")
        if task_branch not in TASK_BRANCHES:
            raise ValueError(f"task_branch must be one of {TASK_BRANCHES}, got {task_branch!r}")
        if not isinstance(compile_collision, bool):
            raise TypeError(f"compile_collision must be a bool, got {compile_collision!r}")
        if robot is None:
            robot = UR5e(device=self.device, dtype=dtype)
        elif not isinstance(robot, UR5e):
            raise TypeError(f"robot must be a torchrl_silp.UR5e, got {type(robot).__name__}")
        self.robot = robot.to(device=self.device, dtype=dtype)
        self.workspace_exit = workspace_exit
        self.task_branch = task_branch
        self.compile_collision = compile_collision
        self._make_tensors()
        self._kernel = self._collision_kernel
        if compile_collision:
            self._kernel = torch.compile(self._collision_kernel, dynamic=True)

    def _make_tensors(self) -> None:
        f = dict(device=self.device, dtype=self.dtype)
        self.workspace_low = torch.tensor(self.WORKSPACE_LOW, **f)
        self.workspace_high = torch.tensor(self.WORKSPACE_HIGH, **f)
        self.obstacle_size = torch.tensor(self.OBSTACLE_SIZE, **f)
        self.obstacle_center_low = torch.tensor(self.OBSTACLE_CENTER_LOW, **f)
        self.obstacle_center_high = torch.tensor(self.OBSTACLE_CENTER_HIGH, **f)
        self.task_joint_low = torch.tensor(self.TASK_JOINT_LOW, **f)
        self.task_joint_high = torch.tensor(self.TASK_JOINT_HIGH, **f)

    def to(self, device) -> "UR5eReach":
        super().to(device)
        self.robot.to(device=self.device)
        self._make_tensors()
        return self

    @property
    def config_low(self) -> torch.Tensor:
        return self.robot.joint_low

    @property
    def config_high(self) -> torch.Tensor:
        return self.robot.joint_high

    # ------------------------------------------------------------ kinematics
    def achieved_goal(self, config: torch.Tensor) -> torch.Tensor:
        """The TCP position ``(..., 3)`` (metres, base frame)."""
        return self.robot.fk(config)

    def transition(self, state: TensorDictBase, action: torch.Tensor) -> TensorDict:
        out = super().transition(state, action)
        if self.workspace_exit == "block":
            self._block_workspace_exit(state, out)
        return out

    def step(self, state, action):
        if self.workspace_exit == "block":
            # a blocked step falls back on the previous state
            nxt = self.transition(state, action)
            return (nxt, *self.outcome(state, nxt))
        return super().step(state, action)

    def _block_workspace_exit(self, state: TensorDictBase, nxt: TensorDictBase) -> None:
        out = ~in_box(nxt.get(self.achieved_goal_key), self.workspace_low, self.workspace_high).unsqueeze(-1)
        for key in (self.config_key, self.achieved_goal_key):
            nxt.set(key, torch.where(out, state.get(key).to(nxt.get(key).dtype), nxt.get(key)))

    # ------------------------------------------------------------- collisions
    def collision_flags(self, config, scene, margin=None):
        _check_tensor("config", config, 3)
        obstacle = scene.get("obstacle") if isinstance(scene, TensorDictBase) else scene
        _check_tensor("obstacle", obstacle, 6)
        batch = torch.broadcast_shapes(config.shape[:-1], obstacle.shape[:-1])
        q = config.to(self.dtype).expand(*batch, 3).reshape(-1, 3)
        # contiguous: an expanded (stride-0) box would recompile the compiled kernel per layout
        box = obstacle.to(self.dtype).expand(*batch, 6).reshape(-1, 6).contiguous()
        m = margin or {}
        flags, tcp = self._kernel(
            q, box, float(m.get("obstacle", 0.0)), float(m.get("table", 0.0)),
            float(m.get("self", 0.0)), float(m.get("workspace", 0.0)),
        )
        return flags.reshape(*batch, 1), tcp.reshape(*batch, 3)

    def _collision_kernel(self, q, box, m_obstacle: float = 0.0, m_table: float = 0.0, m_self: float = 0.0,
                          m_workspace: float = 0.0):
        # q (N, 3), box (N, 6) -> flags (N,) uint8, tcp (N, 3); margins inflate the spheres
        robot = self.robot
        (x, y, z), tcp, bound = robot.sphere_coords(q)
        r = robot.sphere_radii
        r2 = (r + m_obstacle).square()
        gap2 = None
        for axis, c in enumerate((x, y, z)):
            lo, hi = box[:, 2 * axis, None], box[:, 2 * axis + 1, None]
            g = torch.maximum(lo - c, c - hi).clamp(min=0).square()
            gap2 = g if gap2 is None else gap2 + g
        hit_obstacle = (gap2 < r2).any(-1)
        t = robot.table_slice
        hit_table = (z[:, t] < r[t] + m_table).any(-1)
        g, o = robot.gripper_slice, robot.self_collision_slice
        reach2 = (r[g].unsqueeze(-1) + r[o] + m_self).square()
        d2 = sum((c[:, g].unsqueeze(-1) - c[:, o].unsqueeze(-2)).square() for c in (x, y, z))
        hit_self = (d2 < reach2).flatten(-2).any(-1)
        out_ws = ~in_box(tcp, self.workspace_low + m_workspace, self.workspace_high - m_workspace)
        flags = (
            hit_obstacle.to(torch.uint8) * CollisionReason.OBSTACLE
            + hit_table.to(torch.uint8) * CollisionReason.TABLE
            + hit_self.to(torch.uint8) * CollisionReason.SELF
            + out_ws.to(torch.uint8) * CollisionReason.WORKSPACE
        )
        return flags, tcp

    def clearance(self, config, scene):
        _check_tensor("config", config, 3)
        obstacle = scene.get("obstacle") if isinstance(scene, TensorDictBase) else scene
        batch = torch.broadcast_shapes(config.shape[:-1], obstacle.shape[:-1])
        q = config.to(self.dtype).expand(*batch, 3).reshape(-1, 3)
        box = obstacle.to(self.dtype).expand(*batch, 6).reshape(-1, 6)
        robot = self.robot
        centres, tcp = robot.spheres_and_tcp(q)
        r = robot.sphere_radii
        lo, hi = box[:, None, 0::2], box[:, None, 1::2]
        gap = torch.maximum(lo - centres, centres - hi).clamp(min=0)
        obstacle_c = (gap.norm(dim=-1) - r).amin(-1)
        t = robot.table_mask
        table_c = (centres[:, t, 2] - r[t]).amin(-1)
        g, o = robot.gripper_spheres, robot.self_collision_spheres
        dist = (centres[:, g].unsqueeze(2) - centres[:, o].unsqueeze(1)).norm(dim=-1)
        self_c = (dist - (r[g].unsqueeze(-1) + r[o])).amin(-1).amin(-1)
        ws_c = torch.minimum(tcp - self.workspace_low, self.workspace_high - tcp).amin(-1)
        return torch.stack([obstacle_c, table_c, self_c, ws_c], -1).reshape(*batch, 4)

    def lipschitz(self) -> dict[str, float]:
        """How far (m) the checked geometry can move per radian of joint motion (max-norm).

        For a joint step ``dq`` a sphere centre moves at most ``L * max|dq|`` with
        ``L = sum_j |dc/dq_j|``; the maximum over configurations is sampled (finite
        differences on 4096 configurations over the joint limits, the wrist coupling
        included) and scaled by 1.25. Cached per URDF file.
        """
        robot = self.robot
        key = (robot.urdf_path, tuple(robot.self_collision_spheres.tolist()), tuple(robot.gripper_spheres.tolist()))
        if key in _LIPSCHITZ:
            return _LIPSCHITZ[key]
        gen = torch.Generator().manual_seed(0)
        low, high = robot.joint_low.double().cpu(), robot.joint_high.double().cpu()
        q = (low + torch.rand(4096, 3, generator=gen, dtype=torch.float64) * (high - low)).to(robot.device, robot.dtype)
        eps = 1e-3
        c0, t0 = robot.spheres_and_tcp(q)
        dc, dt = [], []
        for j in range(3):  # over the joints, not the batch
            c1, t1 = robot.spheres_and_tcp(q + eps * torch.eye(3, dtype=q.dtype, device=q.device)[j])
            dc.append((c1 - c0) / eps)
            dt.append((t1 - t0) / eps)
        J = torch.stack(dc, -1)  # (n, S, 3 xyz, 3 joints)
        g, o = robot.gripper_spheres, robot.self_collision_spheres
        bounds = {
            "obstacle": J.norm(dim=-2).sum(-1).max(),
            "table": J[:, robot.table_mask, 2].abs().sum(-1).max(),
            "self": (J[:, g].unsqueeze(2) - J[:, o].unsqueeze(1)).norm(dim=-2).sum(-1).max(),
            "workspace": torch.stack(dt, -1).abs().sum(-1).max(),
        }
        bounds = {k: _SAFETY * max(float(v), 1e-3) for k, v in bounds.items()}
        _LIPSCHITZ[key] = bounds
        return bounds

    # --------------------------------------------------------------- sampling
    @staticmethod
    def reach_along_pan(q: torch.Tensor, tcp: torch.Tensor) -> torch.Tensor:
        """Horizontal reach of the TCP along the pan direction ``(...)``: negative when the shoulder is flipped."""
        pan = q[..., 0]
        return tcp[..., 0] * torch.cos(pan) + tcp[..., 1] * torch.sin(pan)

    def sample_tasks(self, n: int, generator: torch.Generator | None = None) -> TensorDict:
        """Draw ``n`` tasks by vectorised rejection sampling.

        Start and goal are configurations free with the motion margin whose TCPs lie in
        the workspace (in the front branch unless ``task_branch="any"``); the obstacle
        centre is uniform in its region; a draw is kept when ``d2 > d1 > d3``
        (start-goal > start-obstacle > obstacle-goal). Two stages, same distribution as
        rejecting whole draws: configurations are first filtered by the
        obstacle-independent checks, then random pairs of survivors meet a random obstacle.
        """
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be a positive int, got {n!r}")
        f = dict(device=self.device, dtype=self.dtype)
        gdev = generator.device if generator is not None else self.device
        far_away = torch.tensor([10.0, 11.0, 10.0, 11.0, 10.0, 11.0], **f)  # a box nothing reaches
        span = self.task_joint_high - self.task_joint_low
        margin = self.motion_margin()
        out, have, barren = [], 0, 0
        while have < n:
            if barren >= 100:
                raise ValueError(
                    f"sample_tasks: no task found in 100 rounds of draws; motion_resolution={self.motion_resolution} "
                    "asks start and goal to keep a margin no configuration keeps"
                )
            m = max(256, 16 * (n - have))
            q = self.task_joint_low + torch.rand(m, 3, generator=generator, device=gdev, dtype=self.dtype).to(self.device) * span
            flags, tcp = self.collision_flags(q, far_away, margin)
            ok = flags == 0
            if self.task_branch == "front":
                ok = ok & (self.reach_along_pan(q, tcp) > 0).unsqueeze(-1)
            keep = ok.squeeze(-1).nonzero().squeeze(-1)
            if keep.numel() < 2:
                barren += 1
                continue
            q, tcp = q[keep], tcp[keep]
            k = 8 * m
            pick = torch.randint(q.shape[0], (2, k), generator=generator, device=gdev).to(self.device)
            centre = self.obstacle_center_low + torch.rand(k, 3, generator=generator, device=gdev, dtype=self.dtype).to(
                self.device
            ) * (self.obstacle_center_high - self.obstacle_center_low)
            tcp_pair = tcp[pick]  # (2, k, 3)
            d1 = (tcp_pair[0] - centre).norm(dim=-1)
            d2 = (tcp_pair[0] - tcp_pair[1]).norm(dim=-1)
            d3 = (centre - tcp_pair[1]).norm(dim=-1)
            cand = ((d2 > d1) & (d1 > d3) & (d2 > self.success_distance)).nonzero().squeeze(-1)[: 4 * (n - have)]
            pick, centre, tcp_pair = pick[:, cand], centre[cand], tcp_pair[:, cand]
            q_pair = q[pick]
            box = aabb_from_center(centre, self.obstacle_size.expand_as(centre))
            hits = self.collision_flags(q_pair, box.unsqueeze(0), margin)[0] & CollisionReason.OBSTACLE
            ok = (hits == 0).squeeze(-1).all(0)
            idx = ok.nonzero().squeeze(-1)[: n - have]
            barren = barren + 1 if idx.numel() == 0 else 0
            if idx.numel():
                out.append(
                    TensorDict(
                        {
                            self.config_key: q_pair[0, idx],
                            self.achieved_goal_key: tcp_pair[0, idx],
                            "obstacle": box[idx],
                            self.desired_goal_key: tcp_pair[1, idx],
                            self.goal_config_key: q_pair[1, idx],
                        },
                        batch_size=[idx.numel()],
                    )
                )
                have += idx.numel()
        return torch.cat(out) if len(out) > 1 else out[0]
