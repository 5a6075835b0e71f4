"""Hindsight relabelling on the task model's named keys: TorchRL's HERReplayBuffer, kept consistent."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torchrl.envs import Compose

from torchrl_silp import GoalRelative, UR5eReachEnv
from torchrl_silp.data import GoalRelabelingReplayBuffer

STATE_KEYS = ("joint_position", "achieved_goal", "obstacle", "desired_goal")

_ENVS: dict = {}


def make_env(collision_type: int, n_envs: int, steps: int):
    key = (collision_type, n_envs, steps)
    if key not in _ENVS:
        _ENVS[key] = UR5eReachEnv(num_envs=n_envs, seed=0, max_steps=steps, collision_type=collision_type)
    return _ENVS[key]


def episodes(seed: int, collision_type: int, n_envs: int = 6, steps: int = 20):
    """Random-action episodes, each env's contiguous and in time order (env-major flattening)."""
    env = make_env(collision_type, n_envs, steps)
    env.set_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    policy = lambda td: td.set("action", torch.rand(n_envs, 3, generator=gen) * 2 - 1)  # noqa: E731
    rollout = env.rollout(steps, policy=policy, break_when_any_done=False)
    # cut each env's row after its first done: what an episode assembler hands over
    done = rollout["next", "done"].squeeze(-1)
    alive = torch.ones_like(done)
    alive[:, 1:] = ~done[:, :-1].cumsum(-1).bool()
    flat = rollout.reshape(-1)[alive.reshape(-1)]
    episode = torch.arange(n_envs).unsqueeze(1).expand(n_envs, steps).reshape(-1)[alive.reshape(-1)]
    return env, flat, episode


def hand_reward(model, stored_collision, achieved, goal):
    """The paper's reward by hand: -10 on a collision, +1 within success_distance, else minus the distance."""
    dist = (achieved - goal).norm(dim=-1, keepdim=True)
    success = (dist < model.success_distance) & ~stored_collision
    reward = torch.where(stored_collision, -10.0, torch.where(success, 1.0, -dist))
    return reward, success


@settings(max_examples=6, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), collision_type=st.sampled_from([0, 2]))
def test_relabelled_batches_are_consistent(seed, collision_type):
    env, flat, episode = episodes(seed, collision_type)
    model = env.model
    assert flat["next", "collision"].any(), "the random episodes should collide at least once"
    rb = GoalRelabelingReplayBuffer(model, capacity=1000, her_ratio=1.0, collision_ends_episode=collision_type == 0)
    rb.extend(flat)
    torch.manual_seed(seed)
    batch = rb.sample(64)
    index = batch["index"]
    goal = batch["desired_goal"]
    # "future": the goal is the achieved goal reached at this step or a later one of the same episode
    reached = flat["next", "achieved_goal"]
    same_episode = episode.unsqueeze(0) == episode[index].unsqueeze(1)  # (batch, storage)
    later = torch.arange(len(flat)).unsqueeze(0) >= index.unsqueeze(1)
    matches = (reached.unsqueeze(0) == goal.unsqueeze(1)).all(-1)
    assert (matches & same_episode & later).any(1).all()
    assert (goal != flat["desired_goal"][index]).any(-1).float().mean() > 0.9
    # both named states and both observations carry the new goal, everything else is the stored transition
    assert torch.equal(batch["next", "desired_goal"], goal)
    for key in ("joint_position", "achieved_goal", "obstacle"):
        assert torch.equal(batch[key], flat[key][index]), key
        assert torch.equal(batch["next", key], flat["next", key][index]), key
    assert torch.equal(batch["observation"][:, 12:15], goal)
    assert torch.equal(batch["next", "observation"][:, 12:15], goal)
    assert torch.equal(batch["observation"][:, :12], flat["observation"][index, :12])
    assert torch.equal(batch["next", "observation"][:, :12], flat["next", "observation"][index, :12])
    assert torch.equal(batch["action"], flat["action"][index])
    # reward and termination as the env scores the relabelled transition: the stored collision
    # (type 2 put the arm back, so only the stored flag shows it) and the distance to the new goal
    stored_collision = flat["next", "collision"][index]
    reward, success = hand_reward(model, stored_collision, batch["next", "achieved_goal"], goal)
    torch.testing.assert_close(batch["next", "reward"], reward)
    terminated = success | (stored_collision if collision_type == 0 else torch.zeros_like(success))
    assert torch.equal(batch["next", "terminated"], terminated)
    assert torch.equal(batch["next", "done"], terminated | batch["next", "truncated"])
    assert not (batch["next", "truncated"] & terminated).any()
    assert torch.equal(batch["next", "truncated"], flat["next", "truncated"][index] & ~terminated)
    # a goal taken from the transition's own next achieved goal is always a success (unless it collided)
    own = (goal == reached[index]).all(-1, keepdim=True)
    assert (own & ~stored_collision).any()
    assert (batch["next", "reward"][own & ~stored_collision] == 1.0).all()


def test_no_relabelling_returns_the_stored_transitions():
    env, flat, _ = episodes(3, 2)
    rb = GoalRelabelingReplayBuffer(env, capacity=1000, her_ratio=0.0)
    rb.extend(flat)
    torch.manual_seed(0)
    batch = rb.sample(50)
    stored = flat[batch["index"]]
    keys = ("observation", ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated"),
            ("next", "truncated"), *STATE_KEYS, *[("next", k) for k in STATE_KEYS])
    for key in keys:
        assert torch.equal(batch[key], stored[key]), key


def test_her_ratio_is_the_relabelled_share():
    env, flat, _ = episodes(5, 2, n_envs=8, steps=30)
    rb = GoalRelabelingReplayBuffer(env.model, capacity=1000, her_ratio=0.8)
    rb.extend(flat)
    torch.manual_seed(0)
    batch = rb.sample(500)
    changed = (batch["desired_goal"] != flat["desired_goal"][batch["index"]]).any(-1)
    # the first int(0.8 n) rows are relabelled (a relabelled goal may coincide with the real one: rarely)
    assert not changed[400:].any()
    assert changed[:400].float().mean() > 0.9


@pytest.mark.parametrize("strategy", ["final", "episode"])
def test_strategies_draw_from_the_episode(strategy):
    env, flat, episode = episodes(7, 2)
    rb = GoalRelabelingReplayBuffer(env.model, capacity=1000, her_ratio=1.0, strategy=strategy)
    rb.extend(flat)
    torch.manual_seed(0)
    batch = rb.sample(64)
    index = batch["index"]
    same_episode = episode.unsqueeze(0) == episode[index].unsqueeze(1)
    matches = (flat["next", "achieved_goal"].unsqueeze(0) == batch["desired_goal"].unsqueeze(1)).all(-1)
    if strategy == "final":
        last = torch.tensor([int((episode == episode[i]).nonzero().max()) for i in index.tolist()])
        assert torch.equal(batch["desired_goal"], flat["next", "achieved_goal"][last])
    assert (matches & same_episode).any(1).all()


def test_goal_relative_offset_is_rebuilt():
    env, flat, _ = episodes(11, 2)
    model = env.model
    transform = Compose(GoalRelative(model), model.observation_transform())
    flat = transform(flat.clone())
    flat["next"] = transform(flat["next"])
    rb = GoalRelabelingReplayBuffer(model, capacity=1000, her_ratio=1.0, observation_transform=transform)
    rb.extend(flat)
    torch.manual_seed(0)
    batch = rb.sample(64)
    # the offset the networks read is that of the relabelled goal, at the root and under "next"
    for td in (batch, batch["next"]):
        assert torch.equal(td["goal_offset"], td["desired_goal"] - td["achieved_goal"])
        assert torch.equal(td["observation"][:, 12:15], td["desired_goal"])
    changed = (batch["desired_goal"] != flat["desired_goal"][batch["index"]]).any(-1)
    assert changed.any() and (batch["goal_offset"][changed] != flat["goal_offset"][batch["index"]][changed]).any()


@pytest.mark.parametrize(
    "kwargs,error,match",
    [
        ({"her_ratio": 1.5}, ValueError, "her_ratio"),
        ({"strategy": "past"}, ValueError, "strategy"),
        ({"capacity": 0}, ValueError, "capacity"),
        ({"collision_ends_episode": 1}, TypeError, "collision_ends_episode"),
    ],
)
def test_bad_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        GoalRelabelingReplayBuffer(make_env(2, 6, 20).model, **kwargs)
    with pytest.raises(TypeError, match="TaskModel"):
        GoalRelabelingReplayBuffer(object())
