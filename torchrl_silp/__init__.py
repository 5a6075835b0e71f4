"""torchrl_silp: SILP+ (self-imitation learning by planning plus) as TorchRL components."""

from torchrl_silp.data import DemoReplayBuffer, GoalRelabelingReplayBuffer, MixedReplay
from torchrl_silp.deploy import SingleTaskRollout
from torchrl_silp.envs import ReachEnv, UR5eReachEnv, UR5eReachGymEnv  # importing registers the Gymnasium ids
from torchrl_silp.eval import evaluate
from torchrl_silp.geometry import CollisionReason, sphere_box_distance
from torchrl_silp.models import PandaReach, TaskModel, UR5eReach, check_task_model
from torchrl_silp.panda import Panda
from torchrl_silp.modules import GPGuidedExploration
from torchrl_silp.objectives import SILPLoss
from torchrl_silp.planning import ExperienceRoadmap, plan_demonstrations
from torchrl_silp.robot import UR5e
from torchrl_silp.transforms import CollisionHandling, GoalRelative, PerceptionNoise

__all__ = [
    "SingleTaskRollout",
    "TaskModel",
    "check_task_model",
    "UR5eReach",
    "PandaReach",
    "UR5e",
    "Panda",
    "ReachEnv",
    "UR5eReachEnv",
    "UR5eReachGymEnv",
    "CollisionHandling",
    "GoalRelative",
    "PerceptionNoise",
    "CollisionReason",
    "sphere_box_distance",
    "ExperienceRoadmap",
    "plan_demonstrations",
    "DemoReplayBuffer",
    "MixedReplay",
    "GoalRelabelingReplayBuffer",
    "SILPLoss",
    "GPGuidedExploration",
    "evaluate",
]
__version__ = "0.2.0"
