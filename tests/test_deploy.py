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


@pytest.mark.parametrize("guards", ["inputs", "all"])
def test_compiled_rollout_matches_the_eager_one(guards):
    model = UR5eReach()
    policy = tanh_policy(model, 0)
    eager = SingleTaskRollout(policy, model, max_steps=20, compile=False)
    compiled = SingleTaskRollout(policy, model, max_steps=20, compile=True, guards=guards)
    for seed in range(4):
        task = ReachEnv(model, num_envs=1, seed=200 + seed).reset()[0]
        a, b = eager(task), compiled(task)
        assert int(a["steps"]) == int(b["steps"]) and bool(a["collision"]) == bool(b["collision"])
        torch.testing.assert_close(a["joint_position"], b["joint_position"])


def test_two_compiled_rollouts_of_different_policies_each_run_their_own():
    """Under guards=inputs neither the policy's structure nor its weights are checked before a step; each
    rollout's compiled step is its own, and reads its policy's weights as they are now."""
    model = UR5eReach()
    wide, narrow = tanh_policy(model, 0), tanh_policy(model, 1)
    narrow.module[0], narrow.module[2] = nn.Linear(narrow.module[0].in_features, 8), nn.Linear(8, model.action_dim)
    task = ReachEnv(model, num_envs=1, seed=300).reset()[0]
    for policy in (wide, narrow):
        compiled = SingleTaskRollout(policy, model, max_steps=10)
        torch.testing.assert_close(compiled(task)["action"],
                                   SingleTaskRollout(policy, model, max_steps=10, compile=False)(task)["action"])
    with torch.no_grad():  # new weights, loaded in place: the compiled step reads them
        narrow.module[0].weight.mul_(-1.0)
    torch.testing.assert_close(compiled(task)["action"],
                               SingleTaskRollout(narrow, model, max_steps=10, compile=False)(task)["action"])
    with pytest.raises(AttributeError, match="policy"):
        compiled.policy = wide  # another policy needs another rollout


def test_bad_input_is_refused():
    model = UR5eReach()
    with pytest.raises(TypeError, match="policy"):
        SingleTaskRollout(None, model)
    with pytest.raises(ValueError, match="max_steps"):
        SingleTaskRollout(tanh_policy(model, 0), model, max_steps=0)
    with pytest.raises(ValueError, match="guards must be one of \\('all', 'inputs'\\), got 'none'"):
        SingleTaskRollout(tanh_policy(model, 0), model, guards="none")
    run = SingleTaskRollout(tanh_policy(model, 0), model, compile=False)
    with pytest.raises(ValueError, match="one task"):
        run(model.sample_tasks(2))
    with pytest.raises(KeyError, match="obstacle"):
        run(model.sample_tasks(1).exclude("obstacle"))
