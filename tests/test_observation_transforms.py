"""Transforms of what the networks read leave the planner alone: ObservationNorm, GoalRelative.

The planner, the demo buffer, the reward filter's look-ahead and the relabelling read the
task model's named state; only the networks read ``"observation"`` (and ``"goal_offset"``),
which the components build with the ``observation_transform`` they are given, as the env's
transforms do for interaction data.
"""

import copy

import pytest
import torch
from torch import nn
from torchrl.envs import Compose, ObservationNorm, TransformedEnv
from torchrl.modules import MLP, Actor, ValueOperator
from torchrl.objectives import DDPGLoss

from torchrl_silp import CollisionHandling, GoalRelative
from torchrl_silp.data import DemoReplayBuffer, GoalRelabelingReplayBuffer, MixedReplay, transition_keys
from torchrl_silp.envs import ReachEnv
from torchrl_silp.modules.networks import NextGoalOffsetQ
from torchrl_silp.objectives import SILPLoss
from torchrl_silp.planning import plan_demonstrations

STATE_KEYS = ("joint_position", "achieved_goal", "obstacle", "desired_goal")
NUM_ENVS, STEPS, SEED = 4, 40, 3
# per-feature shift and scale, far from the identity on every entry
LOC = torch.linspace(-0.5, 0.7, 15)
SCALE = torch.linspace(0.2, 3.0, 15)


def make_norm():
    return ObservationNorm(loc=LOC.clone(), scale=SCALE.clone(), in_keys=["observation"], standard_normal=True)


def normalised(model, state):
    """What ObservationNorm(standard_normal=True) makes of the model's flat observation, by hand."""
    return (model.observation(state) - LOC) / SCALE


def make_env(model, *extra, num_envs=NUM_ENVS, before=()):
    return TransformedEnv(
        ReachEnv(model, num_envs=num_envs, seed=SEED),
        Compose(CollisionHandling(2), *before, model.observation_transform(), *extra),
    )


def rollout(env):
    gen = torch.Generator().manual_seed(SEED)
    policy = lambda td: td.set("action", torch.rand(NUM_ENVS, 3, generator=gen) * 2 - 1)  # noqa: E731
    return env.rollout(STEPS, policy=policy, break_when_any_done=False)


@pytest.fixture(scope="module")
def rollouts(model):
    """The same seeded rollout without and with an ObservationNorm in the env."""
    return rollout(make_env(model)), rollout(make_env(model, make_norm()))


def plan(model, episodes, **kwargs):
    return plan_demonstrations(model, episodes, n_pairs=6, generator=torch.Generator().manual_seed(0), **kwargs)


def named_keys():
    return [*STATE_KEYS, "goal_joint_position", *[("next", k) for k in (*STATE_KEYS, "goal_joint_position")]]


OUTCOME_KEYS = ("action", ("next", "reward"), ("next", "done"), ("next", "terminated"), ("next", "success"),
                ("next", "collision"))


# ------------------------------------------------------------------ ObservationNorm
def test_the_env_normalises_its_observation_and_nothing_else(model, rollouts):
    plain, normed = rollouts
    for key in (*named_keys(), *OUTCOME_KEYS):
        assert torch.equal(plain[key], normed[key]), key
    assert plain["next", "collision"].any(), "the random rollout should collide (and be put back) at least once"
    torch.testing.assert_close(normed["observation"], normalised(model, normed))
    torch.testing.assert_close(normed["next", "observation"], normalised(model, normed["next"]))
    assert torch.equal(plain["observation"], model.observation(plain))
    assert not torch.isclose(plain["observation"], normed["observation"]).any()


def test_the_planner_makes_the_same_demonstrations(model, rollouts):
    plain, normed = rollouts
    a, b = plan(model, plain), plan(model, normed)
    assert len(a) > 20 and int(a["next", "done"].sum()) >= 4
    assert a.batch_size == b.batch_size
    for key in (*named_keys(), *OUTCOME_KEYS, ("next", "collision_reason")):
        assert torch.equal(a[key], b[key]), key
    # without an observation transform the demos carry the model's plain observation, whatever the env did
    assert torch.equal(b["observation"], model.observation(b))
    # with the env's observation transforms they carry the normalised one
    c = plan(model, normed, observation_transform=Compose(model.observation_transform(), make_norm()))
    for key in (*named_keys(), *OUTCOME_KEYS):
        assert torch.equal(a[key], c[key]), key
    torch.testing.assert_close(c["observation"], normalised(model, c))
    torch.testing.assert_close(c["next", "observation"], normalised(model, c["next"]))


def test_the_demo_buffer_stores_what_the_env_would_have_produced(model, rollouts):
    plain, normed = rollouts
    def planner_kwargs():
        return {"n_pairs": 6, "generator": torch.Generator().manual_seed(0)}

    transform = Compose(model.observation_transform(), make_norm())
    buffer = DemoReplayBuffer(model, observation_transform=transform, planner_kwargs=planner_kwargs())
    buffer.extend(normed)
    stored = buffer[: len(buffer)]
    reference = plan(model, plain)
    assert len(stored) == len(reference) > 0
    for key in (*STATE_KEYS, *[("next", k) for k in STATE_KEYS], *OUTCOME_KEYS[:4]):
        assert torch.equal(stored[key], reference[key]), key
    torch.testing.assert_close(stored["observation"], normalised(model, stored))
    # the normalised env, stepped from each demo state with the demo's action, observes what was stored
    K = len(stored)
    env = make_env(model, make_norm(), num_envs=K)
    td = reference.select(*STATE_KEYS, "goal_joint_position", "action")
    td["step_count"] = torch.zeros(K, 1, dtype=torch.long)
    out = env.step(td)["next"]
    for key in (*STATE_KEYS, "reward"):
        torch.testing.assert_close(out[key], stored["next", key], atol=1e-6, rtol=0)
    assert torch.equal(out["success"], reference["next", "success"])
    torch.testing.assert_close(out["observation"], stored["next", "observation"], atol=1e-5, rtol=1e-5)
    # a buffer without the norm stores the plain observation of the same states
    plain_buffer = DemoReplayBuffer(model, planner_kwargs=planner_kwargs())
    plain_buffer.extend(plain)
    assert torch.equal(plain_buffer[: len(plain_buffer)]["observation"], model.observation(stored))


class Unnormalise(nn.Module):
    """x * scale + loc: the actor of a normalised env sees what the plain actor sees."""

    def forward(self, x):
        return x * SCALE + LOC


def filter_pair(model, k=2):
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(15, 32), nn.Tanh(), nn.Linear(32, 3), nn.Tanh())
    critic = ValueOperator(MLP(in_features=18, out_features=1, num_cells=[16]), in_keys=["observation", "action"])
    plain = SILPLoss(DDPGLoss(Actor(net, in_keys=["observation"]), critic), model, filter="reward", k=k, gamma=0.9)
    actor = Actor(nn.Sequential(Unnormalise(), copy.deepcopy(net)), in_keys=["observation"])
    transform = Compose(model.observation_transform(), make_norm())
    normed = SILPLoss(
        DDPGLoss(actor, copy.deepcopy(critic)), model, filter="reward", k=k, gamma=0.9, observation_transform=transform
    )
    # the mismatch: the normalised actor, its look-ahead inputs built without the norm
    wrong = SILPLoss(DDPGLoss(copy.deepcopy(actor), copy.deepcopy(critic)), model, filter="reward", k=k, gamma=0.9)
    return plain, normed, wrong


def filter_batch(model, rollouts, transform):
    """Planned demos and interaction steps (flagged as demos too, for a mix of filter outcomes)."""
    plain, normed = rollouts
    episodes = normed if transform else plain
    keys = transition_keys(model)
    demos = plan(model, episodes, observation_transform=transform).select(*keys)
    steps = episodes[:, :10].reshape(-1).select(*keys, strict=False)
    steps["is_demo"] = torch.ones(len(steps), 1, dtype=torch.bool)
    return torch.cat([demos, steps])


def test_the_reward_filter_is_the_same_with_the_norm(model, rollouts):
    plain, normed, wrong = filter_pair(model)
    data_plain = filter_batch(model, rollouts, None)
    data_norm = filter_batch(model, rollouts, Compose(model.observation_transform(), make_norm()))
    for key in STATE_KEYS:
        assert torch.equal(data_plain[key], data_norm[key])
    assert not torch.isclose(data_plain["observation"], data_norm["observation"]).any()
    # the two actors agree on every state
    torch.testing.assert_close(plain._policy_action(data_plain), normed._policy_action(data_norm), atol=1e-5, rtol=0)
    mask_plain, mask_norm = plain.bc_filter(data_plain), normed.bc_filter(data_norm)
    assert 0 < int(mask_plain.sum()) < len(mask_plain), "the batch should exercise both filter outcomes"
    assert torch.equal(mask_plain, mask_norm)
    for x, y in zip(plain.lookahead_returns(data_plain), normed.lookahead_returns(data_norm)):
        torch.testing.assert_close(x, y, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(plain.bc_loss(data_plain)[0], normed.bc_loss(data_norm)[0], atol=1e-5, rtol=1e-5)
    # without the matching transform the look-ahead feeds the actor the wrong inputs
    assert not torch.allclose(wrong.lookahead_returns(data_norm)[1], normed.lookahead_returns(data_norm)[1])


def test_relabelling_rebuilds_the_normalised_observation(model, rollouts):
    _, normed = rollouts
    flat = normed.reshape(-1)  # env-major: each env's steps contiguous
    transform = Compose(model.observation_transform(), make_norm())
    rb = GoalRelabelingReplayBuffer(model, capacity=1000, her_ratio=1.0, observation_transform=transform)
    rb.extend(flat)
    torch.manual_seed(0)
    batch = rb.sample(64)
    stored = flat[batch["index"]]
    changed = (batch["desired_goal"] != stored["desired_goal"]).any(-1)
    assert changed.float().mean() > 0.9
    for td in (batch, batch["next"]):
        torch.testing.assert_close(td["observation"], normalised(model, td))
    # only the goal's entries of the normalised observation moved
    torch.testing.assert_close(batch["observation"][:, :12], stored["observation"][:, :12])
    assert not torch.isclose(batch["observation"][changed, 12:], stored["observation"][changed, 12:]).all(-1).any()


# ------------------------------------------------------------------ GoalRelative
def goal_relative(model):
    return Compose(GoalRelative(model), model.observation_transform())


def test_demos_carry_the_goal_offset(model, rollouts):
    plain, _ = rollouts
    demos = plan(model, plain, observation_transform=goal_relative(model))
    reference = plan(model, plain)
    for key in (*named_keys(), *OUTCOME_KEYS, "observation", ("next", "observation")):
        assert torch.equal(demos[key], reference[key]), key
    for td in (demos, demos["next"]):
        assert torch.equal(td["goal_offset"], td["desired_goal"] - td["achieved_goal"])
    # the last step of a demo ends within success_distance of its goal
    last = demos["next", "done"].squeeze(-1)
    assert (demos["next", "goal_offset"][last].norm(dim=-1) < model.success_distance).all()
    # stored with the named state when the buffer is told the networks read it
    buffer = DemoReplayBuffer(
        model, observation_transform=goal_relative(model), observation_keys=("observation", "goal_offset"),
        planner_kwargs={"n_pairs": 6, "generator": torch.Generator().manual_seed(0)},
    )
    buffer.extend(plain)
    stored = buffer[: len(buffer)]
    assert torch.equal(stored["goal_offset"], demos["goal_offset"])
    assert torch.equal(stored["next", "goal_offset"], demos["next", "goal_offset"])


class OffsetActor(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = nn.Linear(18, 3)

    def forward(self, observation, goal_offset):
        return torch.tanh(self.net(torch.cat([observation, 10 * goal_offset], -1)))


def test_look_ahead_builds_the_goal_offset_for_the_actor(model, rollouts):
    plain, _ = rollouts
    torch.manual_seed(1)
    module = OffsetActor()
    actor = Actor(module, in_keys=["observation", "goal_offset"])
    critic = ValueOperator(MLP(in_features=18, out_features=1, num_cells=[16]), in_keys=["observation", "action"])
    silp = SILPLoss(DDPGLoss(actor, critic), model, filter="reward", k=2, gamma=0.8,
                    observation_transform=goal_relative(model))
    data = plan(model, plain, observation_transform=goal_relative(model))[:12]
    r_demo, r_pi = silp.lookahead_returns(data)

    def pi(state):
        with torch.no_grad():
            return module(model.observation(state), state["desired_goal"] - state["achieved_goal"])

    def hand(r0, state):
        ret = r0
        for j in (1, 2):
            nxt = model.transition(state, pi(state))
            ret = ret + 0.8**j * model.reward(state, nxt).squeeze(-1)
            state = nxt
        return ret

    for i in range(len(data)):
        s0 = data.select(*STATE_KEYS)[i : i + 1]
        s1 = data["next"].select(*STATE_KEYS)[i : i + 1]
        want_demo = hand(data["next", "reward"][i], s1)
        s1_pi = model.transition(s0, pi(s0))
        want_pi = hand(model.reward(s0, s1_pi).squeeze(-1), s1_pi)
        torch.testing.assert_close(r_demo[i : i + 1], want_demo.reshape(1), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(r_pi[i : i + 1], want_pi.reshape(1), atol=1e-5, rtol=1e-5)


def test_goal_offset_networks_train_on_mixed_batches(model):
    env = make_env(model, before=(GoalRelative(),))
    episodes = rollout(env)
    assert torch.equal(episodes["goal_offset"], episodes["desired_goal"] - episodes["achieved_goal"])
    keys = ("observation", "goal_offset")
    demos = DemoReplayBuffer(model, observation_transform=goal_relative(model), observation_keys=keys,
                             planner_kwargs={"generator": torch.Generator().manual_seed(0)})
    mixed = MixedReplay(demos, demo_fraction=0.25, batch_size=32)
    mixed.extend(episodes)
    demos.extend(episodes)
    torch.manual_seed(0)
    batch = mixed.sample()
    assert int(batch["is_demo"].sum()) == 8
    for td in (batch, batch["next"]):
        assert torch.equal(td["goal_offset"], td["desired_goal"] - td["achieved_goal"])
    actor = Actor(OffsetActor(), in_keys=list(keys))
    q_net = NextGoalOffsetQ(MLP(in_features=15 + 3 + 3 + 3, out_features=1, num_cells=[16]), model, list(keys))
    critic = ValueOperator(q_net, in_keys=q_net.in_keys)
    silp = SILPLoss(DDPGLoss(actor, critic), model, filter="reward", observation_transform=goal_relative(model))
    out = silp(batch)
    total = out["loss_actor"] + out["loss_value"] + out["loss_bc"]
    assert torch.isfinite(total) and float(out["num_demos"]) == 8
    total.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
