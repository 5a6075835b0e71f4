"""SingleTaskRollout: the same episode as evaluate's env rollout, eager and compiled."""

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_silp import SingleTaskRollout, evaluate
from torchrl_silp.envs import ReachEnv
from torchrl_silp.models import PandaReach, UR5eReach


def tanh_policy(model, seed: int, gain: float = 2.0) -> TensorDictModule:
    torch.manual_seed(seed)
    obs_dim = model.observation(model.sample_tasks(1)).shape[-1]
    net = nn.Sequential(nn.Linear(obs_dim, 32), nn.Tanh(), nn.Linear(32, model.action_dim), nn.Tanh())
    with torch.no_grad():
        net[-2].weight.mul_(gain)  # decisive actions: some episodes collide, some run to the end
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def env_episode(policy, model, seed: int, max_steps: int):
    """evaluate's rollout of test task ``seed`` (one task): the path and the outcome."""
    metrics, rollout = evaluate(policy, n_tasks=1, seed=seed, model=model, max_steps=max_steps, return_rollout=True)
    rollout = rollout[0]
    path = torch.cat([rollout[:1]["joint_position"], rollout["next", "joint_position"]])
    return path, metrics


@pytest.mark.parametrize("model_cls", [UR5eReach, PandaReach])
def test_eager_rollout_is_the_env_episode(model_cls):
    model = model_cls()
    outcomes = set()
    for seed in range(8):
        policy = tanh_policy(model, seed, gain=2.0 if seed % 2 else 0.5)
        task = ReachEnv(model, num_envs=1, seed=100 + seed).reset()[0]
        out = SingleTaskRollout(policy, model, max_steps=20, compile=False)(task)
        path, metrics = env_episode(policy, model, 100 + seed, 20)
        steps = int(out["steps"])
        # the env ran on after a collision (evaluate's rollout stops when every task is done: here, at it)
        assert torch.equal(out["joint_position"], path[: steps + 1])
        assert bool(out["collision"]) == (metrics["collision_rate"] == 1.0)
        assert bool(out["success"]) == (metrics["success_rate"] == 1.0)
        if not (out["collision"] or out["success"]):
            assert steps == 20  # it ran to the end
        outcomes.add((bool(out["collision"]), bool(out["success"])))
    assert (True, False) in outcomes and (False, False) in outcomes  # both kinds of episode were compared


def test_compiled_rollout_matches_the_eager_one():
    model = UR5eReach()
    policy = tanh_policy(model, 0)
    eager = SingleTaskRollout(policy, model, max_steps=20, compile=False)
    compiled = SingleTaskRollout(policy, model, max_steps=20, compile=True)
    for seed in range(4):
        task = ReachEnv(model, num_envs=1, seed=200 + seed).reset()[0]
        a, b = eager(task), compiled(task)
        assert int(a["steps"]) == int(b["steps"]) and bool(a["collision"]) == bool(b["collision"])
        torch.testing.assert_close(a["joint_position"], b["joint_position"])


def test_bad_input_is_refused():
    model = UR5eReach()
    with pytest.raises(TypeError, match="policy"):
        SingleTaskRollout(None, model)
    with pytest.raises(ValueError, match="max_steps"):
        SingleTaskRollout(tanh_policy(model, 0), model, max_steps=0)
    run = SingleTaskRollout(tanh_policy(model, 0), model, compile=False)
    with pytest.raises(ValueError, match="one task"):
        run(model.sample_tasks(2))
    with pytest.raises(KeyError, match="obstacle"):
        run(model.sample_tasks(1).exclude("obstacle"))
