"""recipes/report.py: the blocks of the paper's Tables 2, 3, 4, A.1 and of the ablations, from synthetic results files."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))
import report  # noqa: E402

PAPER = yaml.safe_load((RECIPES / "config" / "paper_settings.yaml").read_text())


def _run(root: Path, method: str, seed: int, success: float, collisions: int = 100, validation: float | None = None,
         kept: list[float] | None = None, config: dict | None = None, test_collision_rate: float = 0.0):
    run = root / method / f"seed{seed}"
    run.mkdir(parents=True)
    summary = {"success_rate": success, "validation_success_rate": validation, "frames": 200_000 + seed,
               "episodes": 10_000 + seed, "train_wall_s": 1800.0 + 60 * seed, "collisions_during_training": collisions,
               "test_collision_rate": test_collision_rate}
    (run / "summary.json").write_text(json.dumps(summary))
    history = [{"episodes": e, "success_rate": success, "frames": 20 * e,
                **({"bc_filter_fraction": kept[i]} if kept else {})} for i, e in enumerate((2000, 6000, 10000))]
    (run / "history.json").write_text(json.dumps({"history": history}))
    cfg = config or {"algorithm": "sac", "silp": {"demos": True}, "exploration": {"mode": "gp"}, **PAPER}
    (run / "config.yaml").write_text(yaml.safe_dump({**cfg, "collector": {"total_episodes": 10000}}))


def _row(text: str, method: str) -> list[str]:
    line = next(line for line in text.splitlines() if f"(`{method}`)" in line or f"| `{method}` |" in line)
    return [c.strip() for c in line.strip("|").split("|")]


def test_table2_rows_and_orderings(tmp_path):
    values = {"sac": [0.8, 0.9], "sac_collision0": [0.85, 0.87], "sac_collision1": [0.4, 0.5],
              "sac_silp_plus": [0.95, 0.97, 0.96], "sac_silp_plus_collision0": [0.97, 0.98]}
    for method, successes in values.items():
        for seed, v in enumerate(successes):
            _run(tmp_path, method, seed, v, test_collision_rate=(1 - v) / (seed + 2))
    runs = report.load_results(tmp_path)
    text = report.paper_table_block(runs, "table2", tmp_path, None, tmp_path / "r.md", "cmd")
    cells = _row(text, "sac")
    assert cells[1] == "paper's" and cells[2] == f"{np.mean([0.8, 0.9]):.3f} ({np.std([0.8, 0.9]):.3f})"
    assert cells[3] == "0.865 (0.021)" and cells[9] == "2"
    collision = [0.2 / 2, 0.1 / 3]  # (1 - success) / (seed + 2)
    assert cells[4] == f"{np.mean(collision):.3f} ({np.std(collision):.3f})"
    assert _row(text, "sac_silp_plus_collision1")[4] == "—"
    assert _row(text, "sac_silp_plus_collision1")[2] == "not run"
    # SAC: type-0 (0.86) beats type-2 (0.85): does not hold; SILP+ type-1 missing: not run
    assert "- does not hold: SAC: type-2 ≥ type-0 ≥ type-1" in text
    assert "- not run: SAC-SILP+: type-2 ≥ type-0 ≥ type-1 (missing: sac_silp_plus_collision1)" in text
    assert text.startswith("<!-- table2:begin -->") and text.endswith("<!-- table2:end -->")


def test_table3_compares_collisions(tmp_path):
    for seed in range(3):
        _run(tmp_path, "sac_silp_plus", seed, 0.97, collisions=6000 + seed)
        _run(tmp_path, "sac_silp_plus_random_recovery", seed, 0.96, collisions=30000 + 10 * seed)
    text = report.paper_table_block(report.load_results(tmp_path), "table3", tmp_path, None, tmp_path / "r.md", "cmd")
    assert _row(text, "sac_silp_plus")[7] == f"{np.mean([6000, 6001, 6002]):,.0f} ({np.std([6000, 6001, 6002]):,.0f})"
    assert _row(text, "sac_silp_plus")[8] == "6,153"
    assert "- holds: GP recovery: fewer collisions during training than random recovery" in text
    assert "- holds: GP recovery: a success rate at least that of random recovery" in text


def test_table4_draws_the_filter_share(tmp_path):
    for seed in range(2):
        _run(tmp_path, "sac_silp_plus", seed, 0.97, kept=[0.6, 0.3 + 0.1 * seed, 0.1])
        _run(tmp_path, "sac_silp_plus_q_filter", seed, 0.98, kept=[0.7, 0.6, 0.5])
    png = tmp_path / "share.png"
    text = report.paper_table_block(report.load_results(tmp_path), "table4", tmp_path, png, tmp_path / "r.md", "cmd")
    assert png.stat().st_size > 0 and "share.png" in text
    assert "- does not hold: reward filter ≥ Q-filter (success rate)" in text
    assert _row(text, "sac_silp_plus_no_filter")[2] == "not run"


def test_ablations_report_the_validation_difference(tmp_path):
    ours = {"algorithm": "sac", "silp": {"demos": True}, "exploration": {"mode": "gp"}}  # schema defaults: ours
    _run(tmp_path, "sac_silp_plus_ext", 0, 0.98, validation=0.975, config=ours)
    _run(tmp_path, "sac_silp_plus_ext", 1, 0.97, validation=0.5, config=ours)  # other seeds are not the reference
    _run(tmp_path, "sac_silp_plus_ext_no_next_tcp", 0, 0.95, validation=0.94,
         config={**ours, "network": {"next_tcp_feature": False}})
    text = report.ablations_block(report.load_results(tmp_path), tmp_path, "cmd")
    cells = _row(text, "sac_silp_plus_ext_no_next_tcp")
    assert cells[1] == "`network.next_tcp_feature=false`" and cells[2] == "0.940" and cells[3] == f"{0.94 - 0.975:+.3f}"
    assert _row(text, "sac_silp_plus_ext_auto_entropy")[2] == "not run"


def test_ablations_sort_each_change_by_ours_seed_spread(tmp_path):
    ours = {"algorithm": "sac", "silp": {"demos": True}, "exploration": {"mode": "gp"}}
    for seed, validation in enumerate((0.96, 0.97, 0.98)):  # std (ddof=0) sqrt(2/3) * 0.01 = 0.00816
        _run(tmp_path, "sac_silp_plus_ext", seed, 0.97, validation=validation, config=ours)
    _run(tmp_path, "sac_silp_plus_ext_no_next_tcp", 0, 0.95, validation=0.94, config=ours)  # -0.020: beyond 0.0163
    _run(tmp_path, "sac_silp_plus_ext_no_goal_node", 0, 0.95, validation=0.975, config=ours)  # +0.015: within
    text = report.ablations_block(report.load_results(tmp_path), tmp_path, "cmd")
    line = next(line for line in text.splitlines() if line.startswith("Ours over its 3 seeds"))
    assert line == ("Ours over its 3 seeds: validation success 0.970, std 0.008. Beyond twice that std from ours' "
                    "seed 0: `sac_silp_plus_ext_no_next_tcp` (-0.020). Within it: `sac_silp_plus_ext_no_goal_node` "
                    "(+0.015).")


@pytest.mark.parametrize("name", ["table2", "table3", "table4", "tableA1"])
def test_every_paper_table_row_is_a_sweep_method(name):
    registry = yaml.safe_load((RECIPES / "config" / "sweep.yaml").read_text())["registry"]
    assert {m for m, *_ in report.PAPER_TABLES[name]["rows"]} <= set(registry)


def test_every_ablation_is_in_the_ablation_sweep():
    sweep = yaml.safe_load((RECIPES / "config" / "sweep_ablations.yaml").read_text())
    assert set(report.ABLATIONS) == set(sweep["methods"]) == set(sweep["registry"])
    for method, change in report.ABLATIONS.items():
        key, value = change.split("=")
        assert f"{key}={value}" in sweep["registry"][method]["overrides"] or f"{key}={value}.0" in sweep["registry"][method]["overrides"]


def test_table5_means_over_seeds_beside_the_papers_scenarios(tmp_path):
    perception = {"obstacle_noise": 0.01, "latency_steps": 1, "joint_noise": 1e-4}
    for seed, (free, block) in enumerate([(1.0, 0.9), (0.96, 0.8)]):
        rows = [{"scenario": sc, "noise": "paper", "n_tasks": 100, "success_rate": v, "collision_rate": 1 - v,
                 "mean_steps": 12.0, "time_to_success_s": 1.2 + seed, "policy_ms_per_step": 3.0,
                 "perception": perception} for sc, v in (("free", free), ("block", block))]
        result = {"checkpoint": f"runs/x/seed{seed}", "method": "sac_silp_plus", "seed": seed, "trained_frames": 1,
                  "trained_episodes": 10_000, "control_dt": 0.1, "max_steps": 50, "rows": rows}
        (tmp_path / f"sac_silp_plus_seed{seed}.json").write_text(json.dumps(result))
    text = report.table5_block(report.load_transfer(tmp_path), tmp_path, "cmd")
    free = next(line for line in text.splitlines() if "| free | paper |" in line)
    cells = [c.strip() for c in free.strip("|").split("|")]
    assert cells[3] == f"{np.mean([1.0, 0.96]):.3f} ({np.std([1.0, 0.96]):.3f})"
    assert cells[5] == f"{np.mean([1.2, 2.2]):.2f} ({np.std([1.2, 2.2]):.2f})" and cells[6] == "2"
    # the paper: 3 and 4 failures in 50 Free trials, in simulation and on the real robot
    assert cells[7:] == ["0.94", "0.92"]
    assert "| block | none |" not in text and "box noise 0.01 m, latency 1 step(s)" in text
    # a run's pick-and-place file shares its checkpoint: the runs line names each policy once
    pick = {**result, "rows": [{**rows[0], "scenario": "pick_place"}]}
    (tmp_path / "sac_silp_plus_seed1_pick_place.json").write_text(json.dumps(pick))
    prm = {**result, "method": "prm_0.1_replanned", "checkpoint": None, "seed": 0, "trained_episodes": 0}
    (tmp_path / "prm_0.1_replanned_seed0_none.json").write_text(json.dumps(prm))
    runs = next(line for line in report.table5_block(report.load_transfer(tmp_path), tmp_path, "cmd").splitlines()
                if line.startswith("Runs: "))
    assert runs == ("Runs: PRM-0.1, replanned every control step: seed 0 (a planner, no training); "
                    "SAC-SILP+ (paper's): seed 0 (10,000 episodes, `runs/x/seed0`), "
                    "seed 1 (10,000 episodes, `runs/x/seed1`).")
    with pytest.raises(FileNotFoundError, match="transfer"):
        report.load_transfer(tmp_path / "none")


def test_collision_net_block_sets_each_labeller_beside_the_paper(tmp_path):
    for labeller, acc in (("exact", 0.97), ("mujoco", 0.99)):
        net = {"labeller": labeller, "n": 1000, "collision_share": 0.5, "command": f"python x --labeller {labeller}",
               "metrics": {"accuracy": acc, "recall": 0.9, "precision": 0.8, "specificity": 0.7},
               "roc": {"fpr": [1.0, 0.2, 0.0], "tpr": [1.0, 0.9, 0.0], "auc": 0.95}}
        (tmp_path / f"{labeller}.json").write_text(json.dumps(net))
    png = tmp_path / "roc.png"
    text = report.collision_net_block(report.load_collision_nets(tmp_path), tmp_path, png, tmp_path / "r.md", "cmd")
    rows = [line for line in text.splitlines() if line.startswith("| ")][1:]  # past the header
    assert rows[0].startswith("| the paper's (appendix B) | 485,000 | — | 0.991 | 0.984 | 0.989 | 0.995 |")
    assert rows[1] == "| exact | 1,000 | 0.500 | 0.970 | 0.900 | 0.800 | 0.700 | 0.9500 |"
    assert rows[2].startswith("| mujoco | 1,000 | 0.500 | 0.990 |") and png.stat().st_size > 0


def test_table1_says_how_far_ours_is_from_the_papers_silp(tmp_path):
    for seed, (paper, ours) in enumerate([(0.90, 0.97), (0.92, 0.99)]):
        _run(tmp_path, "sac_silp_plus", seed, paper)
        _run(tmp_path, "sac_silp_plus_ext", seed, ours)
    runs = report.load_results(tmp_path)
    text = report.block(runs, tmp_path, None, tmp_path / "r.md", "cmd", [], "table1")
    assert f"- SAC-SILP+ extended (ours) − SAC-SILP+ (paper's): {0.98 - 0.91:+.3f} success rate (2 and 2 seeds)" in text


def test_sac_utd_block_sets_each_update_ratio_beside_table1s_sac_at_equal_frames(tmp_path, monkeypatch):
    def run(root: Path, method: str, seed: int, ratio: float, end: int, slope: float) -> dict[int, float]:
        path = root / method / f"seed{seed}"
        path.mkdir(parents=True)
        curve = {f: round(slope * f / 1000 + 0.01 * seed, 4) for f in range(8000, end + 1, 8000)}
        (path / "history.json").write_text(json.dumps(
            {"history": [{"frames": f, "success_rate": v} for f, v in curve.items()]}))
        (path / "summary.json").write_text(json.dumps(
            {"success_rate": 0.5 + seed / 10, "validation_success_rate": curve[max(curve)], "frames": end,
             "updates": int(end * ratio), "train_wall_s": 600.0, "test_collision_rate": 0.01}))
        (path / "config.yaml").write_text(yaml.safe_dump({"algorithm": "sac", "optim": {"utd_ratio": ratio},
                                                          "collector": {"total_frames": end}}))
        return curve

    utd, budget = tmp_path / "sac_utd", tmp_path / "paper_budget"
    low = run(utd, "sac_utd0.25", 0, 0.25, 64_000, 0.001)
    high = run(utd, "sac_utd1", 0, 1.0, 64_000, 0.004)
    table1 = [run(budget, "sac", seed, 0.25, 160_000, 0.0005) for seed in (0, 1)]
    monkeypatch.setitem(report.RESULTS_OF, "table1", str(budget))
    text = report.main(["--block", "sac_utd", "--results", str(utd), "--out", str(tmp_path / "r.md")])
    lines = text.splitlines()
    # columns every 20k frames up to the sweep's runs' end, however far Table 1's runs went
    assert "| Frames | 20k | 40k | 60k | 64k |" in lines
    assert "The settings this sweep's runs differ in (their `config.yaml`, names and paths aside): `optim.utd_ratio`." in text
    cells = lambda label: [c.strip() for c in next(l for l in lines if l.startswith(f"| {label}")).strip("|").split("|")]
    last_at = lambda curve, f: curve[max(k for k in curve if k <= f)]
    assert cells("`sac_utd1`, 1.0 updates")[1:] == [f"{last_at(high, f):.3f}" for f in (20_000, 40_000, 60_000, 64_000)]
    assert cells("`sac_utd0.25`, 0.25 updates")[1:] == [f"{last_at(low, f):.3f}" for f in (20_000, 40_000, 60_000, 64_000)]
    at_40k = np.array([last_at(c, 40_000) for c in table1])
    assert cells("Table 1's `sac`")[2] == f"{at_40k.mean():.3f} ({at_40k.std():.3f})"
    row = cells("`sac_utd1` |")
    assert row[1:5] == ["1.0", "1", "64000", "64000"] and row[6] == f"{high[64_000]:.3f}" and row[7] == "0.500"


def test_speed_tuning_block_names_each_rows_changed_setting_and_orders_rows_by_time_to_095(tmp_path):
    def run(method: str, to_095: float | None, frames: int, updates: int, validation: float, seed: int = 0,
            **changed) -> None:
        path = tmp_path / method / f"seed{seed}"
        path.mkdir(parents=True)
        (path / "summary.json").write_text(json.dumps(
            {"success_rate": validation, "validation_success_rate": validation, "frames": frames, "updates": updates,
             "train_wall_s": to_095 if to_095 is not None else 900.5, "time_to_095_s": to_095}))
        config = {"seed": seed, "run_dir": str(path), "logger": {"exp_name": method},
                  "eval": {"seed": 7, "test_seed": 7}, "collector": {"total_frames": 160_000},
                  "optim": {"utd_ratio": 0.25, "batch_size": 256}, "env": {"num_envs": 32}}
        for dotted, value in changed.items():
            section, key = dotted.split("__")
            config[section][key] = value
        (path / "config.yaml").write_text(yaml.safe_dump(config))

    run("tune_default", 257.4, 104_000, 24_200, 0.957)
    run("tune_default_again", 301.0, 104_000, 24_200, 0.951)
    run("tune_utd0.5", 330.0, 72_000, 32_000, 0.953, optim__utd_ratio=0.5)
    run("tune_utd0.5", 270.0, 56_000, 24_000, 0.957, seed=1, optim__utd_ratio=0.5)
    run("tune_batch512_utd0.125", 190.2, 112_000, 12_000, 0.955, optim__batch_size=512, optim__utd_ratio=0.125)
    run("tune_envs16", None, 150_000, 37_000, 0.94, env__num_envs=16)
    text = report.main(["--block", "speed_tuning", "--results", str(tmp_path), "--out", str(tmp_path / "r.md")])
    rows = [line for line in text.splitlines() if line.startswith("| `tune_")]
    # the default first and last of the sweep, then the rows that reached 0.95 by their time to it, then the others
    assert [r.split("|")[1].strip() for r in rows] == [
        "`tune_default`", "`tune_default_again`", "`tune_batch512_utd0.125`", "`tune_utd0.5`", "`tune_envs16`"]
    cells = [[c.strip() for c in r.strip("|").split("|")] for r in rows]
    assert cells[0][1] == "none (the default)" and cells[1][1] == "none (the default)"
    assert cells[2][1] == "`optim.batch_size=512`, `optim.utd_ratio=0.125`"
    assert cells[2][3:] == ["1 of 1", "112,000", "12,000", "0:03:10", "0:03:10", "0.955"]
    assert cells[0][7] == "0:04:17"  # 257.4 s
    # two seeds: mean (std), the std of 330 and 270 s being 30 s
    assert cells[3][2:8] == ["2", "2 of 2", "64,000 (8,000)", "28,000 (4,000)", "0:05:00 (0:00:30)", "0:05:00 (0:00:30)"]
    assert cells[4][1] == "`env.num_envs=16`" and cells[4][3] == "0 of 1" and cells[4][6:8] == ["0:15:00", "—"]
    test_tasks = report._schema_defaults()["eval.test_seed"]
    assert (f"read the tasks of `eval.seed` 7, and so does its final evaluation (`eval.test_seed` 7): no tuning run "
            f"reads the test tasks (`eval.test_seed` {test_tasks} by default)") in text
    assert (tmp_path / "r.md").read_text().strip() == text
    run("tune_on_test_tasks", 200.0, 96_000, 22_000, 0.96, eval__seed=test_tasks, eval__test_seed=test_tasks)
    text = report.main(["--block", "speed_tuning", "--results", str(tmp_path), "--out", str(tmp_path / "r.md")])
    assert f"**some read the test tasks** (`eval.test_seed` {test_tasks} by default)" in text
