"""torchrl_silp: SILP+ (self-imitation learning by planning plus) as TorchRL components."""

from torchrl_silp.data import DemoReplayBuffer, MixedReplay
from torchrl_silp.envs import UR5eReachEnv, UR5eReachGymEnv  # importing registers torchrl_silp/UR5eReach-v0
from torchrl_silp.eval import evaluate
from torchrl_silp.geometry import CollisionReason, sphere_box_distance
from torchrl_silp.modules import GPGuidedExploration
from torchrl_silp.objectives import SILPLoss
from torchrl_silp.planning import ExperienceRoadmap, plan_demonstrations
from torchrl_silp.robot import UR5e

__all__ = [
    "UR5e",
    "UR5eReachEnv",
    "UR5eReachGymEnv",
    "CollisionReason",
    "sphere_box_distance",
    "ExperienceRoadmap",
    "plan_demonstrations",
    "DemoReplayBuffer",
    "MixedReplay",
    "SILPLoss",
    "GPGuidedExploration",
    "evaluate",
]
__version__ = "0.1.0"
