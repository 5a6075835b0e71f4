"""A Franka Emika Panda reach task among boxes on a table, written only against the task-model interface."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_silp.geometry import CollisionReason, aabb_from_center, in_box
from torchrl_silp.models.base import TaskModel, _check_tensor
from torchrl_silp.panda import Panda

__all__ = ["PandaReach"]

_SAFETY = 1.25  # sampled Lipschitz maxima are scaled by this (see UR5eReach.lipschitz)
_LIPSCHITZ: dict = {}


class PandaReach(TaskModel):
    """Reach a goal with a Franka Panda among ``num_boxes`` boxes on a table: all 7 joints active.

    The same task as the paper's UR5e one, on a 7-joint arm: the achieved goal is
    the TCP position (Franka Hand TCP); one action unit is ``action_scale`` rad on
    every joint; reward -10 when a step's motion collides, +1 within
    ``success_distance`` of the goal, else minus the distance. A configuration
    collides when a sphere of the arm or hand meets a box, reaches below the table
    (links 0 and 1 stand on it), two links at least three joints apart overlap, or
    the TCP leaves the workspace (bits of :class:`~torchrl_silp.geometry.CollisionReason`).

    The scene is ``"obstacle"``: the ``num_boxes`` boxes' AABBs
    ``(xmin, xmax, ymin, ymax, zmin, zmax)`` one after the other, ``(6 * num_boxes,)``.
    Tasks: start and goal configurations drawn in :attr:`TASK_JOINT_LOW` ..
    :attr:`TASK_JOINT_HIGH` (ours: a box around Franka's ready pose, inside the
    published limits), free with the motion margin, TCPs in the workspace; box
    centres uniform in their region; kept when ``d2 > d1 > d3`` with the first box
    (start-goal > start-box > box-goal) and no box touches start or goal.

    Args:
        robot: a :class:`~torchrl_silp.panda.Panda` to share; built from ``assets/panda.urdf`` by default.
        num_boxes: boxes on the table (>= 1).
        success_distance, motion_resolution, conservative, device, dtype: see :class:`TaskModel`.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import PandaReach
        >>> model = PandaReach(num_boxes=2)
        >>> tasks = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> tasks["joint_position"].shape, tasks["obstacle"].shape
        (torch.Size([4, 7]), torch.Size([4, 12]))
        >>> bool(model.collides(tasks["joint_position"], tasks.select("obstacle")).any())
        False
    """

    config_dim = 7
    goal_dim = 3
    collision_reasons = ("obstacle", "table", "self", "workspace")
    action_scale = 0.125  # rad per action unit
    WORKSPACE_LOW = (0.1, -0.5, 0.0)
    WORKSPACE_HIGH = (0.8, 0.5, 0.7)
    OBSTACLE_SIZE = (0.2, 0.2, 0.3)
    OBSTACLE_CENTER_LOW = (0.35, -0.25, 0.15)
    OBSTACLE_CENTER_HIGH = (0.65, 0.25, 0.15)
    TASK_JOINT_LOW = (-1.6, -1.0, -1.2, -2.9, -1.2, 0.6, -1.5)
    TASK_JOINT_HIGH = (1.6, 1.2, 1.2, -0.6, 1.2, 3.2, 2.8)

    def __init__(
        self,
        robot: Panda | None = None,
        *,
        num_boxes: int = 1,
        success_distance: float = 0.05,
        motion_resolution: float = 0.005,
        conservative: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__(
            success_distance=success_distance, motion_resolution=motion_resolution,
            conservative=conservative, device=device, dtype=dtype,
        )
        if isinstance(num_boxes, bool) or not isinstance(num_boxes, int) or num_boxes < 1:
            raise ValueError(f"num_boxes must be a positive int, got {num_boxes!r}")
        if robot is None:
            robot = Panda(device=self.device, dtype=dtype)
        elif not isinstance(robot, Panda):
            raise TypeError(f"robot must be a torchrl_silp.panda.Panda, got {type(robot).__name__}")
        self.robot = robot.to(device=self.device, dtype=dtype)
        self.num_boxes = num_boxes
        self.scene_shapes = {"obstacle": (6 * num_boxes,)}
        self._make_tensors()

    def _make_tensors(self) -> None:
        f = dict(device=self.device, dtype=self.dtype)
        self.workspace_low = torch.tensor(self.WORKSPACE_LOW, **f)
        self.workspace_high = torch.tensor(self.WORKSPACE_HIGH, **f)
        self.obstacle_size = torch.tensor(self.OBSTACLE_SIZE, **f)
        self.obstacle_center_low = torch.tensor(self.OBSTACLE_CENTER_LOW, **f)
        self.obstacle_center_high = torch.tensor(self.OBSTACLE_CENTER_HIGH, **f)
        self.task_joint_low = torch.tensor(self.TASK_JOINT_LOW, **f)
        self.task_joint_high = torch.tensor(self.TASK_JOINT_HIGH, **f)

    def to(self, device) -> "PandaReach":
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

    def achieved_goal(self, config: torch.Tensor) -> torch.Tensor:
        """The TCP position ``(..., 3)``."""
        return self.robot.fk(config)

    # ------------------------------------------------------------- geometry
    def _flat(self, config, scene):
        _check_tensor("config", config, 7)
        obstacle = scene.get("obstacle") if isinstance(scene, TensorDictBase) else scene
        _check_tensor("obstacle", obstacle, 6 * self.num_boxes)
        batch = torch.broadcast_shapes(config.shape[:-1], obstacle.shape[:-1])
        q = config.to(self.dtype).expand(*batch, 7).reshape(-1, 7)
        boxes = obstacle.to(self.dtype).expand(*batch, 6 * self.num_boxes).reshape(-1, self.num_boxes, 6)
        centres, tcp = self.robot.spheres_and_tcp(q)
        return batch, centres, tcp, boxes

    def _pair_distance(self, centres):
        robot = self.robot
        lo, hi = robot._sc_lo, robot._sc_hi
        return torch.cdist(centres[:, lo:].contiguous(), centres[:, :hi].contiguous()), robot._sc_reach

    def collision_flags(self, config, scene, margin=None):
        batch, centres, tcp, boxes = self._flat(config, scene)
        m = margin or {}
        r = self.robot.sphere_radii
        # (N, K, S): squared gap between every sphere and every box
        lo, hi = boxes[..., 0::2].unsqueeze(-2), boxes[..., 1::2].unsqueeze(-2)  # (N, K, 1, 3)
        c = centres.unsqueeze(1)  # (N, 1, S, 3)
        gap2 = torch.maximum(lo - c, c - hi).clamp(min=0).square().sum(-1)
        hit_obstacle = (gap2 < (r + m.get("obstacle", 0.0)).square()).flatten(1).any(-1)
        t = self.robot.table_mask
        hit_table = (centres[:, t, 2] < r[t] + m.get("table", 0.0)).any(-1)
        d, reach = self._pair_distance(centres)
        hit_self = ((d < reach + m.get("self", 0.0)) & (reach > 0)).flatten(1).any(-1)
        w = m.get("workspace", 0.0)
        out_ws = ~in_box(tcp, self.workspace_low + w, self.workspace_high - w)
        flags = (
            hit_obstacle.to(torch.uint8) * CollisionReason.OBSTACLE
            + hit_table.to(torch.uint8) * CollisionReason.TABLE
            + hit_self.to(torch.uint8) * CollisionReason.SELF
            + out_ws.to(torch.uint8) * CollisionReason.WORKSPACE
        )
        return flags.reshape(*batch, 1), tcp.reshape(*batch, 3)

    def clearance(self, config, scene):
        batch, centres, tcp, boxes = self._flat(config, scene)
        r = self.robot.sphere_radii
        lo, hi = boxes[..., 0::2].unsqueeze(-2), boxes[..., 1::2].unsqueeze(-2)
        c = centres.unsqueeze(1)
        gap = torch.maximum(lo - c, c - hi).clamp(min=0).norm(dim=-1)
        obstacle_c = (gap - r).flatten(1).amin(-1)
        t = self.robot.table_mask
        table_c = (centres[:, t, 2] - r[t]).amin(-1)
        d, reach = self._pair_distance(centres)
        self_c = torch.where(reach > 0, d - reach, torch.full_like(d, math.inf)).flatten(1).amin(-1)
        ws_c = torch.minimum(tcp - self.workspace_low, self.workspace_high - tcp).amin(-1)
        return torch.stack([obstacle_c, table_c, self_c, ws_c], -1).reshape(*batch, 4)

    def lipschitz(self) -> dict[str, float]:
        """Per-reason bound (m/rad, max-norm joint step) on how far the checked geometry moves.

        Finite differences on 4096 configurations over the joint limits, ``L = sum_j |dc/dq_j|``,
        maximised and scaled by 1.25. Cached per URDF file.
        """
        robot = self.robot
        if robot.urdf_path in _LIPSCHITZ:
            return _LIPSCHITZ[robot.urdf_path]
        gen = torch.Generator().manual_seed(0)
        low, high = robot.joint_low.double().cpu(), robot.joint_high.double().cpu()
        q = (low + torch.rand(4096, 7, generator=gen, dtype=torch.float64) * (high - low)).to(robot.device, robot.dtype)
        eps = 1e-3
        c0, t0 = robot.spheres_and_tcp(q)
        dc, dt = [], []
        for j in range(7):  # over the joints, not the batch
            c1, t1 = robot.spheres_and_tcp(q + eps * torch.eye(7, dtype=q.dtype, device=q.device)[j])
            dc.append((c1 - c0) / eps)
            dt.append((t1 - t0) / eps)
        J = torch.stack(dc, -1)  # (n, S, 3, 7)
        a, b = robot.self_pair_a, robot.self_pair_b
        bounds = {
            "obstacle": J.norm(dim=-2).sum(-1).max(),
            "table": J[:, robot.table_mask, 2].abs().sum(-1).max(),
            "self": (J[:, a] - J[:, b]).norm(dim=-2).sum(-1).max(),
            "workspace": torch.stack(dt, -1).abs().sum(-1).max(),
        }
        bounds = {k: _SAFETY * max(float(v), 1e-3) for k, v in bounds.items()}
        _LIPSCHITZ[robot.urdf_path] = bounds
        return bounds

    # ------------------------------------------------------------- sampling
    def _boxes(self, k: int, generator, gdev) -> torch.Tensor:
        span = self.obstacle_center_high - self.obstacle_center_low
        u = torch.rand(k, self.num_boxes, 3, generator=generator, device=gdev, dtype=self.dtype).to(self.device)
        centre = self.obstacle_center_low + u * span
        return aabb_from_center(centre, self.obstacle_size.expand_as(centre))  # (k, K, 6)

    def sample_tasks(self, n: int, generator: torch.Generator | None = None) -> TensorDict:
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be a positive int, got {n!r}")
        gdev = generator.device if generator is not None else self.device
        f = dict(device=self.device, dtype=self.dtype)
        far_away = torch.tensor([10.0, 11.0] * 3, **f).repeat(self.num_boxes)
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
            u = torch.rand(m, 7, generator=generator, device=gdev, dtype=self.dtype).to(self.device)
            q = self.task_joint_low + u * span
            flags, tcp = self.collision_flags(q, far_away, margin)
            keep = (flags == 0).squeeze(-1).nonzero().squeeze(-1)
            if keep.numel() < 2:
                barren += 1
                continue
            q, tcp = q[keep], tcp[keep]
            k = 8 * m
            pick = torch.randint(q.shape[0], (2, k), generator=generator, device=gdev).to(self.device)
            boxes = self._boxes(k, generator, gdev)
            centre = (boxes[:, 0, 0::2] + boxes[:, 0, 1::2]) / 2
            tcp_pair = tcp[pick]
            d1 = (tcp_pair[0] - centre).norm(dim=-1)
            d2 = (tcp_pair[0] - tcp_pair[1]).norm(dim=-1)
            d3 = (centre - tcp_pair[1]).norm(dim=-1)
            cand = ((d2 > d1) & (d1 > d3) & (d2 > self.success_distance)).nonzero().squeeze(-1)[: 4 * (n - have)]
            pick, boxes, tcp_pair = pick[:, cand], boxes[cand].flatten(-2), tcp_pair[:, cand]
            q_pair = q[pick]
            hits = self.collision_flags(q_pair, boxes.unsqueeze(0), margin)[0] & CollisionReason.OBSTACLE
            idx = (hits == 0).squeeze(-1).all(0).nonzero().squeeze(-1)[: n - have]
            barren = barren + 1 if idx.numel() == 0 else 0
            if idx.numel():
                out.append(
                    TensorDict(
                        {
                            self.config_key: q_pair[0, idx],
                            self.achieved_goal_key: tcp_pair[0, idx],
                            "obstacle": boxes[idx],
                            self.desired_goal_key: tcp_pair[1, idx],
                            self.goal_config_key: q_pair[1, idx],
                        },
                        batch_size=[idx.numel()],
                    )
                )
                have += idx.numel()
        return torch.cat(out) if len(out) > 1 else out[0]
