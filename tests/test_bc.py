"""The behaviour-cloning baselines (recipes/bc.py): demonstrations, the fit, a run end to end, bad configs."""

from __future__ import annotations

import copy
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, ValidationError
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_silp import CollisionHandling, ReachEnv
from torchrl_silp.data import transition_keys

from torchrl_silp.recipes import bc, builders
from torchrl_silp.recipes.schema import load_config

RECIPES = Path(bc.__file__).parent
CPU = torch.device("cpu")
HAS_OMPL = importlib.util.find_spec("ompl") is not None


def greedy_expert(model):
    """A scripted expert: the best of 38 candidate actions by the task model's transition and reward.

    The reward is scored on where each candidate ends (``collision_flags`` of the next configuration),
    not along its swept motion as ``model.step`` does: ten times cheaper, and good enough to imitate.
    """
    gen = torch.Generator().manual_seed(0)
    candidates = torch.cat([torch.rand(32, 3, generator=gen) * 2 - 1, torch.eye(3), -torch.eye(3)])
    C = candidates.shape[0]

    def policy(td: TensorDict) -> TensorDict:
        batch = td.batch_size
        states = td.select(*model.state_keys).unsqueeze(-1).expand(*batch, C)
        nxt = model.transition(states, candidates.expand(*batch, C, 3))
        flags, _ = model.collision_flags(nxt[model.config_key], states.select(*model.scene_keys))
        reward = model.score(flags, nxt[model.achieved_goal_key], nxt[model.desired_goal_key])[0]
        return td.set("action", candidates[reward.squeeze(-1).argmax(-1)])

    return policy


def source_env(model, source_cfg, n: int, seed: int) -> TransformedEnv:
    """The env the source policy is rolled out in: collision type 0, its own input transforms."""
    return TransformedEnv(ReachEnv(model, num_envs=n, seed=seed),
                          Compose(CollisionHandling(0), builders.make_observation_transform(source_cfg, model)))


@pytest.fixture(scope="module")
def source_run(tmp_path_factory):
    """A finished SAC run dir: its evaluated (averaged) actor imitates the greedy expert, its online actor is untrained.

    Returns the run dir, the expert-imitating actor itself (not loaded from the dir) and the run's config.
    """
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("source_run")
    cfg = load_config("sac_silp", ["env.num_envs=4", "network.hidden_sizes=[64,64]", f"run_dir={root}"])
    model = builders.make_model(cfg, CPU)
    env = builders.make_env(cfg, model, CPU, seed=0)
    torch.manual_seed(0)
    actor, critic = builders.make_actor_critic(cfg, model, env, CPU)
    loss, _ = builders.make_loss(cfg, actor, critic, model, env)
    online = copy.deepcopy(loss.state_dict())
    # the expert's states and actions, then the actor's deterministic action fitted to them
    with torch.no_grad():
        data = source_env(model, cfg, 200, 123).rollout(50, greedy_expert(model), break_when_any_done=False)
    keys = builders.observation_keys(cfg)
    inputs, act = data.select(*keys).reshape(-1), data["action"].reshape(-1, 3)
    opt = torch.optim.Adam(actor.parameters(), lr=3e-3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(800):
        idx = torch.randint(act.shape[0], (256,), generator=gen)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            pred = actor(inputs[idx])["action"]
        fit = (pred - act[idx]).pow(2).mean()
        opt.zero_grad()
        fit.backward()
        opt.step()
    # what torch.optim.swa_utils.AveragedModel saves: the module's state under "module."
    averaged = {f"module.{k}": v.detach().clone() for k, v in actor.state_dict().items()}
    (root / "checkpoint").mkdir()
    torch.save({"loss": online, "averaged_actor": averaged}, root / "checkpoint" / "state.pt")
    OmegaConf.save(cfg, root / "config.yaml", resolve=True)
    return root, actor, cfg


def test_policy_demonstrations_are_the_successful_episodes(source_run, monkeypatch):
    root, expert, source_cfg = source_run
    monkeypatch.setattr(bc, "COLLECT_BATCH", 64)  # 150 tasks in batches of 64: the last one is cut
    model = builders.make_model(source_cfg, CPU)
    policy, policy_transform = bc.load_source_policy(root, model, CPU)
    assert policy.in_keys == ["observation", "goal_offset"]
    # the demonstrations keep what the learner reads (here the flat observation only), not what the source read
    demos, stats = bc.collect_policy_demonstrations(policy, model, 150, seed=5, policy_transform=policy_transform)

    # independently: the expert actor itself, stepped by hand on the same tasks (3 resets of one env of 64)
    env = source_env(model, source_cfg, 64, 5)
    batches = []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(3):
            td, steps = env.reset(), []
            for _ in range(50):
                td = env.step(expert(td))
                steps.append(td.clone())
                td = step_mdp(td)
            batches.append(torch.stack(steps, 1))
    ro = torch.cat(batches)[:150]
    done = ro["next", "done"].squeeze(-1)
    end = done.float().argmax(-1)  # every episode ends by step 50
    rows = torch.arange(150)
    success = ro["next", "success"].squeeze(-1)[rows, end]
    expected = success.nonzero().squeeze(-1)
    # the averaged actor was loaded (the untrained online one succeeds on none of these)
    assert 30 < expected.numel() < 150
    assert stats == {"n_attempted": 150, "n_kept": expected.numel(), "n_transitions": int((end[expected] + 1).sum()),
                     "success_rate": expected.numel() / 150}
    assert demos.shape[0] == stats["n_transitions"]
    assert set(demos.keys(True, True)) == {*transition_keys(model), "is_demo", "episode"}
    assert demos["is_demo"].all()
    assert torch.equal(demos["episode"].unique(), expected)
    for e in expected.tolist():
        ep = demos[demos["episode"] == e]
        steps = int(end[e]) + 1
        assert ep.shape[0] == steps
        # each kept episode ends in success, nothing before its end is done, and its transitions are the rollout's
        assert ep["next", "terminated"][-1].item() and ep["next", "reward"][-1].item() == 1.0
        assert not ep["next", "done"][:-1].any()
        torch.testing.assert_close(ep["action"], ro["action"][e, :steps])
        for key in ("observation", "joint_position", "achieved_goal", "desired_goal"):
            torch.testing.assert_close(ep["next", key], ro["next", key][e, :steps])
        torch.testing.assert_close(ep["observation"], ro["observation"][e, :steps])


BC_TINY = [
    "n_demos=100",
    "eval.n_tasks=50",
    "eval.every_updates=150",
    "checkpoint.every_updates=100",
    "optim.n_updates=300",
    "optim.batch_size=64",
    "network.hidden_sizes=[64,64]",
    "progress=false",
    "threads=1",
]


@pytest.fixture(scope="module")
def bc_run(source_run, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("bc") / "run"
    overrides = [*BC_TINY, f"source_run_dir={source_run[0]}", f"run_dir={run_dir}"]
    cfg = load_config("bc", overrides)
    return cfg, overrides, bc.run(cfg)


def test_bc_run_writes_a_consistent_summary(bc_run):
    cfg, _, summary = bc_run
    run_dir = Path(cfg.run_dir)
    assert summary == json.loads((run_dir / "summary.json").read_text())
    assert summary["method"] == "bc" and summary["source"] == "policy" and summary["seed"] == 0
    assert summary["env"] == "ur5e_reach"
    assert summary["episodes"] == 0 and summary["frames"] == 0 and summary["updates"] == 300
    cache = torch.load(run_dir / "demos.pt", weights_only=False)
    demos = cache["demos"]
    model = builders.make_model(cfg, CPU)
    # the demonstrations hold what the BC actor reads: the observation and the goal offset
    assert set(demos.keys(True, True)) == {*transition_keys(model, builders.observation_keys(cfg)), "is_demo", "episode"}
    torch.testing.assert_close(demos["goal_offset"], demos["desired_goal"] - demos["achieved_goal"])
    assert summary["n_demos_attempted"] == 100
    assert 0 < summary["n_demos_kept"] == demos["episode"].unique().numel() < 100
    assert summary["n_transitions"] == demos.shape[0]
    assert summary["collection_wall_s"] == cache["collection_wall_s"] > 0
    assert summary["train_wall_s"] == pytest.approx(summary["collection_wall_s"] + summary["bc_wall_s"])
    history = json.loads((run_dir / "history.json").read_text())["history"]
    assert [h["updates"] for h in history] == [150, 300]
    assert history[0]["train_wall_s"] < history[1]["train_wall_s"] == pytest.approx(summary["train_wall_s"])
    # the curve is on the validation tasks; the reported figure on the test tasks, read once at the end
    assert history[-1]["success_rate"] == summary["validation_success_rate"]
    assert summary["validation_seed"] == cfg.eval.seed != cfg.eval.test_seed == summary["test_seed"]
    assert OmegaConf.load(run_dir / "config.yaml").source_run_dir == cfg.source_run_dir

    # the reported success rate is that of the checkpointed BC network on the same test tasks
    actor = bc.make_bc_actor(cfg, model, CPU)
    assert actor.in_keys == builders.observation_keys(cfg)
    state = torch.load(run_dir / "checkpoint" / "state.pt", weights_only=False)
    bc.make_bc_loss(actor).load_state_dict(state["loss"])
    again = bc.evaluate(actor, n_tasks=50, seed=cfg.eval.test_seed, model=model,
                        observation_transform=builders.make_observation_transform(cfg, model))
    assert again["success_rate"] == summary["success_rate"]
    assert again["collision_rate"] == summary["test_collision_rate"]


def test_bc_fits_the_demonstrated_actions(bc_run):
    cfg, _, _ = bc_run
    run_dir = Path(cfg.run_dir)
    demos = torch.load(run_dir / "demos.pt", weights_only=False)["demos"]
    model = builders.make_model(cfg, CPU)
    torch.manual_seed(cfg.seed)  # the run's initial network
    untrained = bc.make_bc_actor(cfg, model, CPU)
    trained = bc.make_bc_actor(cfg, model, CPU)
    bc.make_bc_loss(trained).load_state_dict(torch.load(run_dir / "checkpoint" / "state.pt", weights_only=False)["loss"])
    inputs = demos.select(*builders.observation_keys(cfg))
    with torch.no_grad():
        mse = {name: (net(inputs.clone())["action"] - demos["action"]).pow(2).mean().item()
               for name, net in (("untrained", untrained), ("trained", trained))}
    assert mse["trained"] < 0.3 * mse["untrained"], mse


def test_resume_after_completion_does_not_collect_again(bc_run):
    cfg, overrides, summary = bc_run
    run_dir = Path(cfg.run_dir)
    cached = (run_dir / "demos.pt").stat().st_mtime_ns
    proc = subprocess.run([sys.executable, str(RECIPES / "bc.py"), *overrides, "resume=true"],
                          cwd=run_dir.parent, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "from the cache" in proc.stdout and "resumed from" in proc.stdout
    assert (run_dir / "demos.pt").stat().st_mtime_ns == cached
    again = json.loads((run_dir / "summary.json").read_text())
    for key in ("collection_wall_s", "bc_wall_s", "success_rate", "n_demos_kept", "n_transitions", "updates"):
        assert again[key] == summary[key], key
    assert len(json.loads((run_dir / "history.json").read_text())["history"]) == 2
    # resuming with other collection settings than the cache's is refused
    with pytest.raises(ValueError, match="n_demos"):
        bc.run(load_config("bc", [*overrides, "resume=true", "n_demos=101"]))
    # so is resuming with other network inputs than the checkpointed run's (the field is named)
    with pytest.raises(ValueError, match="^network: is .* in the run being resumed"):
        bc.run(load_config("bc", [*overrides, "resume=true", "network.goal_relative=false"]))


class Killed(Exception):
    """Stands for the kill of a run during its demonstration collection."""


def test_a_run_killed_during_collection_resumes_at_its_next_batch(source_run, tmp_path, monkeypatch):
    root = source_run[0]
    monkeypatch.setattr(bc, "COLLECT_BATCH", 32)  # 100 tasks: batches of 32, 32, 32 and 4
    real = bc.policy_demonstration_batches
    starts: list[int] = []

    def killed_after(n_batches: int | None):
        def batches(*args, start_episode=0, **kwargs):
            starts.append(start_episode)
            it = real(*args, start_episode=start_episode, **kwargs)

            def gen():
                for i, item in enumerate(it):
                    if i == n_batches:
                        raise Killed
                    yield item
            return gen()
        return batches

    def config(run_dir: Path, *more: str):
        return load_config("bc", [*BC_TINY, f"source_run_dir={root}", f"run_dir={run_dir}", *more])

    model = builders.make_model(config(tmp_path), CPU)
    whole_dir, cut_dir = tmp_path / "whole", tmp_path / "cut"
    whole_dir.mkdir(), cut_dir.mkdir()
    whole = bc.demonstrations(config(whole_dir), model, whole_dir, CPU)

    monkeypatch.setattr(bc, "policy_demonstration_batches", killed_after(2))
    with pytest.raises(Killed):
        bc.demonstrations(config(cut_dir), model, cut_dir, CPU)
    assert sorted(f.name for f in (cut_dir / "demos_partial").iterdir()) == ["batch_00000.pt", "batch_00001.pt"]
    assert not (cut_dir / "demos.pt").exists()
    # other collection settings than the saved batches' are refused, naming the setting
    with pytest.raises(ValueError, match="n_demos"):
        bc.demonstrations(config(cut_dir, "resume=true", "n_demos=101"), model, cut_dir, CPU)

    monkeypatch.setattr(bc, "policy_demonstration_batches", killed_after(None))
    starts.clear()
    resumed = bc.demonstrations(config(cut_dir, "resume=true"), model, cut_dir, CPU)
    assert starts == [64]  # the two saved batches were not collected again
    assert not (cut_dir / "demos_partial").exists()
    # the same demonstrations and stats as the collection that was never cut, nothing lost or repeated
    assert whole["stats"]["n_attempted"] == 100 and 0 < whole["stats"]["n_kept"] < 100
    assert resumed["stats"] == whole["stats"] and resumed["settings"] == whole["settings"]
    assert set(resumed["demos"].keys(True, True)) == set(whole["demos"].keys(True, True))
    for key in whole["demos"].keys(True, True):
        assert torch.equal(resumed["demos"][key], whole["demos"][key]), key
    assert torch.equal(resumed["demos"]["episode"].unique(), whole["demos"]["episode"].unique())
    saved = torch.load(cut_dir / "demos.pt", weights_only=False)
    assert saved["stats"] == resumed["stats"] and saved["collection_wall_s"] == resumed["collection_wall_s"] > 0

    # a fresh run (resume=false) drops the batches of a killed one
    monkeypatch.setattr(bc, "policy_demonstration_batches", killed_after(1))
    fresh_dir = tmp_path / "fresh"
    fresh_dir.mkdir()
    with pytest.raises(Killed):
        bc.demonstrations(config(fresh_dir), model, fresh_dir, CPU)
    monkeypatch.setattr(bc, "policy_demonstration_batches", killed_after(None))
    starts.clear()
    bc.demonstrations(config(fresh_dir), model, fresh_dir, CPU)
    assert starts == [0]


@pytest.mark.parametrize("override", ["n_demos=abc", "optim.lr=fast", "network.goal_relative=maybe", "seed=1.5"])
def test_wrong_types_are_rejected_by_the_schema(override):
    # hydra wraps the schema's error of a command-line override in a ConfigCompositionException
    with pytest.raises(ConfigCompositionException) as err:
        load_config("bc", [override])
    assert isinstance(err.value.__cause__, ValidationError)
    assert override.split("=")[0].split(".")[-1] in str(err.value.__cause__)


def test_unknown_fields_are_rejected_by_the_schema():
    with pytest.raises(ConfigCompositionException) as err:
        load_config("bc", ["optim.learning_rate=0.1"])
    assert isinstance(err.value.__cause__, (ConfigKeyError, ConfigAttributeError))
    assert "learning_rate" in str(err.value.__cause__)


@pytest.mark.parametrize(
    "override,name",
    [
        # checked by the recipe (no library component takes them)
        ("source=expert", "source"),
        ("source_run_dir=null", "source_run_dir"),
        ("source_run_dir=/nonexistent/run", "source_run_dir"),
        ("source_run_dir=EMPTY", "source_run_dir"),
        ("source_run_dir=OTHER_TASK", "env.name"),
        ("optim.n_updates=-1", "optim.n_updates"),
        ("optim.batch_size=0", "optim.batch_size"),
        ("eval.every_updates=0", "eval.every_updates"),
        ("checkpoint.every_updates=0", "checkpoint.every_updates"),
        # checked by the library where the values are used, naming its parameter
        ("n_demos=0", "n_episodes"),
        pytest.param("prm_budget_s=0", "budget_s",
                     marks=pytest.mark.skipif(not HAS_OMPL, reason="OMPL is not installed")),
        ("optim.lr=-1", "learning rate"),
        ("env.model.task_branch=back", "task_branch"),
        ("env.name=mars_rover", "name"),
        ("env.max_steps=0", "max_steps"),
        ("device=tpu", "device"),
    ],
)
def test_bad_config_is_rejected_before_work(tmp_path, source_run, override, name):
    if override == "source_run_dir=EMPTY":  # a dir with config.yaml but no checkpoint
        (tmp_path / "empty").mkdir()
        (tmp_path / "empty" / "config.yaml").write_text((source_run[0] / "config.yaml").read_text())
        override = f"source_run_dir={tmp_path / 'empty'}"
    if override == "source_run_dir=OTHER_TASK":  # a run of another task
        other = tmp_path / "other"
        (other / "checkpoint").mkdir(parents=True)
        source_cfg = OmegaConf.load(source_run[0] / "config.yaml")
        source_cfg.env.name = "panda_reach"
        OmegaConf.save(source_cfg, other / "config.yaml")
        (other / "checkpoint" / "state.pt").write_bytes((source_run[0] / "checkpoint" / "state.pt").read_bytes())
        override = f"source_run_dir={other}"
    if override.startswith("prm_budget_s"):
        override = ["source=prm", override]
    run_dir = tmp_path / "run"
    overrides = [f"source_run_dir={source_run[0]}", f"run_dir={run_dir}", "progress=false"]
    cfg = load_config("bc", [*overrides, *(override if isinstance(override, list) else [override])])
    with pytest.raises((ValueError, TypeError)) as err:
        bc.run(cfg)
    assert name in str(err.value)
    assert not (run_dir / "demos.pt").exists() and not (run_dir / "checkpoint").exists()


def test_a_source_without_successes_stops_the_run(tmp_path, source_run):
    # the source run without its averaged actor: its untrained online actor is loaded, and reaches no goal
    src = tmp_path / "online_only"
    (src / "checkpoint").mkdir(parents=True)
    (src / "config.yaml").write_text((source_run[0] / "config.yaml").read_text())
    state = torch.load(source_run[0] / "checkpoint" / "state.pt", weights_only=False)
    state["averaged_actor"] = None
    torch.save(state, src / "checkpoint" / "state.pt")
    cfg = load_config("bc", [*BC_TINY, "n_demos=20", f"source_run_dir={src}", f"run_dir={tmp_path / 'run'}"])
    with pytest.raises(RuntimeError, match="none of the 20 demonstration episodes succeeded"):
        bc.run(cfg)


@pytest.mark.skipif(not HAS_OMPL, reason="OMPL is not installed")
def test_prm_source_end_to_end(tmp_path):
    cfg = load_config("bc", ["source=prm", "n_demos=4", "prm_budget_s=1.0", "optim.n_updates=20",
                                "eval.every_updates=20", "eval.n_tasks=10", "network.hidden_sizes=[16]",
                                "progress=false", "threads=1", f"run_dir={tmp_path / 'run'}"])
    summary = bc.run(cfg)
    demos = torch.load(tmp_path / "run" / "demos.pt", weights_only=False)["demos"]
    model = builders.make_model(cfg, CPU)
    assert set(demos.keys(True, True)) >= {*transition_keys(model, builders.observation_keys(cfg)), "episode"}
    assert summary["source"] == "prm" and summary["n_demos_attempted"] == 4
    assert 0 < summary["n_demos_kept"] == demos["episode"].unique().numel() <= 4
    assert summary["n_transitions"] == demos.shape[0]
    # every kept episode ends in success, and only there
    done = demos["next", "done"].reshape(-1)
    assert int(done.sum()) == summary["n_demos_kept"]
    assert (demos["next", "reward"].reshape(-1)[done] == 1.0).all() and demos["next", "terminated"].reshape(-1)[done].all()
    last = torch.ones_like(done)
    last[:-1] = demos["episode"][1:] != demos["episode"][:-1]
    assert torch.equal(done, last)
