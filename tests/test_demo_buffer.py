"""DemoReplayBuffer and MixedReplay: exact split, flags, empty buffers, checkpoint round trip."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp import UR5eReachEnv
from torchrl_silp.data import TRANSITION_KEYS, DemoReplayBuffer, MixedReplay


@pytest.fixture(scope="module")
def env():
    return UR5eReachEnv(num_envs=8, seed=0, collision_type=1)


@pytest.fixture(scope="module")
def episodes(env):
    torch.manual_seed(0)
    return env.rollout(50, break_when_any_done=False)


def filled(env, episodes, n_demo_rows=100, demo_fraction=0.25, **kw):
    demos = DemoReplayBuffer(env, capacity=10_000)
    # ready-made transitions stand in for planned ones: the split logic is what is tested
    demos.add_demonstrations(episodes.reshape(-1)[:n_demo_rows].clone())
    mixed = MixedReplay(demos, interaction_capacity=10_000, demo_fraction=demo_fraction, **kw)
    mixed.extend(episodes)
    return mixed


@settings(max_examples=30, deadline=None, derandomize=True)
@given(batch=st.integers(1, 300), fraction=st.floats(0.0, 1.0))
def test_exact_split(env, episodes, batch, fraction):
    mixed = filled(env, episodes, demo_fraction=fraction)
    out = mixed.sample(batch)
    n_demo = round(fraction * batch)
    assert out.batch_size == (batch,)
    assert int(out["is_demo"].sum()) == n_demo
    # demos first, then interaction
    assert out["is_demo"][:n_demo].all() and not out["is_demo"][n_demo:].any()
    assert mixed.split(batch) == (n_demo, batch - n_demo)


def test_proportional_split_samples_as_one_buffer(env, episodes):
    # *-Demon: demos and interaction as if in one ordinary buffer, so the demo count of a
    # batch is Binomial(batch, demo share of all stored transitions)
    mixed = filled(env, episodes, n_demo_rows=100, demo_fraction="proportional")
    share = 100 / len(mixed)
    torch.manual_seed(0)
    counts = torch.tensor([mixed.split(200)[0] for _ in range(2000)], dtype=torch.float64)
    mean, var = 200 * share, 200 * share * (1 - share)
    assert abs(counts.mean() - mean) < 4 * (var / 2000) ** 0.5
    assert abs(counts.var() / var - 1) < 0.15
    out = mixed.sample(64)
    assert out.batch_size == (64,) and 0 <= int(out["is_demo"].sum()) <= 64


def test_demo_rows_come_from_the_demo_buffer(env, episodes):
    demos = DemoReplayBuffer(env, capacity=1000)
    marked = episodes.reshape(-1)[:50].clone()
    marked["action"] = torch.full_like(marked["action"], 0.777)
    demos.add_demonstrations(marked)
    mixed = MixedReplay(demos, interaction_capacity=10_000, demo_fraction=0.5)
    mixed.extend(episodes)
    out = mixed.sample(64)
    is_demo = out["is_demo"].squeeze(-1)
    assert (out["action"][is_demo] == 0.777).all()
    assert not (out["action"][~is_demo] == 0.777).all(-1).any()


def test_empty_demo_buffer_samples_interaction_only(env, episodes):
    mixed = MixedReplay(DemoReplayBuffer(env), interaction_capacity=10_000, demo_fraction=0.3, batch_size=40)
    mixed.extend(episodes)
    out = mixed.sample()
    assert out.batch_size == (40,) and not out["is_demo"].any()


def test_empty_interaction_buffer_samples_demos_only(env, episodes):
    demos = DemoReplayBuffer(env)
    demos.add_demonstrations(episodes.reshape(-1)[:30].clone())
    mixed = MixedReplay(demos, demo_fraction=0.3)
    assert mixed.sample(16)["is_demo"].all()


def test_both_empty_and_bad_arguments(env):
    mixed = MixedReplay(DemoReplayBuffer(env), interaction_capacity=10)
    with pytest.raises(RuntimeError, match="empty"):
        mixed.sample(4)
    with pytest.raises(ValueError, match="batch_size"):
        mixed.sample()
    with pytest.raises(ValueError, match="demo_fraction"):
        MixedReplay(DemoReplayBuffer(env), demo_fraction=1.5)
    with pytest.raises(ValueError, match="demo_fraction"):
        MixedReplay(DemoReplayBuffer(env), demo_fraction="uniform")
    with pytest.raises(ValueError, match="capacity"):
        DemoReplayBuffer(env, capacity=0)
    with pytest.raises(TypeError, match="env"):
        DemoReplayBuffer(object())


def test_discarded_transitions_are_dropped(env, episodes):
    discard = episodes["next", "discard"]
    assert discard.any(), "the random rollout should collide at least once"
    mixed = MixedReplay(DemoReplayBuffer(env), interaction_capacity=10_000)
    mixed.extend(episodes)
    assert len(mixed.interaction_buffer) == episodes.numel() - int(discard.sum())
    assert mixed.discarded == int(discard.sum())


def test_checkpoint_round_trip(env, episodes, tmp_path):
    mixed = filled(env, episodes, n_demo_rows=77, demo_fraction=0.4, batch_size=32)
    mixed.demo_buffer.planning_time = 1.25
    mixed.dumps(tmp_path / "ckpt")
    restored = MixedReplay(DemoReplayBuffer(env, capacity=10_000), interaction_capacity=10_000)
    restored.loads(tmp_path / "ckpt")
    assert len(restored.demo_buffer) == 77 and len(restored.interaction_buffer) == len(mixed.interaction_buffer)
    assert restored.demo_fraction == 0.4 and restored.batch_size == 32
    assert restored.demo_buffer.planning_time == 1.25
    n = len(mixed.interaction_buffer)
    a = mixed.interaction_buffer[:n]
    b = restored.interaction_buffer[:n]
    assert (a == b).all()
    assert (mixed.demo_buffer[:77] == restored.demo_buffer[:77]).all()
    # and it goes on: new data lands after the restored data, nothing is overwritten
    restored.extend(episodes[:1])
    assert len(restored.interaction_buffer) == n + episodes[:1].numel() - int(episodes[:1]["next", "discard"].sum())
    assert (restored.interaction_buffer[:n] == a).all()


def test_demo_buffer_plans_from_episodes(env, episodes):
    demos = DemoReplayBuffer(env, capacity=100_000, batch_size=64)
    demos.extend(episodes)
    assert len(demos) > 0 and demos.planning_time > 0
    assert demos.episodes_planned >= 8
    batch = demos.sample()
    assert batch["is_demo"].all()
    assert set(TRANSITION_KEYS) <= set(batch.keys(include_nested=True))
    # demo actions are feasible and their rewards are the env's own
    assert batch["action"].abs().max() <= 1.0
    torch.testing.assert_close(batch["next", "reward"], env.reward(batch["observation"], batch["next", "observation"]))
