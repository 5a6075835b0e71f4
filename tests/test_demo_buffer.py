"""DemoReplayBuffer and MixedReplay: exact split, flags, empty buffers, checkpoint round trip, planned demos."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp import UR5eReachEnv
from torchrl_silp.data import TRANSITION_KEYS, DemoReplayBuffer, MixedReplay, transition_keys
from torchrl_silp.planning import plan_demonstrations

STATE_KEYS = ("joint_position", "achieved_goal", "obstacle", "desired_goal")


@pytest.fixture(scope="module")
def env():
    return UR5eReachEnv(num_envs=8, seed=0, collision_type=1)


@pytest.fixture(scope="module")
def env_model(env):
    """The env's own task model (collision_type=1), the one its episodes were drawn with."""
    return env.model


@pytest.fixture(scope="module")
def episodes(env):
    env.set_seed(0)
    gen = torch.Generator().manual_seed(0)
    policy = lambda td: td.set("action", torch.rand(8, 3, generator=gen) * 2 - 1)  # noqa: E731
    return env.rollout(50, policy=policy, break_when_any_done=False)


def filled(env, episodes, n_demo_rows=100, demo_fraction=0.25, **kw):
    demos = DemoReplayBuffer(env.model, capacity=10_000)
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
    with pytest.raises(TypeError, match="TaskModel"):
        DemoReplayBuffer(object())
    with pytest.raises(ValueError, match="observation_transform"):
        DemoReplayBuffer(env, planner_kwargs={"observation_transform": None})
    with pytest.raises(ValueError, match="keys"):
        DemoReplayBuffer(env, keys="all")


def test_discarded_transitions_are_dropped(env, episodes):
    discard = episodes["next", "discard"]
    assert discard.any(), "the random rollout should collide at least once"
    mixed = MixedReplay(DemoReplayBuffer(env), interaction_capacity=10_000)
    mixed.extend(episodes)
    assert len(mixed.interaction_buffer) == episodes.numel() - int(discard.sum())
    assert mixed.discarded == int(discard.sum())


def test_collision_steps_are_stored_as_terminal_without_ending_the_episode():
    env = UR5eReachEnv(num_envs=8, seed=0, collision_type=2)
    gen = torch.Generator().manual_seed(1)
    policy = lambda td: td.set("action", torch.rand(8, 3, generator=gen) * 2 - 1)  # noqa: E731
    episodes = env.rollout(50, policy=policy, break_when_any_done=False).reshape(-1)
    collision = episodes["next", "collision"].clone()
    terminated, done = episodes["next", "terminated"].clone(), episodes["next", "done"].clone()
    assert collision.any() and (~collision).any(), "the random rollout should collide, and not always"
    assert not (terminated & collision).any(), "type 2 puts the arm back: the env's step is not terminal"

    mixed = MixedReplay(DemoReplayBuffer(env.model), interaction_capacity=10_000, collision_terminal=True)
    mixed.extend(episodes)
    stored = mixed.interaction_buffer[:]
    assert torch.equal(stored["next", "terminated"], terminated | collision)  # every row kept (type 2), in order
    assert torch.equal(stored["next", "done"], done)  # the episode boundaries stay the env's
    # the caller's data keeps the env's flags: the same episodes plan demonstrations afterwards
    assert torch.equal(episodes["next", "terminated"], terminated)

    plain = MixedReplay(DemoReplayBuffer(env.model), interaction_capacity=10_000)
    plain.extend(episodes)
    assert torch.equal(plain.interaction_buffer[:]["next", "terminated"], terminated)
    with pytest.raises(KeyError, match="collision"):
        mixed.extend(episodes.exclude(("next", "collision")))


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


def test_transition_keys(env_model):
    keys = transition_keys(env_model)
    assert keys[: len(TRANSITION_KEYS)] == TRANSITION_KEYS
    named = [*STATE_KEYS, *[("next", k) for k in STATE_KEYS]]
    assert set(keys) == set(TRANSITION_KEYS) | set(named) and len(keys) == len(set(keys))
    more = transition_keys(env_model, ("observation", "goal_offset"))
    assert set(more) == set(keys) | {"goal_offset", ("next", "goal_offset")}
    # the default buffer stores exactly these
    assert DemoReplayBuffer(env_model).keys == keys
    assert DemoReplayBuffer(env_model, observation_keys=("observation", "goal_offset")).keys == more
    assert DemoReplayBuffer(env_model, keys=None).keys is None


def test_demo_buffer_plans_from_episodes(env, env_model, episodes):
    gen = torch.Generator().manual_seed(3)
    demos = DemoReplayBuffer(env, capacity=100_000, batch_size=64, planner_kwargs={"n_pairs": 4, "generator": gen})
    assert demos.model is env_model
    index = demos.extend(episodes)
    assert len(demos) > 0 and demos.planning_time > 0
    # 8 rows of 50 steps, plus the episodes that ended early (a success or max_steps)
    assert demos.episodes_planned == 8 + int(episodes["next", "done"][:, :-1].sum())
    assert demos.demos_added == len(demos) == index.numel()
    # what is stored is what the planner makes of the episodes (same draw), keys selected
    planned = plan_demonstrations(env_model, episodes, n_pairs=4, generator=torch.Generator().manual_seed(3))
    assert len(planned) == len(demos)
    stored = demos[: len(demos)]
    assert set(stored.keys(True, True)) - {"index"} == set(transition_keys(env_model))
    for key in transition_keys(env_model):
        if key != "is_demo":
            assert torch.equal(stored[key], planned[key]), key
    batch = demos.sample()
    assert batch["is_demo"].all()
    # demo actions are feasible and their rewards are the model's own on the named states
    assert batch["action"].abs().max() <= 1.0
    s0, s1 = batch.select(*STATE_KEYS), batch["next"].select(*STATE_KEYS)
    torch.testing.assert_close(batch["next", "reward"], env_model.outcome(s0, s1)[0])
    dist = (s1["achieved_goal"] - s1["desired_goal"]).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(batch["next", "reward"], torch.where(dist < env_model.success_distance, 1.0, -dist))
    assert torch.equal(batch["observation"], env_model.observation(s0))
    assert torch.equal(batch["next", "observation"], env_model.observation(s1))
    # a demo ends with its successful step
    assert torch.equal(batch["next", "done"], batch["next", "terminated"])
    assert torch.equal(batch["next", "done"], dist < env_model.success_distance)


def test_mixed_batches_carry_the_named_state(env, env_model, episodes):
    mixed = MixedReplay(DemoReplayBuffer(env_model, planner_kwargs={"n_pairs": 2}), demo_fraction=0.25, batch_size=64)
    assert mixed.keys == transition_keys(env_model)
    mixed.extend(episodes)
    mixed.demo_buffer.extend(episodes)
    out = mixed.sample()
    assert int(out["is_demo"].sum()) == 16
    assert set(out.keys(True, True)) == set(transition_keys(env_model))
    # interaction rows are stored transitions (not discarded ones), with their named state intact
    flat = episodes.reshape(-1)
    flat = flat[~flat["next", "discard"].squeeze(-1)]
    rows = out[16:]
    match = (rows["observation"].unsqueeze(1) == flat["observation"].unsqueeze(0)).all(-1)
    match &= (rows["action"].unsqueeze(1) == flat["action"].unsqueeze(0)).all(-1)
    assert match.any(1).all()
    assert torch.equal(rows["observation"], env_model.observation(rows))
    assert torch.equal(rows["next", "observation"], env_model.observation(rows["next"]))


def _dir_bytes(path):
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def test_checkpoint_holds_contents_not_capacity(env, episodes, tmp_path):
    small = filled(env, episodes, n_demo_rows=77)
    small.dumps(tmp_path / "small")
    rows = len(small)
    huge = MixedReplay(DemoReplayBuffer(env, capacity=2_000_000), interaction_capacity=5_000_000)
    huge.extend(episodes)
    huge.demo_buffer.add_demonstrations(small.demo_buffer[:77])
    huge.dumps(tmp_path / "huge")
    # 7M rows of capacity, a few hundred of them filled: the checkpoint is the filled rows' size
    row_bytes = sum(v.element_size() * v[0].numel() for v in small.interaction_buffer[:1].values(True, True))
    assert _dir_bytes(tmp_path / "huge") < 2 * rows * row_bytes + 200_000
    assert abs(_dir_bytes(tmp_path / "huge") - _dir_bytes(tmp_path / "small")) < 50_000


def test_checkpoint_of_a_wrapped_circular_buffer(tmp_path):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_silp.data import FilledStorageCheckpointer

    def buffer():
        return TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4, checkpointer=FilledStorageCheckpointer())

    rb = buffer()
    rb.extend(TensorDict({"x": torch.arange(23.0)}, [23]))  # rows hold 20..22 then 13..19; the cursor is at row 3
    rb.dumps(tmp_path)
    restored = buffer()
    restored.loads(tmp_path)
    assert len(restored) == 10 and restored.storage.max_size == 10
    assert restored.storage[:10]["x"].tolist() == [20, 21, 22, 13, 14, 15, 16, 17, 18, 19]
    # the next write replaces the oldest row (13), as it would have in the original buffer
    rb.extend(TensorDict({"x": torch.tensor([99.0])}, [1]))
    restored.extend(TensorDict({"x": torch.tensor([99.0])}, [1]))
    assert restored.storage[:10]["x"].tolist() == rb.storage[:10]["x"].tolist() == [20, 21, 22, 99, 14, 15, 16, 17, 18, 19]


def test_a_checkpoint_loaded_into_a_filled_buffer_leaves_only_its_own_rows(tmp_path):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_silp.data import FilledStorageCheckpointer

    def buffer():
        return TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=64, checkpointer=FilledStorageCheckpointer())

    rb = buffer()
    rb.extend(TensorDict({"x": torch.arange(4.0)}, [4]))
    rb.dumps(tmp_path)
    filled = buffer()
    filled.extend(TensorDict({"x": 100 + torch.arange(9.0)}, [9]))
    filled.loads(tmp_path)
    # the length is the checkpoint's, not the 9 rows held before: sampling never reaches the rows beyond it
    assert len(filled) == 4 and filled.storage[:4]["x"].tolist() == [0, 1, 2, 3]
    assert set(filled.sample()["x"].tolist()) == {0, 1, 2, 3}


def test_checkpoint_written_by_torchrl_still_loads(tmp_path):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_silp.data import FilledStorageCheckpointer

    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(50))  # TorchRL's own checkpointer: all 50 rows
    plain.extend(TensorDict({"x": torch.arange(7.0)}, [7]))
    plain.dumps(tmp_path)
    restored = TensorDictReplayBuffer(storage=LazyTensorStorage(50), checkpointer=FilledStorageCheckpointer())
    restored.loads(tmp_path)
    assert len(restored) == 7 and restored.storage[:7]["x"].tolist() == list(range(7))
