"""The training recipes end to end, with tiny overrides: smoke runs, resume after a kill, the averaged actor.

Config validation runs in-process: tests/test_recipe_builders.py."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_silp.data import EpisodeAssembler, FilledStorageCheckpointer
from torchrl_silp.data.demo_buffer import _load as load_checkpointed_buffer

RECIPES = Path(__file__).parents[1] / "recipes"

# seconds-long runs: 4 envs, 100 transitions per collector batch, a few gradient steps
TINY = [
    "env.num_envs=4",
    "collector.frames_per_batch=100",
    "collector.init_random_frames=100",
    "eval.n_tasks=8",
    "eval.every_frames=200",
    "optim.batch_size=16",
    "replay_buffer.size=5000",
    "replay_buffer.demo_size=5000",
    "exploration.n_candidates=8",
    "checkpoint.every_iters=1",
    "progress=false",
    "threads=1",
    "compile.compile=false",  # one test compiles (test_compiled_update_trains)
]
# the Panda reach task through the same recipe, no code of its own
PANDA = ["env=panda_reach", "env.num_envs=4"]


def run_recipe(script: str, run_dir: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(RECIPES / script), *TINY, f"run_dir={run_dir}", *overrides]
    return subprocess.run(cmd, cwd=run_dir.parent, capture_output=True, text=True, timeout=timeout)


def summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def load_buffer(path: Path) -> TensorDictReplayBuffer:
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(5000), checkpointer=FilledStorageCheckpointer())
    load_checkpointed_buffer(buffer, path)  # as MixedReplay.loads does (a buffer that held nothing is marked empty)
    return buffer


@pytest.mark.parametrize(
    "script,overrides,bc,demos",
    [
        ("sac_silp.py", [], True, True),
        ("ddpg_silp.py", [], True, True),
        # the plain (s, a) Q-network, without the model's next TCP (the default feeds it)
        ("sac_silp.py", ["network.next_tcp_feature=false"], True, True),
        # plain SAC: SILP+ off, no recovery exploration
        ("sac_silp.py", ["silp.demos=false", "silp.bc=false", "exploration.mode=none"], False, False),
    ],
)
def test_recipe_smoke(tmp_path, script, overrides, bc, demos):
    run_dir = tmp_path / "run"
    proc = run_recipe(script, run_dir, "collector.total_frames=300", *overrides)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = summary(run_dir)
    assert out["frames"] == 300
    assert out["algorithm"] == ("ddpg" if script.startswith("ddpg") else "sac")
    assert out["silp_bc"] is bc and out["silp_demos"] is demos
    # training starts once init_random_frames are collected (TorchRL recipes' rule):
    # 3 batches of 100 at 0.25 updates per frame
    assert out["updates"] == 3 * 25
    assert out["success_rate"] * 8 == round(out["success_rate"] * 8)  # a share of the 8 test tasks
    # the test tasks split by the straight path (tests/test_eval.py): the two kinds' successes make up the whole
    free, parts = out["test_free_task_share"], (out["test_free_success_rate"], out["test_blocked_success_rate"])
    assert free * 8 == round(free * 8)
    solved = sum(share * rate for share, rate in zip((free, 1 - free), parts) if rate is not None)
    assert solved == pytest.approx(out["success_rate"])
    # SAC's policy on the test tasks with sampled actions too; DDPG's is deterministic
    sampling = out["sampling_success_rate"]
    assert (sampling is None) is script.startswith("ddpg") and (sampling is None or sampling * 8 == round(sampling * 8))
    assert (out["demos_stored"] > 0) is demos
    assert out["rollout_time_per_episode_s"] > 0
    for name in ("learning_curve.png", "test_rollouts.png", "history.json"):
        assert (run_dir / name).stat().st_size > 0
    history = json.loads((run_dir / "history.json").read_text())["history"]
    assert [h["frames"] for h in history] == [200, 300]
    # the CSV logger wrote the training and evaluation metrics
    scalars = next((run_dir / "logs").rglob("scalars"))
    assert (scalars / "eval" / "success_rate.csv").exists()
    assert (scalars / "train" / "collisions.csv").exists()
    if bc:
        assert (scalars / "train" / "loss_bc.csv").exists()
    printed = proc.stdout
    assert "success_rate" in printed and "planning_share" in printed
    if script == "sac_silp.py" and not overrides:
        # the failure analysis reads the same checkpoint and agrees with the run's own evaluation
        diag = subprocess.run(
            [sys.executable, str(RECIPES / "diagnose.py"), str(run_dir), *TINY],
            cwd=tmp_path, capture_output=True, text=True, timeout=300,
        )
        assert diag.returncode == 0, diag.stderr[-3000:]
        lines = diag.stdout.splitlines()
        # the default config evaluates an average of the actor: diagnose looks at that policy
        assert lines[0].startswith("policy: the averaged actor")
        first = lines[1].split()
        assert first[:2] == ["outcomes:", "success"]
        # diagnose.py rolls out all 1000 test tasks (the run evaluated 8 of them): a share of 1000
        assert len(first[2].split(".")[-1]) == 3
        assert "critic on the demos buffer" in diag.stdout and "random policy" in diag.stdout
        # the default tasks all start in the front IK branch
        assert "start in the front branch: 1000 tasks" in diag.stdout
        assert "shoulder-flipped" not in diag.stdout
        # the demonstrations' analysis reads the run's validation tasks (its 8), never the test ones
        demos = subprocess.run(
            [sys.executable, str(RECIPES / "diagnose_demos.py"), str(run_dir), *TINY],
            cwd=tmp_path, capture_output=True, text=True, timeout=300,
        )
        assert demos.returncode == 0, demos.stderr[-3000:]
        assert "8 validation tasks" in demos.stdout and "the test tasks are not read" in demos.stdout
        yields = [line for line in demos.stdout.splitlines() if "sampled nodes per episode (mean" in line]
        assert len(yields) == 3
        for line in yields:  # shares of the 8 episodes
            share = float(line.split("a path in ")[1].split()[0])
            assert share * 8 == round(share * 8)
        costs = [line for line in demos.stdout.splitlines() if "ms of planning per episode" in line]
        assert len(costs) == 3
        for line in costs:  # random pairs among the visited nodes always give some; a demonstration is a step or more
            transitions = float(line.split("sampled nodes per episode: ")[1].split()[0])
            length = float(line.split("transitions per episode, ")[1].split()[0])
            assert transitions > 0 and length >= 1
        assert "demonstration buffer:" in demos.stdout and "critic on" in demos.stdout


@pytest.mark.parametrize("method", ["sac_her", "ddpg_demon"])
def test_table1_baselines_train(tmp_path, method):
    run_dir = tmp_path / "run"
    proc = run_recipe("sac_silp.py", run_dir, "collector.total_frames=300", f"method={method}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = summary(run_dir)
    assert out["method"] == method and out["frames"] == 300
    assert out["her"] is (method == "sac_her") and out["silp_bc"] is False
    assert (out["demos_stored"] > 0) is (method == "ddpg_demon")
    ckpt = run_dir / "checkpoint"
    interaction = load_buffer(ckpt / "buffers" / "interaction")
    if method == "sac_her":
        # hindsight relabelling stores whole episodes only: the unfinished ones wait in the checkpoint
        assembler = EpisodeAssembler()
        assembler.load_state_dict(torch.load(ckpt / "state.pt", weights_only=False)["assembler"])
        n_pending = assembler.num_pending
        assert len(interaction) + n_pending == 300
        assert bool(interaction.storage[len(interaction) - 1]["next", "done"])
        # no update before the first episode ended (the first 100-frame batch ends none: 25 steps of 50)
        assert 50 <= out["updates"] <= 75
    else:
        assert len(interaction) == 300 and out["updates"] == 75


def logged_steps(run_dir: Path) -> dict[str, list[int]]:
    """The steps of every CSV scalar log of a run: ``{"train/episodes": [100, 200, ...], ...}``."""
    root = run_dir / "logs" / "sac_silp_plus_ext" / "scalars"  # the default config's exp_name
    return {str(p.relative_to(root).with_suffix("")): [int(row.split(",")[0]) for row in p.read_text().splitlines()]
            for p in sorted(root.rglob("*.csv"))}


def wait_for(proc: subprocess.Popen, condition, what: str, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert proc.poll() is None, f"the run ended before {what}: {proc.stderr.read()[-3000:]}"
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.2)


def saved_counters(ckpt: Path) -> dict | None:
    try:
        return torch.load(ckpt / "state.pt", weights_only=False)["counters"]
    except (FileNotFoundError, RuntimeError, EOFError, KeyError):
        return None


def start_run(run_dir: Path, *overrides: str) -> subprocess.Popen:
    cmd = [sys.executable, str(RECIPES / "sac_silp.py"), *TINY, f"run_dir={run_dir}", *overrides]
    return subprocess.Popen(cmd, cwd=run_dir.parent, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_kill_at_a_random_time_then_resume_loses_and_repeats_nothing(tmp_path):
    """kill -9 at a random point after the first checkpoint (saved by time: every_iters is out of
    reach), then resume: counters, buffer contents and logs continue as if never killed."""
    run_dir, rng = tmp_path / "run", np.random.default_rng()
    ckpt = run_dir / "checkpoint"
    delay = float(rng.uniform(0.0, 4.0))
    proc = start_run(run_dir, "collector.total_frames=100000", "checkpoint.every_iters=100000", "checkpoint.every_s=1.5")
    try:
        wait_for(proc, lambda: saved_counters(ckpt) is not None, "checkpoint")
        time.sleep(delay)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    # what the killed run had saved last (a kill between save_checkpoint's two renames leaves ".old")
    found = ckpt if (ckpt / "state.pt").exists() else ckpt.with_name("checkpoint.old")
    before = saved_counters(found)
    assert before is not None and before["iterations"] < 100000, f"(kill {delay:.2f} s after the first checkpoint)"
    interaction = load_buffer(found / "buffers" / "interaction")
    demos = load_buffer(found / "buffers" / "demos")
    n_inter, n_demo = len(interaction), len(demos)
    assert n_inter == before["frames"] > 0

    target = before["frames"] + 300
    resumed = run_recipe("sac_silp.py", run_dir, f"collector.total_frames={target}", "resume=must")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resumed from {ckpt}" in resumed.stdout and f"{before['frames']} frames" in resumed.stdout
    after = torch.load(ckpt / "state.pt", weights_only=False)["counters"]
    assert after["frames"] == target
    assert after["iterations"] == before["iterations"] + 3
    assert after["updates"] == before["updates"] + 3 * 25
    assert after["episodes"] >= before["episodes"] and after["collisions"] >= before["collisions"]
    # every stored transition is still there, in place, and each new one once
    interaction_after = load_buffer(ckpt / "buffers" / "interaction")
    demos_after = load_buffer(ckpt / "buffers" / "demos")
    assert len(interaction_after) == target
    assert (interaction_after.storage[:n_inter] == interaction.storage[:n_inter]).all()
    assert len(demos_after) >= n_demo
    if n_demo:  # (a checkpoint saved before the first planned episode holds no demos)
        assert (demos_after.storage[:n_demo] == demos.storage[:n_demo]).all()
    # each batch logged exactly once, in order, the killed run's rows after its checkpoint dropped
    steps = logged_steps(run_dir)
    assert steps["train/episodes"] == list(range(100, target + 1, 100))
    assert all(s == sorted(set(s)) for s in steps.values())
    assert steps["eval/success_rate"] == list(range(200, target + 1, 200))
    assert summary(run_dir)["frames"] == target


def test_sigterm_saves_then_stops_and_resume_continues(tmp_path):
    run_dir = tmp_path / "run"
    ckpt = run_dir / "checkpoint"
    episodes_log = run_dir / "logs" / "sac_silp_plus_ext" / "scalars" / "train" / "episodes.csv"
    proc = start_run(run_dir, "collector.total_frames=100000", "checkpoint.every_iters=100000", "checkpoint.every_s=1e6")
    try:
        wait_for(proc, lambda: episodes_log.exists() and len(episodes_log.read_text().splitlines()) >= 2, "logged batch")
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert "SIGTERM: stopping at the next update" in out and "resume=true" in out.splitlines()[-1]
    assert "Traceback" not in err
    # the checkpoint is the state after the last logged batch (its updates owed, if the stop cut them short)
    counters = saved_counters(ckpt)
    frames = counters["frames"]
    assert counters["updates"] + counters["updates_owed"] == 25 * counters["iterations"]
    assert logged_steps(run_dir)["train/episodes"] == list(range(100, frames + 1, 100))
    assert not (run_dir / "summary.json").exists()
    resumed = run_recipe("sac_silp.py", run_dir, f"collector.total_frames={frames + 100}", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert logged_steps(run_dir)["train/episodes"] == list(range(100, frames + 101, 100))
    assert summary(run_dir)["updates"] == 25 * (frames + 100) // 100


def test_sigterm_in_the_middle_of_a_batch_s_updates_stops_within_seconds_and_resume_owes_nothing(tmp_path):
    """500 updates a batch (seconds, many times the stop's allowance): the stop comes at the next update,
    not at the batch's end; the resumed run makes the updates the stop cut short, then goes on, each counter
    and log row once."""
    run_dir = tmp_path / "run"
    ckpt = run_dir / "checkpoint"
    many = ("optim.utd_ratio=5", "collector.total_frames=300", "eval.every_frames=100000")
    proc = start_run(run_dir, *many)
    try:
        wait_for(proc, lambda: saved_counters(ckpt) is not None, "checkpoint")
        time.sleep(2.0)  # into the second batch's updates
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - sent
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert took < 10, f"{took:.1f} s from SIGTERM to exit"
    assert "Traceback" not in err
    counters = saved_counters(ckpt)
    assert counters["frames"] == 200 and 0 < counters["updates_owed"] <= 500
    assert counters["updates"] + counters["updates_owed"] == 1000
    resumed = run_recipe("sac_silp.py", run_dir, *many, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    done = summary(run_dir)
    assert done["frames"] == 300 and done["updates"] == 1500
    assert saved_counters(ckpt)["updates_owed"] == 0
    assert len(load_buffer(ckpt / "buffers" / "interaction")) == 300
    steps = logged_steps(run_dir)
    assert steps["train/episodes"] == [100, 200, 300]
    assert all(s == sorted(set(s)) for s in steps.values())


def test_checkpoint_of_a_1600_frame_run_is_small(tmp_path):
    """The default networks (256 x 256, Adam state, target and averaged copies) and the filled rows only."""
    run_dir = tmp_path / "run"
    proc = run_recipe("sac_silp.py", run_dir, "collector.total_frames=1600", "collector.frames_per_batch=400",
                      "eval.every_frames=100000", "checkpoint.every_iters=100000")
    assert proc.returncode == 0, proc.stderr[-3000:]
    size = sum(f.stat().st_size for f in (run_dir / "checkpoint").rglob("*") if f.is_file())
    assert size < 5e6, f"{size / 1e6:.1f} MB"
    assert len(load_buffer(run_dir / "checkpoint" / "buffers" / "interaction")) == 1600


def _actor_tensors(state: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """The averaged actor and the trained actor of a checkpoint, each flattened into one vector."""
    loss = state["loss"]
    # AveragedModel's state: "n_averaged" and "module.<the actor's state_dict keys>"
    averaged = {key[len("module."):]: v for key, v in state["averaged_actor"].items() if key.startswith("module.")}
    params = [key for key in averaged if f"rl_loss.actor_network_params.{key}" in loss]
    assert params
    online = [loss[f"rl_loss.actor_network_params.{key}"] for key in params]
    return torch.cat([averaged[k].flatten() for k in params]), torch.cat([v.flatten() for v in online])


def train_in_process(run_dir: Path, *overrides: str) -> dict:
    """:func:`run_recipe`'s run in this process (the recipe's ``train``, no interpreter to start)."""
    from torchrl_silp.recipes.sac_silp import train
    from torchrl_silp.recipes.schema import load_config

    return train(load_config("sac_silp", [*TINY, f"run_dir={run_dir}", *overrides]))


def test_averaged_actor_is_evaluated_checkpointed_and_resumed(tmp_path):
    run_dir = tmp_path / "run"
    state_of = lambda: torch.load(run_dir / "checkpoint" / "state.pt", weights_only=False)  # noqa: E731
    s = train_in_process(run_dir, "collector.total_frames=200", "eval.actor_average_decay=0.999")
    assert s == summary(run_dir)
    assert s["evaluated_actor"] == "average (decay 0.999)"
    assert s["online_success_rate"] * 8 == round(s["online_success_rate"] * 8)  # the online actor on the 8 tasks
    avg1, online1 = _actor_tensors(state_of())
    gap = (online1 - avg1).norm()
    assert gap > 0  # 50 updates moved the actor away from its slow average

    # resumed, the average goes on from the checkpoint's (25 updates at decay 0.999 move it by
    # ~2.5 % of its gap to the actor); restarted from the actor it would jump the whole gap
    train_in_process(run_dir, "collector.total_frames=300", "eval.actor_average_decay=0.999", "resume=true")
    avg2, _ = _actor_tensors(state_of())
    assert 0 < (avg2 - avg1).norm() < 0.1 * gap

    # with a vanishing decay the average is the trained actor: it follows the right parameters
    train_in_process(run_dir, "collector.total_frames=400", "eval.actor_average_decay=1e-6", "resume=true")
    avg3, online3 = _actor_tensors(state_of())
    torch.testing.assert_close(avg3, online3, rtol=0, atol=1e-5)

    # a run saved without an average cannot silently start one from the current actor on resume: the script
    # refuses it naming the key
    plain = tmp_path / "plain"
    train_in_process(plain, "collector.total_frames=100", "eval.actor_average_decay=null")
    bad = run_recipe("sac_silp.py", plain, "collector.total_frames=200", "eval.actor_average_decay=0.999", "resume=true")
    assert bad.returncode != 0 and "eval.actor_average_decay" in bad.stderr


def _fake_run(path: Path, success: list[float], wall: float, to_095) -> None:
    path.mkdir(parents=True)
    episodes = [100 * (i + 1) for i in range(len(success))]
    history = [{"episodes": e, "success_rate": s, "frames": 50 * e} for e, s in zip(episodes, success)]
    summary = {
        "success_rate": success[-1], "train_wall_s": wall, "time_to_095_s": to_095, "planning_share": 0.05,
        "collisions_during_training": 1000, "rollout_time_per_episode_s": 0.002,
    }
    (path / "summary.json").write_text(json.dumps(summary))
    (path / "history.json").write_text(json.dumps({"history": history}))


def test_compare_runs_table_and_curves(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("compare_runs", RECIPES / "compare_runs.py")
    compare = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compare)
    _fake_run(tmp_path / "a" / "seed0", [0.2, 0.9, 0.96], 600.0, 500.0)
    _fake_run(tmp_path / "a" / "seed1", [0.4, 0.95, 0.98], 1200.0, 900.0)
    _fake_run(tmp_path / "b" / "seed0", [0.1, 0.3], 300.0, None)
    png = tmp_path / "curves.png"
    text = compare.main(["--group", f"A={tmp_path}/a/seed*", "--group", f"B={tmp_path}/b/seed*", "--png", str(png)])
    rows = {line.split("|")[1].strip(): line for line in text.splitlines()[2:]}
    # mean (population std) over the seeds, against numpy
    assert f"{np.mean([0.96, 0.98]):.3f} ({np.std([0.96, 0.98]):.3f})" in rows["A"]
    assert f"{np.mean([10.0, 20.0]):.3f} ({np.std([10.0, 20.0]):.3f})" in rows["A"]
    assert "(0/1 reached)" in rows["B"]
    assert png.stat().st_size > 0
    grid, mean, std = compare.curve(
        [json.loads((tmp_path / "a" / s / "history.json").read_text())["history"] for s in ("seed0", "seed1")]
    )
    i = int(np.argmin(np.abs(grid - 200)))
    assert grid[i] == pytest.approx(200, abs=3) and mean[i] == pytest.approx(0.925, abs=0.01)
    with pytest.raises(SystemExit):
        compare.main(["--group", f"C={tmp_path}/nothing*"])


@pytest.mark.slow
def test_sac_silp_learns_to_reach(tmp_path):
    """End to end on the default config, cut to 40k frames (~6 min here alone): the planner is learning.

    Seed 0 of the default config reached 0.86 on the 1000 test tasks at 40k frames
    (0.75 with the reward filter, 0.52 with lambda2 = 1);
    0.35 leaves room for other machines' float rounding.
    """
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(RECIPES / "sac_silp.py"), f"run_dir={run_dir}", "collector.total_frames=40000",
           "eval.every_frames=20000", "progress=false"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = summary(run_dir)
    assert out["success_rate"] >= 0.35
    assert out["planning_share"] < 0.10
    assert out["demos_stored"] > 10_000


def test_time_to_success_benchmark_stops_on_validation_and_tests_once(tmp_path, capsys, load_benchmark):
    time_to_success = load_benchmark("time_to_success")
    from torchrl_silp.eval import DEFAULT_VALIDATION_SEED

    tiny = [o for o in TINY if not o.startswith("threads")]
    out = time_to_success.main(["--bar", "0.0001", "--run-dir", str(tmp_path / "run"), *tiny,
                                "collector.total_frames=400"])
    printed = capsys.readouterr().out
    config = (tmp_path / "run" / "config.yaml").read_text()
    assert f"seed: {DEFAULT_VALIDATION_SEED}" in config and "stop_at_success: 0.0001" in config
    # stopped at the first evaluation that reached the bar (every 200 frames), not at the budget
    history = json.loads((tmp_path / "run" / "history.json").read_text())["history"]
    hits = [h["frames"] for h in history if h["success_rate"] >= 0.0001]
    if hits:
        assert out["summary"]["frames"] == hits[0] and "(reached 0.0001" in printed
    else:
        assert out["summary"]["frames"] == 400 and "(not reached 0.0001" in printed
    assert "test success of that policy (8 test tasks)" in printed
    assert out["summary"]["test_seed"] != out["summary"]["validation_seed"] == DEFAULT_VALIDATION_SEED
