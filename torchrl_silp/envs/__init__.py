"""Environments: the batched TorchRL reach env and its Gymnasium twin."""

from torchrl_silp.envs.reach import COLLISION_TYPES, UR5eReachEnv

__all__ = ["UR5eReachEnv", "COLLISION_TYPES"]
