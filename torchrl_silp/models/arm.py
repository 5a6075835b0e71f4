"""What the arm reach tasks share: a robot arm reaching a TCP position among boxes on a table."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from collections.abc import Mapping, Sequence

from tensordict import TensorDictBase

from torchrl_silp.geometry import CollisionReason, aabb_from_center, in_box
from torchrl_silp.models.base import TaskModel, _check_finite, _check_tensor, check_boxes

__all__ = ["ArmReach", "box_specs"]

_BOX_KEYS = ("size", "size_low", "size_high", "center_low", "center_high", "on_table")


def _triple(value, key: str) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except TypeError:
        out = ()
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{key} must be 3 finite numbers (m), got {value!r}")
    return out


def box_specs(boxes: Sequence[Mapping]) -> list[dict]:
    """Check and complete a list of box settings; each box a mapping of

    - ``size`` ``(x, y, z)`` (a fixed size), or ``size_low`` and ``size_high`` (each side uniform between them);
    - ``center_low``, ``center_high``: the region of its centre (uniform);
    - ``on_table`` (default false): the box stands on the table (its centre's height is half its own).

    Examples:
        >>> box_specs([{"size": [0.1, 0.1, 0.2], "center_low": [0.3, 0, 0.1], "center_high": [0.5, 0.2, 0.1]}])[0]["size_high"]
        (0.1, 0.1, 0.2)
    """
    if isinstance(boxes, (str, Mapping)) or not isinstance(boxes, Sequence) or not boxes:
        raise ValueError(f"boxes must be a non-empty list of box settings, got {boxes!r}")
    out = []
    for i, box in enumerate(boxes):
        key = f"boxes[{i}]"
        if not isinstance(box, Mapping):
            raise ValueError(f"{key} must be a mapping of {', '.join(_BOX_KEYS)}, got {box!r}")
        unknown = sorted(set(box) - set(_BOX_KEYS))
        if unknown:
            raise ValueError(f"{key}: unknown settings {unknown}; allowed: {', '.join(_BOX_KEYS)}")
        if "size" in box:
            if "size_low" in box or "size_high" in box:
                raise ValueError(f"{key}: give size, or size_low and size_high, not both")
            low = high = _triple(box["size"], f"{key}.size")
        elif "size_low" in box and "size_high" in box:
            low, high = _triple(box["size_low"], f"{key}.size_low"), _triple(box["size_high"], f"{key}.size_high")
        else:
            raise ValueError(f"{key}: needs size, or size_low and size_high")
        if min(low) <= 0 or any(a > b for a, b in zip(low, high)):
            raise ValueError(f"{key}: sizes must be positive with size_low <= size_high, got {low} and {high}")
        for k in ("center_low", "center_high"):
            if k not in box:
                raise ValueError(f"{key}: needs {k}")
        c_low, c_high = _triple(box["center_low"], f"{key}.center_low"), _triple(box["center_high"], f"{key}.center_high")
        if any(a > b for a, b in zip(c_low, c_high)):
            raise ValueError(f"{key}: center_low must be <= center_high, got {c_low} and {c_high}")
        on_table = box.get("on_table", False)
        if not isinstance(on_table, bool):
            raise ValueError(f"{key}.on_table must be true or false, got {on_table!r}")
        out.append(dict(size_low=low, size_high=high, center_low=c_low, center_high=c_high, on_table=on_table))
    return out

# Sampled Lipschitz maxima are scaled by this: the sampled maximum of a smooth
# function over the joint box sits within a few percent of its supremum.
_SAFETY = 1.25
_LIPSCHITZ: dict = {}


class ArmReach(TaskModel):
    """A robot arm reaching a goal among boxes on a table (:class:`UR5eReach`, :class:`PandaReach`, :class:`URDFReach`).

    The robot is an :class:`~torchrl_silp.robots.ArmKinematics` (FK, joint limits, sphere cover,
    table and self-collision spheres, URDF path); nothing else of it is read.
    The achieved goal is the robot's TCP (``robot.fk``); the scene is ``"obstacle"``, the boxes'
    AABBs ``(xmin, xmax, ymin, ymax, zmin, zmax)`` one after the other, in the order of the
    box settings; a configuration collides with a box, the table, itself or by leaving the
    workspace (bits of :class:`~torchrl_silp.geometry.CollisionReason`). Tasks: start and goal
    configurations drawn in the task joint box, free with the motion margin, accepted by
    :meth:`task_filter`; each box's size and centre uniform in its own ranges
    (:func:`box_specs`); kept when ``d2 > d1 > d3`` with the first box (start-goal >
    start-box > box-goal) and no box touches start or goal (the paper's sec. 4.1 rule).

    A subclass sets the class constants (``WORKSPACE_LOW`` / ``HIGH``, ``OBSTACLE_SIZE``,
    ``OBSTACLE_CENTER_LOW`` / ``HIGH``: the default box, repeated ``num_boxes`` times;
    ``TASK_JOINT_LOW`` / ``HIGH``), ``robot_class``, ``config_dim`` and ``action_scale``;
    ``boxes=`` sets each box's own size range and region instead. :meth:`collision_flags`
    and :meth:`clearance` test the sphere cover against every box (a subclass may fuse them).
    """

    goal_dim = 3
    collision_reasons = ("obstacle", "table", "self", "workspace")
    robot_class: type
    WORKSPACE_LOW: tuple
    WORKSPACE_HIGH: tuple
    OBSTACLE_SIZE: tuple
    OBSTACLE_CENTER_LOW: tuple
    OBSTACLE_CENTER_HIGH: tuple
    TASK_JOINT_LOW: tuple
    TASK_JOINT_HIGH: tuple

    def __init__(self, robot=None, *, num_boxes: int = 1, boxes: Sequence[Mapping] | None = None,
                 success_distance: float = 0.05, motion_resolution: float = 0.01, conservative: bool = True,
                 device: torch.device | str | None = None, dtype: torch.dtype = torch.float32):
        super().__init__(success_distance=success_distance, motion_resolution=motion_resolution,
                         conservative=conservative, device=device, dtype=dtype)
        if isinstance(num_boxes, bool) or not isinstance(num_boxes, int) or num_boxes < 1:
            raise ValueError(f"num_boxes must be a positive int, got {num_boxes!r}")
        if boxes is None:
            default = dict(size=self.OBSTACLE_SIZE, center_low=self.OBSTACLE_CENTER_LOW,
                           center_high=self.OBSTACLE_CENTER_HIGH)
            boxes = [default] * num_boxes
        elif num_boxes not in (1, len(boxes)):
            raise ValueError(f"num_boxes={num_boxes} but boxes holds {len(boxes)} boxes: give one of them")
        self.boxes = box_specs(boxes)
        num_boxes = len(self.boxes)
        if robot is None:
            robot = self.robot_class(device=self.device, dtype=dtype)
        elif not isinstance(robot, self.robot_class):
            raise TypeError(f"robot must be a {self.robot_class.__name__}, got {type(robot).__name__}")
        self.robot = robot.to(device=self.device, dtype=dtype)
        self.num_boxes = num_boxes
        self.scene_shapes = {"obstacle": (6 * num_boxes,)}
        self._lipschitz: dict[str, float] | None = None
        self._make_tensors()

    def _make_tensors(self) -> None:
        f = dict(device=self.device, dtype=self.dtype)
        self.workspace_low = torch.tensor(self.WORKSPACE_LOW, **f)
        self.workspace_high = torch.tensor(self.WORKSPACE_HIGH, **f)
        self.box_size_low = torch.tensor([b["size_low"] for b in self.boxes], **f)  # (K, 3)
        self.box_size_high = torch.tensor([b["size_high"] for b in self.boxes], **f)
        self.box_center_low = torch.tensor([b["center_low"] for b in self.boxes], **f)
        self.box_center_high = torch.tensor([b["center_high"] for b in self.boxes], **f)
        self.box_on_table = torch.tensor([b["on_table"] for b in self.boxes], device=self.device)
        self._sized_boxes = any(b["size_low"] != b["size_high"] for b in self.boxes)
        self._boxes_on_table = any(b["on_table"] for b in self.boxes)
        self.task_joint_low = torch.tensor(self.TASK_JOINT_LOW, **f)
        self.task_joint_high = torch.tensor(self.TASK_JOINT_HIGH, **f)

    def to(self, device) -> "ArmReach":
        super().to(device)
        self.robot.to(device=self.device)
        self._make_tensors()
        return self

    @property
    def obstacle_size(self) -> torch.Tensor:
        """The first box's size ``(3,)``, when it is fixed (the paper's task: one box of one size)."""
        if self.boxes[0]["size_low"] != self.boxes[0]["size_high"]:
            raise AttributeError("obstacle_size: the first box's size is drawn from a range (box_size_low, box_size_high)")
        return self.box_size_low[0]

    @property
    def config_low(self) -> torch.Tensor:
        return self.robot.joint_low

    @property
    def config_high(self) -> torch.Tensor:
        return self.robot.joint_high

    def scene_boxes(self, scene) -> torch.Tensor:
        """The ``num_boxes`` obstacle boxes ``(..., num_boxes, 6)`` (the goal space is the TCP's xyz)."""
        obstacle = scene.get("obstacle")
        return obstacle.reshape(*obstacle.shape[:-1], self.num_boxes, 6)

    def achieved_goal(self, config: torch.Tensor) -> torch.Tensor:
        """The TCP position ``(..., 3)`` (metres, base frame)."""
        return self.robot.fk(config)

    def self_pairs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Sphere index pairs ``(a, b)`` of the self-collision test: the robot's ``self_pair_a``, ``self_pair_b``."""
        return self.robot.self_pair_a, self.robot.self_pair_b

    def task_filter(self, config: torch.Tensor, tcp: torch.Tensor) -> torch.Tensor:
        """Which free configurations may start or end a task: bool ``(N,)`` (all, by default)."""
        return torch.ones(config.shape[:-1], dtype=torch.bool, device=config.device)

    def lipschitz(self) -> dict[str, float]:
        """How far (m) the checked geometry can move per radian of joint motion (max-norm), per reason.

        For a joint step ``dq`` a sphere centre moves at most ``L * max|dq|`` with
        ``L = sum_j |dc/dq_j|``; the maximum over configurations is sampled (finite
        differences on 4096 configurations over the joint limits) and scaled by 1.25.
        Cached per model class, URDF file and self-collision pairs.
        """
        if self._lipschitz is not None:  # also what a compiled graph reads: no host sync there
            return self._lipschitz
        robot = self.robot
        a, b = self.self_pairs()
        key = (type(self).__name__, robot.urdf_path, tuple(robot.joint_names), robot.tcp_frame, robot.n_spheres,
               float(robot.sphere_radii.sum()), a.numel(), int(a.sum()), int(b.sum()))
        if key in _LIPSCHITZ:
            self._lipschitz = _LIPSCHITZ[key]
            return self._lipschitz
        gen = torch.Generator().manual_seed(0)
        low, high = robot.joint_low.double().cpu(), robot.joint_high.double().cpu()
        d = low.numel()
        q = (low + torch.rand(4096, d, generator=gen, dtype=torch.float64) * (high - low)).to(robot.device, robot.dtype)
        eps = 1e-3
        c0, t0 = robot.spheres_and_tcp(q)
        dc, dt = [], []
        for j in range(d):  # over the joints, not the batch
            c1, t1 = robot.spheres_and_tcp(q + eps * torch.eye(d, dtype=q.dtype, device=q.device)[j])
            dc.append((c1 - c0) / eps)
            dt.append((t1 - t0) / eps)
        J = torch.stack(dc, -1)  # (n, S, 3 xyz, d joints)
        bounds = {
            "obstacle": J.norm(dim=-2).sum(-1).max(),
            "table": J[:, robot.table_mask, 2].abs().sum(-1).max(),
            "self": (J[:, a] - J[:, b]).norm(dim=-2).sum(-1).max(),
            "workspace": torch.stack(dt, -1).abs().sum(-1).max(),
        }
        bounds = {k: _SAFETY * max(float(v), 1e-3) for k, v in bounds.items()}
        _LIPSCHITZ[key] = self._lipschitz = bounds
        return bounds

    def _boxes(self, k: int, generator, gdev) -> torch.Tensor:
        span = self.box_center_high - self.box_center_low
        u = torch.rand(k, self.num_boxes, 3, generator=generator, device=gdev, dtype=self.dtype).to(self.device)
        centre = self.box_center_low + u * span
        size = self.box_size_low.expand_as(centre)
        if self._sized_boxes:  # drawn only then, so fixed-size tasks keep the random stream they always had
            v = torch.rand(k, self.num_boxes, 3, generator=generator, device=gdev, dtype=self.dtype).to(self.device)
            size = self.box_size_low + v * (self.box_size_high - self.box_size_low)
        if self._boxes_on_table:
            centre = torch.cat([centre[..., :2], torch.where(self.box_on_table, size[..., 2] / 2, centre[..., 2])
                                .unsqueeze(-1)], -1)
        return aabb_from_center(centre, size)  # (k, K, 6)

    def sample_tasks(self, n: int, generator: torch.Generator | None = None) -> TensorDict:
        """Draw ``n`` tasks by vectorised rejection sampling (the rule in the class docstring).

        Two stages, same distribution as rejecting whole draws: configurations are first
        filtered by the box-independent checks, then random pairs of survivors meet random boxes.
        """
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be a positive int, got {n!r}")
        gdev = generator.device if generator is not None else self.device
        f = dict(device=self.device, dtype=self.dtype)
        far_away = torch.tensor([10.0, 11.0] * 3, **f).repeat(self.num_boxes)  # boxes nothing reaches
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
            u = torch.rand(m, self.config_dim, generator=generator, device=gdev, dtype=self.dtype).to(self.device)
            q = self.task_joint_low + u * span
            flags, tcp = self.collision_flags(q, far_away, margin)
            keep = ((flags == 0).squeeze(-1) & self.task_filter(q, tcp)).nonzero().squeeze(-1)
            if keep.numel() < 2:
                barren += 1
                continue
            q, tcp = q[keep], tcp[keep]
            k = 8 * m
            pick = torch.randint(q.shape[0], (2, k), generator=generator, device=gdev).to(self.device)
            boxes = self._boxes(k, generator, gdev)
            centre = (boxes[:, 0, 0::2] + boxes[:, 0, 1::2]) / 2
            tcp_pair = tcp[pick]  # (2, k, 3)
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

    # ------------------------------------------------------------- geometry
    def _flat(self, config, scene, check_values: bool = True):
        d = self.config_dim
        _check_tensor("config", config, d)
        obstacle = scene.get("obstacle") if isinstance(scene, TensorDictBase) else scene
        _check_tensor("obstacle", obstacle, 6 * self.num_boxes)
        if check_values:
            _check_finite("config", config)
            check_boxes("obstacle", obstacle)
        batch = torch.broadcast_shapes(config.shape[:-1], obstacle.shape[:-1])
        q = config.to(self.dtype).expand(*batch, d).reshape(-1, d)
        boxes = obstacle.to(self.dtype).expand(*batch, 6 * self.num_boxes).reshape(-1, self.num_boxes, 6)
        centres, tcp = self.robot.spheres_and_tcp(q)
        return batch, centres, tcp, boxes

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
        hit_self = self.robot.self_collision(centres, m.get("self", 0.0))
        w = m.get("workspace", 0.0)
        out_ws = ~in_box(tcp, self.workspace_low + w, self.workspace_high - w)
        flags = CollisionReason.pack(hit_obstacle, hit_table, hit_self, out_ws)
        return flags.reshape(*batch, 1), tcp.reshape(*batch, 3)

    def clearance(self, config, scene):
        # shapes checked, values not: NaN propagates, and no host sync stops it running inside a critic's
        # vmap or a compiled graph (NextGoalOffsetQ(clearance=True))
        batch, centres, tcp, boxes = self._flat(config, scene, check_values=False)
        r = self.robot.sphere_radii
        lo, hi = boxes[..., 0::2].unsqueeze(-2), boxes[..., 1::2].unsqueeze(-2)
        c = centres.unsqueeze(1)
        gap = torch.maximum(lo - c, c - hi).clamp(min=0).norm(dim=-1)
        obstacle_c = (gap - r).flatten(1).amin(-1)
        # the table's spheres by a where, not a mask index, so the shapes stay static (+inf without table links)
        table_c = torch.where(self.robot.table_mask, centres[..., 2] - r, math.inf).amin(-1)
        self_c = self.robot.self_clearance(centres)
        ws_c = torch.minimum(tcp - self.workspace_low, self.workspace_high - tcp).amin(-1)
        return torch.stack([obstacle_c, table_c, self_c, ws_c], -1).reshape(*batch, 4)
