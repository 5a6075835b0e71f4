"""RunningObservationNorm (torchrl_silp.transforms) and the recipes' ``network.normalize_observation``.

The statistics are checked against numpy's over the concatenated data (float64), the output against
the formula computed here, the env wiring with TorchRL's spec check, and a recipe run against the raw
observations its interaction buffer stored.
"""

from __future__ import annotations

import io
import types

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_silp import ReachEnv, RunningObservationNorm, UR5eReach
from torchrl_silp.data import FilledStorageCheckpointer
from torchrl_silp.data.demo_buffer import _load as load_checkpointed_buffer
from torchrl_silp.recipes import builders, checkpointing, sac_silp, update
from torchrl_silp.recipes.schema import ConfigError, check_config, load_config

CPU = torch.device("cpu")


def expected(x: np.ndarray, data: np.ndarray, clip: float = 5.0, eps: float = 1e-2) -> np.ndarray:
    """The normalised ``x`` under the float64 statistics of ``data`` (rows: samples)."""
    std = np.maximum(data.std(axis=0), eps)
    return np.clip((x - data.mean(axis=0)) / std, -clip, clip)


# ------------------------------------------------------------------ statistics
@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    sizes=st.lists(st.integers(1, 40), min_size=1, max_size=6),
    lead=st.sampled_from([(), (2,), (3, 2)]),  # leading dims of each batch besides its rows
    features=st.integers(1, 6),
    loc=st.floats(-20, 20),
    scale=st.floats(0.05, 20),
    seed=st.integers(0, 2**16),
)
def test_running_statistics_equal_numpy_s_over_all_batches(sizes, lead, features, loc, scale, seed):
    rng = np.random.default_rng(seed)
    batches = [rng.normal(loc, scale, size=(n, *lead, features)) for n in sizes]
    norm = RunningObservationNorm()
    for b in batches:
        norm.update(torch.as_tensor(b, dtype=torch.float32))
    data = np.concatenate([b.reshape(-1, features) for b in batches])
    assert norm.mean.dtype == norm.m2.dtype == norm.count.dtype == torch.float32
    assert int(norm.count) == len(data)
    tol = 1e-5 * (abs(loc) + scale)
    np.testing.assert_allclose(norm.mean.numpy(), data.mean(axis=0), rtol=0, atol=tol)
    np.testing.assert_allclose(norm.var.numpy(), data.var(axis=0), rtol=1e-4, atol=tol * scale)
    # the transform's output: the formula with numpy's statistics
    x = rng.normal(loc, 3 * scale, size=(7, features))
    td = norm(TensorDict({"observation": torch.as_tensor(x, dtype=torch.float32)}, batch_size=[7]))
    np.testing.assert_allclose(td["observation_normalized"].numpy(), expected(x, data), rtol=1e-4, atol=1e-4)


def test_output_is_clipped_and_the_std_floored_at_eps():
    norm = RunningObservationNorm(clip=2.0, eps=0.5)
    data = torch.tensor([[-1.0, 3.0], [1.0, 3.0]])  # std (1, 0): the second floored at 0.5
    norm.update(data)
    x = torch.tensor([[0.5, 3.2], [10.0, -100.0], [-1.5, 3.0]])
    out = norm(TensorDict({"observation": x}, batch_size=[3]))["observation_normalized"]
    torch.testing.assert_close(out, torch.tensor([[0.5, 0.4], [2.0, -2.0], [-1.5, 0.0]]))
    assert out[1].tolist() == [2.0, -2.0]  # exactly the bound
    np.testing.assert_allclose(out.numpy(), expected(x.numpy(), data.numpy(), clip=2.0, eps=0.5), atol=1e-6)


def test_before_any_update_the_output_is_the_clipped_input():
    norm = RunningObservationNorm()
    x = torch.tensor([[0.3, -7.0, 6.0]])
    out = norm(TensorDict({"observation": x}, batch_size=[1]))["observation_normalized"]
    assert out.tolist() == [[0.30000001192092896, -5.0, 5.0]]
    assert norm.mean.numel() == 0 and int(norm.count) == 0 and norm.std.numel() == 0


def test_update_changes_the_statistics_in_place_and_an_empty_batch_nothing():
    norm = RunningObservationNorm()
    norm.update(torch.randn(5, 3))
    mean, m2, count = norm.mean, norm.m2, norm.count
    before = mean.clone()
    norm.update(torch.randn(4, 3) + 10)
    assert norm.mean is mean and norm.m2 is m2 and norm.count is count  # what holds them sees the new values
    assert int(count) == 9 and not torch.equal(mean, before)
    norm.update(torch.empty(0, 3))
    assert int(norm.count) == 9
    with pytest.raises(ValueError, match="4 features, the statistics have 3"):
        norm.update(torch.zeros(2, 4))


def test_state_dict_round_trip_into_a_fresh_norm():
    norm = RunningObservationNorm()
    norm.update(torch.randn(100, 4) * 3 + 1)
    buf = io.BytesIO()
    torch.save(norm.state_dict(), buf)
    buf.seek(0)
    fresh = RunningObservationNorm()  # unsized: takes the saved size
    fresh.load_state_dict(torch.load(buf, weights_only=True))
    assert set(norm.state_dict()) == {"count", "mean", "m2"}
    for key, value in norm.state_dict().items():
        assert torch.equal(fresh.state_dict()[key], value), key
    x = TensorDict({"observation": torch.randn(6, 4) * 5}, batch_size=[6])
    assert torch.equal(fresh(x.clone())["observation_normalized"], norm(x.clone())["observation_normalized"])
    # an updated norm takes a smaller saved state too (here: none yet)
    fresh.load_state_dict(RunningObservationNorm().state_dict())
    assert fresh.mean.numel() == 0 and int(fresh.count) == 0


# ------------------------------------------------------------------ in an env
def test_in_an_env_it_passes_the_spec_check_and_normalises_resets_and_steps_with_the_current_statistics():
    model = UR5eReach()
    norm = RunningObservationNorm()
    env = TransformedEnv(ReachEnv(model, num_envs=6, seed=0), Compose(model.observation_transform(), norm))
    check_env_specs(env, seed=0)
    assert env.observation_spec["observation_normalized"].shape == env.observation_spec["observation"].shape
    torch.manual_seed(0)
    first = env.rollout(10, break_when_any_done=False)
    norm.update(first["observation"])
    data = first["observation"].reshape(-1, first["observation"].shape[-1]).double().numpy()
    second = env.rollout(10, break_when_any_done=False)
    for key in ("observation", ("next", "observation")):
        out_key = "observation_normalized" if key == "observation" else ("next", "observation_normalized")
        np.testing.assert_allclose(second[out_key].numpy(), expected(second[key].double().numpy(), data),
                                   rtol=1e-4, atol=1e-4)


def test_one_instance_in_two_chains_shares_its_statistics():
    model = UR5eReach()
    norm = RunningObservationNorm()
    env = TransformedEnv(ReachEnv(model, num_envs=4, seed=0), Compose(model.observation_transform(), norm))
    planner_side = Compose(model.observation_transform(), norm)  # a second parent: allowed
    td = env.reset()
    norm.update(torch.randn(20, td["observation"].shape[-1]))
    state = td.select(*model.state_keys)
    assert torch.equal(planner_side(state.clone())["observation_normalized"],
                       env.transform(td.clone())["observation_normalized"])
    assert env.reset()["observation_normalized"].abs().max() <= 5.0


# ------------------------------------------------------------------ the recipes
def test_off_by_default_nothing_changes(tiny_config):
    cfg = tiny_config()
    assert cfg.network.normalize_observation is False
    model = builders.make_model(cfg, CPU)
    assert builders.observation_norm(cfg, model) is None
    assert builders.observation_keys(cfg) == ["observation", "goal_offset"]
    transform = builders.make_observation_transform(cfg, model)
    assert not any(isinstance(t, RunningObservationNorm) for t in transform.transforms)
    env = builders.make_env(cfg, model, CPU, seed=0)
    assert "observation_normalized" not in env.reset().keys()


def test_the_switch_must_be_a_bool():
    cfg = OmegaConf.create(OmegaConf.to_container(load_config("sac_silp"), resolve=False))  # no schema: any type
    cfg.network.normalize_observation = "yes"
    with pytest.raises(ConfigError) as error:
        check_config(cfg)
    assert error.value.key == "network.normalize_observation"


def test_every_sampled_batch_is_normalised_with_the_current_statistics(tiny_config):
    cfg = tiny_config("network.normalize_observation=true", "optim.batch_size=32")
    model = builders.make_model(cfg, CPU)
    norm = builders.observation_norm(cfg, model)
    env = builders.make_env(cfg, model, CPU, seed=0)
    buffers = builders.make_buffers(cfg, model, CPU)
    with torch.no_grad():
        episodes = env.rollout(cfg.env.max_steps, break_when_any_done=False)  # normalised before any update
    buffers.extend(episodes)
    buffers.demo_buffer.extend(episodes)
    norm.update(episodes["observation"] * 2 + 1)  # statistics unlike those the stored values were made with
    data = (episodes["observation"] * 2 + 1).reshape(-1, episodes["observation"].shape[-1]).double().numpy()
    seen = []
    state = types.SimpleNamespace(compile_left=0)
    progress = types.SimpleNamespace(show=lambda **kw: None)
    stop = types.SimpleNamespace(requested=False)
    counters = {"updates": 0, "updates_owed": 0}
    update.run_updates(3, stop, lambda sample: seen.append(sample.clone()) or sample, buffers, None, None, counters,
                       state, progress, norm=norm)
    assert len(seen) == 3 and seen[0]["is_demo"].any() and not seen[0]["is_demo"].all()
    for sample in seen:
        for root in ((), ("next",)):
            raw = sample[(*root, "observation")].double().numpy()
            np.testing.assert_allclose(sample[(*root, "observation_normalized")].numpy(), expected(raw, data),
                                       rtol=1e-4, atol=1e-4)


def _interaction_observations(run_dir) -> np.ndarray:
    """The raw observations the run's checkpointed interaction buffer holds (float64)."""
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(5000), checkpointer=FilledStorageCheckpointer())
    load_checkpointed_buffer(buffer, run_dir / "checkpoint" / "buffers" / "interaction")  # as MixedReplay.loads
    obs = buffer.storage[: len(buffer)]["observation"]
    return obs.reshape(-1, obs.shape[-1]).double().numpy()


def test_a_run_normalises_with_statistics_of_the_collected_data_and_resume_restores_them(tmp_path, tiny_config):
    overrides = ("network.normalize_observation=true", "collector.init_random_frames=100", "optim.batch_size=16",
                 "eval.every_frames=200", "replay_buffer.size=5000", "replay_buffer.demo_size=5000",
                 "exploration.n_candidates=8", "network.hidden_sizes=[32,32]", "threads=1")
    run_dir = tmp_path / "run"
    state_of = lambda: torch.load(run_dir / "checkpoint" / "state.pt", weights_only=False)  # noqa: E731

    sac_silp.train(tiny_config(*overrides, "collector.total_frames=200"))
    state = state_of()
    stats, frames = state["observation_norm"], state["counters"]["frames"]
    assert frames == 200 and int(stats["count"]) == frames  # every interaction transition, once
    data = _interaction_observations(run_dir)  # collision_type 2 stores every transition, raw
    assert len(data) == frames
    np.testing.assert_allclose(stats["mean"].numpy(), data.mean(axis=0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose((stats["m2"] / stats["count"]).numpy(), data.var(axis=0), rtol=1e-3, atol=1e-6)
    # SILPLoss's look-ahead holds the same statistics
    assert torch.equal(state["loss"]["observation_transform.transforms.2.mean"], stats["mean"])

    # the networks read the normalised observation, and a rebuilt run normalises with its statistics
    cfg = tiny_config(*overrides, "collector.total_frames=200")
    model = builders.make_model(cfg, CPU)
    env = builders.make_env(cfg, model, CPU, seed=0)
    actor, loss, _ = checkpointing.load_trained_networks(cfg, model, env, run_dir / "checkpoint", CPU)
    assert actor.in_keys == ["observation_normalized", "goal_offset"]
    assert "observation_normalized" in loss.rl_loss.qvalue_network.in_keys
    assert torch.equal(builders.observation_norm(cfg, model).mean, stats["mean"])

    # resumed: the statistics go on from the checkpoint's (started afresh they would count 100)
    sac_silp.train(tiny_config(*overrides, "collector.total_frames=300", "resume=must"))
    after = state_of()["observation_norm"]
    data = _interaction_observations(run_dir)
    assert int(after["count"]) == len(data) == 300
    np.testing.assert_allclose(after["mean"].numpy(), data.mean(axis=0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose((after["m2"] / after["count"]).numpy(), data.var(axis=0), rtol=1e-3, atol=1e-6)


def test_a_run_saved_before_the_switch_existed_resumes(tmp_path, tiny_config):
    from torchrl_silp.recipes import start

    run_dir = tmp_path / "run"
    start.start_run(tiny_config())
    (run_dir / "checkpoint").mkdir()
    torch.save({}, run_dir / "checkpoint" / "state.pt")
    saved = (run_dir / "config.yaml").read_text()
    assert "normalize_observation: false" in saved
    (run_dir / "config.yaml").write_text(saved.replace("  normalize_observation: false\n", ""))
    assert checkpointing.check_resume(tiny_config("resume=true"), run_dir)
    with pytest.raises(ValueError, match="^network: is .* in the run being resumed"):
        checkpointing.check_resume(tiny_config("resume=true", "network.normalize_observation=true"), run_dir)
