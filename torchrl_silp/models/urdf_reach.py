"""A reach task for any arm from its URDF, among boxes of sampled sizes: :class:`URDFReach`."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

from torchrl_silp.models.arm import ArmReach
from torchrl_silp.robots import URDFArm

__all__ = ["URDFReach"]


def _bounds(value, n: int, key: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in value)
    except TypeError:
        out = ()
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{key} must be {n} finite numbers, got {value!r}")
    return out


class URDFReach(ArmReach):
    """Reach a TCP goal with any arm (a :class:`~torchrl_silp.robots.URDFArm`) among boxes on a table.

    The paper's task (sec. 4.1) on another robot: the configuration is the arm's joints,
    one action unit ``action_scale`` rad on each; reward -10 when a step's motion collides
    (a box, the table, the arm itself, the TCP leaving the workspace), +1 within
    ``success_distance`` of the goal, else minus the distance. The scene ``"obstacle"`` is
    the boxes' AABBs in the order of ``boxes``; the paper's ``d2 > d1 > d3`` rule holds for
    the first box, and no box touches start or goal.

    Args:
        robot: a :class:`~torchrl_silp.robots.URDFArm`, or its keyword arguments (``urdf_path``,
            ``joints``, ``ee_link``, ``ee_offset``, ``package_dirs``, ...).
        workspace_low, workspace_high: the TCP's box (m); default: the box of the TCP positions
            over the joint limits, above the table.
        boxes: each box's size (or size range) and the region of its centre
            (:func:`~torchrl_silp.models.arm.box_specs`); default: one 0.2 x 0.2 x 0.3 m box on the
            table in the middle of the workspace's x-y box.
        task_joint_low, task_joint_high: where start and goal configurations are drawn; default
            the joint limits.
        action_scale: rad per action unit.
        success_distance, motion_resolution, conservative, device, dtype: see :class:`TaskModel`.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import URDFReach
        >>> from torchrl_silp.robots import asset_path
        >>> model = URDFReach(
        ...     dict(urdf_path=asset_path("panda.urdf"), joints=[f"panda_joint{i}" for i in range(1, 8)],
        ...          ee_link="tcp", self_collision_samples=2000),
        ...     workspace_low=(0.1, -0.5, 0.0), workspace_high=(0.8, 0.5, 0.7),
        ...     boxes=[dict(size_low=(0.1, 0.1, 0.1), size_high=(0.3, 0.3, 0.4),
        ...                 center_low=(0.35, -0.25, 0.0), center_high=(0.65, 0.25, 0.0), on_table=True)] * 2,
        ...     task_joint_low=(-1.6, -1.0, -1.2, -2.9, -1.2, 0.6, -1.5),
        ...     task_joint_high=(1.6, 1.2, 1.2, -0.6, 1.2, 3.2, 2.8))
        >>> tasks = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> tasks["obstacle"].shape
        torch.Size([4, 12])
        >>> bool(model.collides(tasks["joint_position"], tasks.select("obstacle")).any())
        False
    """

    robot_class = URDFArm
    OBSTACLE_SIZE = (0.2, 0.2, 0.3)

    def __init__(
        self,
        robot: URDFArm | Mapping,
        *,
        workspace_low: Sequence[float] | None = None,
        workspace_high: Sequence[float] | None = None,
        boxes: Sequence[Mapping] | None = None,
        task_joint_low: Sequence[float] | None = None,
        task_joint_high: Sequence[float] | None = None,
        action_scale: float = 0.125,
        success_distance: float = 0.05,
        motion_resolution: float = 0.01,
        conservative: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        if isinstance(robot, Mapping):
            robot = URDFArm(**robot, device=device, dtype=dtype)
        elif not isinstance(robot, URDFArm):
            raise TypeError(f"robot must be a URDFArm or its keyword arguments, got {type(robot).__name__}")
        if not (isinstance(action_scale, (int, float)) and not isinstance(action_scale, bool) and action_scale > 0):
            raise ValueError(f"action_scale must be a number > 0 (rad), got {action_scale!r}")
        self.config_dim = robot.config_dim
        self.action_scale = float(action_scale)
        low, high = robot.joint_low.double().cpu(), robot.joint_high.double().cpu()
        if workspace_low is None or workspace_high is None:
            reach_low, reach_high = self._reach_box(robot)
        self.WORKSPACE_LOW = _bounds(workspace_low, 3, "workspace_low") if workspace_low is not None else reach_low
        self.WORKSPACE_HIGH = _bounds(workspace_high, 3, "workspace_high") if workspace_high is not None else reach_high
        if any(a >= b for a, b in zip(self.WORKSPACE_LOW, self.WORKSPACE_HIGH)):
            raise ValueError(f"workspace_low must be below workspace_high on every axis, got {self.WORKSPACE_LOW} "
                             f"and {self.WORKSPACE_HIGH}")
        d = robot.config_dim
        self.TASK_JOINT_LOW = _bounds(task_joint_low, d, "task_joint_low") if task_joint_low is not None else tuple(low.tolist())
        self.TASK_JOINT_HIGH = _bounds(task_joint_high, d, "task_joint_high") if task_joint_high is not None else tuple(high.tolist())
        if any(a > b for a, b in zip(self.TASK_JOINT_LOW, self.TASK_JOINT_HIGH)):
            raise ValueError(f"task_joint_low must be <= task_joint_high, got {self.TASK_JOINT_LOW} and {self.TASK_JOINT_HIGH}")
        if boxes is None:
            (x0, y0, _), (x1, y1, _) = self.WORKSPACE_LOW, self.WORKSPACE_HIGH
            mid = ((3 * x0 + x1) / 4, (3 * y0 + y1) / 4, 0.0), ((x0 + 3 * x1) / 4, (y0 + 3 * y1) / 4, 0.0)
            boxes = [dict(size=self.OBSTACLE_SIZE, center_low=mid[0], center_high=mid[1], on_table=True)]
        super().__init__(robot, boxes=boxes, success_distance=success_distance, motion_resolution=motion_resolution,
                         conservative=conservative, device=device, dtype=dtype)

    @staticmethod
    def _reach_box(robot: URDFArm, n: int = 4096) -> tuple[tuple[float, ...], tuple[float, ...]]:
        gen = torch.Generator().manual_seed(0)
        low, high = robot.joint_low.double().cpu(), robot.joint_high.double().cpu()
        q = low + torch.rand(n, low.numel(), generator=gen, dtype=torch.float64) * (high - low)
        tcp = robot.fk(q.to(robot.device, robot.dtype)).double().cpu()
        lo, hi = tcp.amin(0), tcp.amax(0)
        lo[2] = max(float(lo[2]), 0.0)
        return tuple(lo.tolist()), tuple(hi.tolist())
