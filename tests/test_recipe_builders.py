"""The recipe builders' networks, against independent computations."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

from test_kinematics import dh_tcp
from torchrl_silp import UR5eReachEnv

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))
from utils import NextTCPFeatureQ, make_actor_critic, make_env  # noqa: E402


def test_next_tcp_feature_is_the_model_next_tcp_to_goal():
    with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
        cfg = compose(config_name="sac_silp", overrides=["env.num_envs=4", "network.next_tcp_feature=true"])
    env = make_env(cfg, torch.device("cpu"), seed=0)
    _, critic = make_actor_critic(cfg, env, torch.device("cpu"))
    q_net = critic.module
    assert isinstance(q_net, NextTCPFeatureQ)
    # the env is the critic's model, not part of its parameters or state
    assert all(name.startswith("inner.") for name in q_net.state_dict())

    tasks = UR5eReachEnv(num_envs=64, seed=3).reset()
    obs = tasks["observation"]
    g = torch.Generator().manual_seed(0)
    action = (torch.rand(64, 3, generator=g) * 2.4 - 1.2).requires_grad_()  # some beyond [-1, 1]: clipped
    seen = {}
    handle = q_net.inner.register_forward_pre_hook(lambda module, args: seen.setdefault("args", args))
    value = critic(TensorDict(observation=obs, action=action, batch_size=[64]))["state_action_value"]
    handle.remove()

    # independent: next joints by the action scale, TCP by the closed-form DH of the wrist-following arm
    q_next = obs[:, :3].double() + action.detach().double().clamp(-1, 1) * UR5eReachEnv.ACTION_SCALE
    tcp_next, _ = dh_tcp(env.base_env.robot.full_joints(q_next).numpy())
    expected = obs[:, 12:15].double().numpy() - tcp_next
    feature = seen["args"][2]
    np.testing.assert_allclose(feature.detach().numpy(), expected, atol=2e-5)

    # the actor's gradient reaches the action through the model as well as directly
    grad_feature, = torch.autograd.grad(feature.pow(2).sum(), action, retain_graph=True)
    inside = action.detach().abs() < 1
    assert (grad_feature[inside] != 0).any() and (grad_feature[~inside] == 0).all()
    value.sum().backward()
    assert action.grad is not None and torch.isfinite(action.grad).all()


METHODS = sorted(p.stem for p in (RECIPES / "config" / "method").glob("*.yaml"))


def test_every_table1_learning_method_is_a_config():
    # the paper's Table 1 rows that train with the recipe loop, each a `method=` option
    from loop import validate

    expected = {
        # method: (algorithm, demos, bc, filter, exploration, her, demo_fraction)
        "sac": ("sac", False, False, "reward", "random", False, 0.25),
        "sac_her": ("sac", False, False, "reward", "random", True, 0.25),
        "sac_demon": ("sac", True, False, "reward", "random", False, "proportional"),
        "sac_silp": ("sac", True, True, "q", "random", False, 0.25),
        "sac_silp_plus": ("sac", True, True, "reward", "gp", False, 0.25),
    }
    expected.update({"ddpg" + name[3:]: ("ddpg",) + flags[1:] for name, flags in expected.items() if name != "sac_silp"})
    assert sorted(expected) == METHODS
    for method, flags in expected.items():
        with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
            cfg = compose(config_name="sac_silp", overrides=[f"method={method}"])
        validate(cfg)
        got = (cfg.algorithm, cfg.silp.demos, cfg.silp.bc, cfg.silp.filter, cfg.exploration.mode,
               cfg.replay_buffer.her, cfg.replay_buffer.demo_fraction)
        assert got == flags, method
        assert cfg.logger.exp_name == method
