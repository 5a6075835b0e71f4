"""Environments: the batched TorchRL reach envs over task models and their Gymnasium twins.

Importing this package registers the Gymnasium id ``torchrl_silp/UR5eReach-v0``.
"""

from torchrl_silp.envs.reach import COLLISION_TYPES, ReachEnv, UR5eReachEnv
from torchrl_silp.envs.gym import ENV_ID, UR5eReachGymEnv  # importing registers the Gymnasium id

__all__ = ["ReachEnv", "UR5eReachEnv", "COLLISION_TYPES", "UR5eReachGymEnv", "ENV_ID"]
