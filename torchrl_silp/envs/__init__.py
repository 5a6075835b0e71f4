"""Environments: the batched TorchRL reach envs over task models and their Gymnasium twins.

The Gymnasium twins are registered (by ``import torchrl_silp``) as ``torchrl_silp/UR5eReach-v0`` and ``torchrl_silp/PandaReach-v0``.
"""

from torchrl_silp.envs.reach import COLLISION_TYPES, ReachEnv, UR5eReachEnv
from torchrl_silp.envs.gym import (
    ENV_ID,
    PANDA_ENV_ID,
    PandaReachGymEnv,
    ReachGymEnv,
    UR5eReachGymEnv,
)

__all__ = [
    "ReachEnv",
    "UR5eReachEnv",
    "COLLISION_TYPES",
    "ReachGymEnv",
    "UR5eReachGymEnv",
    "PandaReachGymEnv",
    "ENV_ID",
    "PANDA_ENV_ID",
]
