"""Hindsight relabelling of UR5eReachEnv data: TorchRL's HERReplayBuffer with goals inside the observation."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp import UR5eReachEnv
from torchrl_silp.data import GoalRelabelingReplayBuffer


def episodes(seed: int, collision_type: int, n_envs: int = 6, steps: int = 20):
    """Random-action episodes, each env's contiguous and in time order (env-major flattening)."""
    env = UR5eReachEnv(num_envs=n_envs, seed=seed, max_steps=steps, collision_type=collision_type)
    torch.manual_seed(seed)
    rollout = env.rollout(steps, break_when_any_done=False)
    # cut each env's row after its first done: what an episode assembler hands over
    done = rollout["next", "done"].squeeze(-1)
    alive = torch.ones_like(done)
    alive[:, 1:] = ~done[:, :-1].cumsum(-1).bool()
    flat = rollout.reshape(-1)[alive.reshape(-1)]
    episode = torch.arange(n_envs).unsqueeze(1).expand(n_envs, steps).reshape(-1)[alive.reshape(-1)]
    return env, flat, episode


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000), collision_type=st.sampled_from([0, 2]))
def test_relabelled_batches_are_env_consistent(seed, collision_type):
    env, flat, episode = episodes(seed, collision_type)
    rb = GoalRelabelingReplayBuffer(env, capacity=1000, her_ratio=1.0)
    rb.extend(flat)
    batch = rb.sample(64)
    index = batch["index"]
    goal = batch["desired_goal"]
    # "future": the goal is the TCP reached at this step or a later one of the same episode
    tcp_next = flat["next", "observation"][:, 3:6]
    same_episode = episode.unsqueeze(0) == episode[index].unsqueeze(1)  # (batch, storage)
    later = torch.arange(len(flat)).unsqueeze(0) >= index.unsqueeze(1)
    matches = (tcp_next.unsqueeze(0) == goal.unsqueeze(1)).all(-1)
    assert (matches & same_episode & later).any(1).all()
    # both observations carry the new goal, everything else is the stored transition
    assert torch.equal(batch["observation"][:, 12:15], goal)
    assert torch.equal(batch["next", "observation"][:, 12:15], goal)
    assert torch.equal(batch["observation"][:, :12], flat["observation"][index, :12])
    assert torch.equal(batch["action"], flat["action"][index])
    # reward and termination as the env scores the relabelled transition
    stored_collision = flat["next", "collision"][index]
    if collision_type == 0:  # the next observation shows the collision itself
        reward, collision, success, _ = env.outcome(batch["observation"], batch["next", "observation"])
        assert torch.equal(collision, stored_collision)
    else:  # the arm was put back: the collision lives only in the stored reward
        collision = stored_collision
        dist = (batch["next", "observation"][:, 3:6] - goal).norm(dim=-1, keepdim=True)
        success = (dist < env.success_distance) & ~collision
        reward = torch.where(collision, -10.0, torch.where(success, 1.0, -dist))
    torch.testing.assert_close(batch["next", "reward"], reward)
    terminated = success | (collision if collision_type == 0 else torch.zeros_like(collision))
    assert torch.equal(batch["next", "terminated"], terminated)
    assert torch.equal(batch["next", "done"], terminated | batch["next", "truncated"])
    assert not (batch["next", "truncated"] & terminated).any()
    # a goal taken from the transition's own next TCP is always a success (unless it collided)
    own = (goal == tcp_next[index]).all(-1, keepdim=True)
    assert (batch["next", "reward"][own & ~collision] == 1.0).all()


def test_no_relabelling_returns_the_stored_transitions():
    env, flat, _ = episodes(3, 2)
    rb = GoalRelabelingReplayBuffer(env, capacity=1000, her_ratio=0.0)
    rb.extend(flat)
    batch = rb.sample(50)
    stored = flat[batch["index"]]
    for key in ("observation", ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated")):
        assert torch.equal(batch[key], stored[key]), key


def test_her_ratio_is_the_relabelled_share():
    env, flat, _ = episodes(5, 2, n_envs=8, steps=30)
    rb = GoalRelabelingReplayBuffer(env, capacity=1000, her_ratio=0.8)
    rb.extend(flat)
    batch = rb.sample(500)
    changed = (batch["desired_goal"] != flat["observation"][batch["index"], 12:15]).any(-1)
    # the first int(0.8 n) rows are relabelled (a relabelled goal may coincide with the real one: rarely)
    assert not changed[400:].any()
    assert changed[:400].float().mean() > 0.9


@pytest.mark.parametrize(
    "kwargs,match",
    [({"her_ratio": 1.5}, "her_ratio"), ({"strategy": "past"}, "strategy"), ({"capacity": 0}, "capacity")],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GoalRelabelingReplayBuffer(UR5eReachEnv(num_envs=1, seed=0), **kwargs)
