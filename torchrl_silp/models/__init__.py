"""Task models: what SILP+ needs from a task (f_s, f_r, collisions, goals), one per robot task."""

from torchrl_silp.models.base import (
    ACHIEVED_GOAL_KEY,
    CONFIG_KEY,
    DESIRED_GOAL_KEY,
    GOAL_CONFIG_KEY,
    TaskModel,
)
from torchrl_silp.models.ur5e import TASK_BRANCHES, WORKSPACE_EXIT_MODES, UR5eReach

__all__ = [
    "TaskModel",
    "UR5eReach",
    "CONFIG_KEY",
    "ACHIEVED_GOAL_KEY",
    "DESIRED_GOAL_KEY",
    "GOAL_CONFIG_KEY",
    "TASK_BRANCHES",
    "WORKSPACE_EXIT_MODES",
]
