"""recipes/sweep.py on a local Ray with a tiny grid, recipes/report.py on what it wrote, and a restart that skips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

ray = pytest.importorskip("ray")

from torchrl_silp.recipes import report, sweep  # noqa: E402  (after the skip without Ray)

RECIPES = Path(sweep.__file__).parent

METHODS, SEEDS = ("sac", "sac_demon"), (0, 1)
# seconds-long runs: 8 envs of 10-step episodes, two collector batches, a few gradient steps
TINY = [
    "env.num_envs=8",
    "env.max_steps=10",
    "collector.frames_per_batch=80",
    "collector.total_frames=160",
    "collector.init_random_frames=80",
    "eval.n_tasks=8",
    "eval.every_frames=80",
    "optim.batch_size=16",
    "replay_buffer.size=2000",
    "replay_buffer.demo_size=2000",
    "checkpoint.every_iters=1",
    "network.hidden_sizes=[16,16]",
    "threads=1",
    "progress=false",
    "compile.compile=false",
]


def sweep_config(results: Path, *extra: str, tiny: list[str] = TINY):
    quoted = ",".join(f"'{o}'" for o in tiny)  # hydra wants list items holding "=" quoted
    # workers reused across runs: each fresh one would import torch and the recipe again (~10 s)
    return sweep.load_config([
        f"results_dir={results}", f"methods=[{','.join(METHODS)}]", f"seeds=[{','.join(map(str, SEEDS))}]",
        f"overrides.sac_silp=[{quoted}]", "fresh_worker=false", *extra,
    ])


def test_bad_grid_is_rejected_before_ray_starts(tmp_path, monkeypatch):
    def no_ray(*args, **kwargs):
        raise AssertionError("ray.init was called")

    monkeypatch.setattr(ray, "init", no_ray)
    with pytest.raises(ValueError, match=r"methods must be .*'sac_silp_plus'.*unknown: \['nope'\]"):
        sweep.run_sweep(sweep_config(tmp_path, "methods=[sac,nope]"))
    with pytest.raises(ValueError, match="seeds must be"):
        sweep.run_sweep(sweep_config(tmp_path, "seeds=[0,-1]"))
    with pytest.raises(ValueError, match="resources.num_cpus"):
        sweep.run_sweep(sweep_config(tmp_path, "resources.num_cpus=0"))
    # a recipe override the config does not have fails when composed, still before Ray
    with pytest.raises(ValueError, match="do not compose.*no_such_key"):
        sweep.run_sweep(sweep_config(tmp_path, "overrides.all=['no_such_key=1']"))
    # the BC of SAC-SILP+ needs SAC-SILP+'s run of the same seed
    with pytest.raises(ValueError, match="needs the finished run of sac_silp_plus"):
        sweep.run_sweep(sweep_config(tmp_path, "methods=[bc_sac_silp_plus]"))
    assert not ray.is_initialized()
    assert not list(tmp_path.iterdir())


def test_report_on_empty_results_is_a_clear_error(tmp_path):
    (tmp_path / "results").mkdir()
    with pytest.raises(FileNotFoundError, match=r"no <method>/seed\*/summary.json under .*results.*sweep.py"):
        report.main(["--results", str(tmp_path / "results"), "--out", str(tmp_path / "results.md"),
                     "--figure", str(tmp_path / "curves.png")])
    assert not (tmp_path / "results.md").exists()


def _cells(block: str, label: str) -> list[str]:
    row = next(line for line in block.splitlines() if line.startswith(f"| {label} |"))
    return [c.strip() for c in row.strip("|").split("|")]


def _agrees(cell: str, value: float) -> bool:
    """The cell's first number (``0.123 (0.045)`` or ``h:mm:ss (...)``) equals ``value`` to its printed precision."""
    text = cell.split(" (")[0]
    if ":" in text:
        h, m, s = map(int, text.split(":"))
        return abs(3600 * h + 60 * m + s - value) <= 0.5 + 1e-9
    decimals = len(text.split(".")[1]) if "." in text else 0
    return abs(float(text.replace(",", "")) - value) <= 0.5 * 10**-decimals + 1e-12


def _of_eval_tasks(rate: float, n_tasks: int = 8) -> bool:
    """Whether ``rate`` is a count of successes over TINY's ``eval.n_tasks`` tasks."""
    return any(abs(rate - k / n_tasks) < 1e-9 for k in range(n_tasks + 1))


def test_sweep_report_and_restart(tmp_path, capsys):
    results = tmp_path / "table1"
    ray.init(address="local", num_cpus=2, include_dashboard=False)
    try:
        outcome = sweep.run_sweep(sweep_config(results))
        out = capsys.readouterr().out
        assert [(r["method"], r["seed"], r["status"]) for r in outcome] == [
            (m, s, "ok") for m in METHODS for s in SEEDS], out
        summaries = {}
        for m in METHODS:
            for s in SEEDS:
                run_dir = results / m / f"seed{s}"
                summary = json.loads((run_dir / "summary.json").read_text())
                history = json.loads((run_dir / "history.json").read_text())["history"]
                assert summary["method"] == m and summary["seed"] == s and summary["frames"] == 160
                assert _of_eval_tasks(summary["success_rate"]) and summary["train_wall_s"] > 0
                assert summary["episodes"] >= 16 and summary["rollout_time_per_episode_s"] > 0
                assert [p["frames"] for p in history] == [80, 160]
                assert all(_of_eval_tasks(p["success_rate"]) and p["episodes"] > 0 for p in history)
                assert "==== sweep: " in (run_dir / "run.log").read_text()
                record = json.loads((run_dir / "sweep.json").read_text())
                assert record["method"] == m and [a["status"] for a in record["attempts"]] == ["ok"]
                summaries[m, s] = summary
        assert "[4/4] ok" in out and "sweep done: 4 ok, 0 failed, 0 skipped" in out

        # the report: both rows hold the means of the summary files, and the curves are drawn
        md, png = tmp_path / "docs" / "results.md", tmp_path / "docs" / "curves.png"
        md.parent.mkdir()
        md.write_text("# Results\n\nearlier sections\n\n<!-- table1:begin -->\nold table\n<!-- table1:end -->\n\nlater\n")
        block = report.main(["--results", str(results), "--out", str(md), "--figure", str(png)])
        text = md.read_text()
        assert text.startswith("# Results\n\nearlier sections\n\n<!-- table1:begin -->") and text.endswith("<!-- table1:end -->\n\nlater\n")
        assert "old table" not in text and block in text and "`collector.total_frames` 160" in block
        for m, label in (("sac", "the paper's SAC as written (`sac`)"), ("sac_demon", "the paper's SAC-Demon as written (`sac_demon`)")):
            cells = _cells(block, label)
            runs = [summaries[m, s] for s in SEEDS]
            assert cells[1] == "paper's"  # the baselines' method configs hold the paper's settings
            assert _agrees(cells[2], np.mean([r["success_rate"] for r in runs])), cells
            assert _agrees(cells[5], np.mean([r["train_wall_s"] for r in runs])), cells
            assert _agrees(cells[7], np.mean([r["rollout_time_per_episode_s"] for r in runs])), cells
            assert cells[9] == "2"
            paper = yaml.safe_load((RECIPES / "reporting" / "paper.yaml").read_text())["table1"][m]["success"]
            assert cells[3] == f"{paper[0]:.3f} ({paper[1]:.3f})"
            assert _agrees(cells[4], np.mean([r["success_rate"] for r in runs]) - paper[0]), cells
        assert "- `sac`: 2 of 3 seeds (seeds 0, 1)" in block and "- `sac_silp_plus`: not run" in block
        assert "not run: SAC-SILP+ ≥ SAC-Demon ≥ SAC" in block
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

        # started again: every run is finished and skipped, nothing is rewritten
        summary_files = [results / m / f"seed{s}" / "summary.json" for m in METHODS for s in SEEDS]
        mtimes = [p.stat().st_mtime_ns for p in summary_files]
        outcome = sweep.run_sweep(sweep_config(results))
        out = capsys.readouterr().out
        assert [r["status"] for r in outcome] == ["skipped"] * 4
        assert "skipped 4 finished run(s)" in out and "nothing to run" in out
        assert [p.stat().st_mtime_ns for p in summary_files] == mtimes

        # without its summary, exactly that run runs again (from its checkpoint)
        summary_files[3].unlink()
        outcome = sweep.run_sweep(sweep_config(results))
        out = capsys.readouterr().out
        assert [r["status"] for r in outcome] == ["skipped"] * 3 + ["ok"]
        assert "skipped 3 finished run(s)" in out and "resuming 1 run(s) from their checkpoint: sac_demon (seed 1)" in out
        assert [p.stat().st_mtime_ns for p in summary_files[:3]] == mtimes[:3] and summary_files[3].exists()
        assert "resumed from" in (results / "sac_demon" / "seed1" / "run.log").read_text()
        record = json.loads((results / "sac_demon" / "seed1" / "sweep.json").read_text())
        assert [a["status"] for a in record["attempts"]] == ["ok", "ok"]

        # a failed run is reported and fails the run that waits for it without running it
        bad_batch = [o.replace("frames_per_batch=80", "frames_per_batch=84") for o in TINY]  # not a multiple of 8 envs
        failing = sweep_config(tmp_path / "failing", "methods=[bc_sac_silp_plus,sac_silp_plus]", "seeds=[0]", tiny=bad_batch)
        outcome = sweep.run_sweep(failing)
        out = capsys.readouterr().out
        assert [(r["method"], r["status"]) for r in outcome] == [("sac_silp_plus", "failed"), ("bc_sac_silp_plus", "failed")]
        assert "multiple of env.num_envs" in outcome[0]["error"]
        assert outcome[1]["error"] == "needs sac_silp_plus/seed0, which failed"
        assert "FAILED  sac_silp_plus seed 0: ConfigError" in out and "0 ok, 2 failed" in out
        assert not (tmp_path / "failing" / "bc_sac_silp_plus").exists()
    finally:
        ray.shutdown()


# what defines a run's task and budget, for each recipe's config (a key a config lacks is skipped)
RUN_DEFINING_KEYS = ("env.name", "collector.total_frames", "collector.total_episodes",
                     "env.collision_type", "planner.d", "silp.filter", "exploration.mode",
                     "exploration.mask_colliding_candidates", "n_demos",
                     "optim.n_updates", "optim.utd_ratio", "budget_s", "source", "eval.n_tasks", "eval.test_seed")


@pytest.mark.parametrize("config_name", ["sweep", "sweep_ablations", "sweep_tasks", "sweep_default",
                                         "sweep_utd", "sweep_sac_type2_causes", "sweep_planar_arm",
                                         "sweep_baselines_rerun"])
def test_each_grid_started_again_composes_its_committed_runs(config_name):
    """A grid whose runs are committed composes, for each method's seed 0, the task and budget of that run's
    config.yaml: the sweep's grid-wide overrides do not overrule a method's own (the Panda runs' 300k
    frames), and sweep_tasks does not inherit the paper's 10,000-episode budget of sweep.yaml."""
    from hydra import compose
    from omegaconf import OmegaConf

    root = Path(__file__).parents[1]
    results = Path(OmegaConf.load(RECIPES / "config" / f"{config_name}.yaml").get("results_dir", "results/paper_budget"))
    cfg = sweep.load_config([f"results_dir={root / results}"], config_name=config_name)
    runs = [run for run in sweep.plan(cfg, check_configs=False)
            if run.seed == 0 and (run.run_dir / "config.yaml").exists() and (run.run_dir / "summary.json").exists()]
    assert runs, f"{config_name}: committed runs expected under {results}"
    for run in runs:
        with sweep.config_context():
            composed = compose(run.config, overrides=list(run.overrides))
        committed = OmegaConf.load(run.run_dir / "config.yaml")
        missing = object()
        for key in RUN_DEFINING_KEYS:
            was = OmegaConf.select(committed, key, default=missing)
            if was is not missing:
                assert OmegaConf.select(composed, key) == was, (run.name, key)


def test_the_baseline_reruns_compose_the_papers_recovery_at_the_papers_budget():
    """sweep_baselines_rerun (its runs are under results/paper_budget/, where the test above holds them to
    their grid): random recovery draws among collision-free actions, Demon recovers by the GP."""
    from hydra import compose

    cfg = sweep.load_config([], config_name="sweep_baselines_rerun")
    runs = [run for run in sweep.plan(cfg, check_configs=False) if run.seed == 0]
    assert {run.method for run in runs} == set(cfg.methods)
    for run in runs:
        with sweep.config_context():
            composed = compose(run.config, overrides=list(run.overrides))
        assert composed.collector.total_episodes == 10_000, run.method
        if run.method.endswith("demon"):
            assert composed.exploration.mode == "gp" and not composed.silp.bc, run.method
        else:
            assert composed.exploration.mode == "random" and composed.exploration.mask_colliding_candidates, run.method


def test_table5s_grid_trains_then_runs_the_reaching_test_on_each_checkpoint(tmp_path):
    """sweep_table5: a training run, then recipes/transfer.py on its checkpoint as a run of the sweep's own
    (its summary.json the test's result); the report's table5 block reads what it wrote."""
    from torchrl_silp.recipes.reporting import pages

    pytest.importorskip("mujoco")
    quoted = ",".join(f"'{o}'" for o in TINY)
    cfg = sweep.load_config([f"results_dir={tmp_path}", "seeds=[0]", "methods=[sac_demon,table5_sac_demon]",
                             f"overrides.sac_silp=[{quoted}]", "overrides.transfer=['trials=2','max_steps=5']",
                             "fresh_worker=false", "ray.num_cpus=1"], config_name="sweep_table5")
    results = sweep.run_sweep(cfg)
    assert [r["status"] for r in results] == ["ok", "ok"]
    summary = json.loads((tmp_path / "table5_sac_demon" / "seed0" / "summary.json").read_text())
    assert summary["checkpoint"] == str(tmp_path / "sac_demon" / "seed0")
    assert [(r["scenario"], r["noise"]) for r in summary["rows"]] == [("reaching", n) for n in ("none", "paper", "double")]
    row = summary["rows"][1]
    assert row["n_tasks"] == 20 and len(row["scenario_success"]) == 10
    assert row["success_rate"] == pytest.approx(np.mean(row["scenario_success"]))
    block = dict(pages.spec()["blocks"]["table5"], results=str(tmp_path), noises=["paper"])
    text = pages.render_block("table5", block, tmp_path / "p.md")
    assert f"| the paper's SAC-Demon as written (`sac_demon`: SILP+ without the BC term, GP recovery included) | paper | " \
           f"{row['success_rate']:.3f} | {row['collision_rate']:.3f} | 1 |" in text
