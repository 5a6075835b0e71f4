"""Bad input at every public entry point: the right exception, naming the parameter, before any work."""

from __future__ import annotations

import pytest
import torch
from hydra.errors import ConfigCompositionException
from torch import nn
from torchrl.modules import MLP, Actor, ValueOperator
from torchrl.objectives import DDPGLoss

from torchrl_silp import ReachEnv, SILPLoss, UR5eReach, UR5eReachEnv, evaluate
from torchrl_silp.data import DemoReplayBuffer, MixedReplay
from torchrl_silp.geometry import aabb_from_center

MODEL = UR5eReach()
TASKS = MODEL.sample_tasks(4, torch.Generator().manual_seed(0))
STATE = TASKS.select(*MODEL.state_keys)


def _with(td, key, value):
    out = td.clone()
    out[key] = value
    return out


def _nan_like(t):
    return torch.full_like(t, float("nan"))


def _inverted(box):
    return box[..., [1, 0, 3, 2, 5, 4]]


def _silp_batch_without_is_demo():
    actor = Actor(nn.Sequential(nn.Linear(15, 3), nn.Tanh()), in_keys=["observation"])
    critic = ValueOperator(MLP(in_features=18, out_features=1, num_cells=[8]), in_keys=["observation", "action"])
    loss = SILPLoss(DDPGLoss(actor, critic), MODEL)
    data = UR5eReachEnv(num_envs=4, seed=0).rollout(3).reshape(-1)
    return lambda: loss(data)


def _env_step(action):
    env = UR5eReachEnv(num_envs=4, seed=0)
    td = env.reset()
    if action is not None:
        td["action"] = action
    return lambda: env.step(td)


CASES = [
    # (entry point, call, exception, words the message must hold)
    ("model.transition", lambda: MODEL.transition(STATE, _nan_like(torch.zeros(4, 3))), ValueError, "action"),
    ("model.transition", lambda: MODEL.transition(_with(STATE, "joint_position", _nan_like(STATE["joint_position"])),
                                                  torch.zeros(4, 3)), ValueError, "state['joint_position']"),
    ("model.transition", lambda: MODEL.transition(STATE, torch.zeros(4, 3, dtype=torch.long)), TypeError, "action"),
    ("model.reward", lambda: MODEL.reward(STATE, _with(STATE, "desired_goal", _nan_like(STATE["desired_goal"]))),
     ValueError, "next_state['desired_goal']"),
    ("model.step", lambda: MODEL.step(STATE.exclude("obstacle"), torch.zeros(4, 3)), KeyError, "obstacle"),
    ("model.collides", lambda: MODEL.collides(STATE["joint_position"], _inverted(TASKS["obstacle"])), ValueError,
     "obstacle"),
    ("model.collides", lambda: MODEL.collides(_nan_like(STATE["joint_position"]), TASKS["obstacle"]), ValueError,
     "config"),
    ("model.collides", lambda: MODEL.collides(torch.zeros(4, 2), TASKS["obstacle"]), ValueError, "config"),
    ("aabb_from_center", lambda: aabb_from_center(torch.zeros(3), torch.tensor([0.2, -0.1, 0.3])), ValueError, "size"),
    ("env.step", _env_step(_nan_like(torch.zeros(4, 3))), ValueError, "NaN"),
    ("env.step", _env_step(None), KeyError, "action"),
    ("evaluate", lambda: evaluate(None, n_tasks=4, model=MODEL), TypeError, "policy"),
    ("evaluate", lambda: evaluate(lambda td: td, n_tasks=0, model=MODEL), ValueError, "n_tasks"),
    ("SILPLoss.forward", _silp_batch_without_is_demo(), KeyError, "is_demo"),
    ("MixedReplay.sample", lambda: MixedReplay(DemoReplayBuffer(MODEL)).sample(-4), ValueError, "batch_size"),
    ("DemoReplayBuffer", lambda: DemoReplayBuffer(MODEL, planner_kwargs={"d": 0}), ValueError, "d must"),
    ("DemoReplayBuffer", lambda: DemoReplayBuffer(MODEL, planner_kwargs={"radius": 1}), TypeError, "radius"),
    ("ReachEnv", lambda: ReachEnv(MODEL, num_envs=-1), ValueError, "num_envs"),
    ("ReachEnv", lambda: ReachEnv("ur5e"), TypeError, "model"),
]


@pytest.mark.parametrize("entry,call,exc,words", CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_library_entry_points_reject_bad_input(entry, call, exc, words):
    with pytest.raises(exc) as err:
        call()
    assert words in str(err.value), f"{entry}: {err.value}"


def _train(tiny_config, *overrides):
    from torchrl_silp.recipes import sac_silp

    return sac_silp.train(tiny_config(*overrides))


@pytest.mark.skipif(torch.cuda.is_available(), reason="the case is a machine without CUDA")
def test_recipe_refuses_cuda_without_a_gpu(tmp_path, tiny_config):
    with pytest.raises(ValueError, match="device"):
        _train(tiny_config, "device=cuda")
    assert not (tmp_path / "run").exists()


def test_recipe_refuses_a_run_dir_that_is_a_file(tmp_path, tiny_config):
    path = tmp_path / "a_file"
    path.write_text("")
    with pytest.raises(ValueError, match="run_dir"):
        _train(tiny_config, f"run_dir={path}")


def test_recipe_refuses_a_non_integer_seed(tiny_config):
    with pytest.raises(ConfigCompositionException) as err:
        _train(tiny_config, "seed=abc")
    assert "seed" in f"{err.value} {err.value.__cause__}"


def test_replay_buffers_show_their_own_signature():
    import inspect

    from torchrl_silp.data import GoalRelabelingReplayBuffer

    assert list(inspect.signature(DemoReplayBuffer).parameters)[:2] == ["model", "capacity"]
    assert "her_ratio" in inspect.signature(GoalRelabelingReplayBuffer).parameters
