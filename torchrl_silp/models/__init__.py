"""Task models: what SILP+ needs from a task (f_s, f_r, collisions, goals), one per robot task."""

from torchrl_silp.models.base import (
    ACHIEVED_GOAL_KEY,
    CONFIG_KEY,
    DESIRED_GOAL_KEY,
    GOAL_CONFIG_KEY,
    TaskModel,
    as_model,
)
from torchrl_silp.models.arm import ArmReach
from torchrl_silp.models.check import TaskModelError, check_task_model
from torchrl_silp.models.panda import PandaReach
from torchrl_silp.models.ur5e import TASK_BRANCHES, WORKSPACE_EXIT_MODES, UR5eReach
from torchrl_silp.models.urdf_reach import URDFReach

#: task models by the name configs use (``env.name`` of the recipes)
TASK_MODELS: dict[str, type[TaskModel]] = {"ur5e_reach": UR5eReach, "panda_reach": PandaReach, "urdf_reach": URDFReach}


def make_model(name: str, **kwargs) -> TaskModel:
    """The task model registered as ``name`` in :data:`TASK_MODELS`, built with ``kwargs``.

    Examples:
        >>> make_model("ur5e_reach", task_branch="any").task_branch
        'any'
    """
    if name not in TASK_MODELS:
        raise ValueError(f"name must be one of {sorted(TASK_MODELS)}, got {name!r}")
    return TASK_MODELS[name](**kwargs)

__all__ = [
    "TaskModel",
    "as_model",
    "ArmReach",
    "UR5eReach",
    "PandaReach",
    "URDFReach",
    "TASK_MODELS",
    "make_model",
    "check_task_model",
    "TaskModelError",
    "CONFIG_KEY",
    "ACHIEVED_GOAL_KEY",
    "DESIRED_GOAL_KEY",
    "GOAL_CONFIG_KEY",
    "TASK_BRANCHES",
    "WORKSPACE_EXIT_MODES",
]
