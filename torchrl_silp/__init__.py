"""torchrl_silp: SILP+ (self-imitation learning by planning plus) as TorchRL components."""

from torchrl_silp.envs.reach import UR5eReachEnv
from torchrl_silp.geometry import CollisionReason, sphere_box_distance
from torchrl_silp.robot import UR5e

__all__ = ["UR5e", "UR5eReachEnv", "CollisionReason", "sphere_box_distance"]
__version__ = "0.1.0"
