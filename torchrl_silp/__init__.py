"""torchrl_silp: SILP+ (self-imitation learning by planning plus) as TorchRL components.

The public names below import on first use (PEP 562), so that ``import torchrl_silp`` and its light
submodules (the recipes' config checks) do not load torch and TorchRL until a component is asked
for. Importing the package registers the Gymnasium ids ``torchrl_silp/UR5eReach-v0`` and
``torchrl_silp/PandaReach-v0`` (their entry points import the envs when made).
"""

import importlib

import gymnasium as _gymnasium

# public name -> the module that defines it
_PUBLIC = {
    "SingleTaskRollout": "torchrl_silp.deploy",
    "TaskModel": "torchrl_silp.models",
    "check_task_model": "torchrl_silp.models",
    "UR5eReach": "torchrl_silp.models",
    "PandaReach": "torchrl_silp.models",
    "URDFReach": "torchrl_silp.models",
    "URDFArm": "torchrl_silp.robots",
    "UR5e": "torchrl_silp.robots",
    "Panda": "torchrl_silp.robots",
    "ReachEnv": "torchrl_silp.envs",
    "UR5eReachEnv": "torchrl_silp.envs",
    "UR5eReachGymEnv": "torchrl_silp.envs",
    "CollisionHandling": "torchrl_silp.transforms",
    "GoalRelative": "torchrl_silp.transforms",
    "PerceptionNoise": "torchrl_silp.transforms",
    "RunningObservationNorm": "torchrl_silp.transforms",
    "CollisionReason": "torchrl_silp.geometry",
    "sphere_box_distance": "torchrl_silp.geometry",
    "ExperienceRoadmap": "torchrl_silp.planning",
    "plan_demonstrations": "torchrl_silp.planning",
    "DemoReplayBuffer": "torchrl_silp.data",
    "MixedReplay": "torchrl_silp.data",
    "GoalRelabelingReplayBuffer": "torchrl_silp.data",
    "SILPLoss": "torchrl_silp.objectives",
    "GPGuidedExploration": "torchrl_silp.modules",
    "evaluate": "torchrl_silp.eval",
}
__all__ = list(_PUBLIC)
__version__ = "0.2.0"

GYM_IDS = {
    "torchrl_silp/UR5eReach-v0": "torchrl_silp.envs.gym:UR5eReachGymEnv",
    "torchrl_silp/PandaReach-v0": "torchrl_silp.envs.gym:PandaReachGymEnv",
}
for _id, _entry_point in GYM_IDS.items():
    if _id not in _gymnasium.registry:  # a reload must not register twice (gymnasium warns)
        _gymnasium.register(id=_id, entry_point=_entry_point)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'torchrl_silp' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value  # the next lookup is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
