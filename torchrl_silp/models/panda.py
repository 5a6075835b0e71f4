"""A Franka Emika Panda reach task among boxes on a table, written only against the task-model interface."""

from __future__ import annotations

import torch

from torchrl_silp.models.arm import ArmReach
from torchrl_silp.robots import Panda

__all__ = ["PandaReach"]


class PandaReach(ArmReach):
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
        robot: a :class:`~torchrl_silp.robots.Panda` to share; built from ``assets/panda.urdf`` by default.
        num_boxes: boxes on the table (>= 1), each the default box.
        boxes: each box's size range and region instead (:func:`~torchrl_silp.models.arm.box_specs`).
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

    robot_class = Panda
    config_dim = 7
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
        boxes=None,
        success_distance: float = 0.05,
        motion_resolution: float = 0.005,
        conservative: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__(
            robot, num_boxes=num_boxes, boxes=boxes, success_distance=success_distance, motion_resolution=motion_resolution,
            conservative=conservative, device=device, dtype=dtype,
        )
