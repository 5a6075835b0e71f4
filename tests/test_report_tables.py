"""recipes/reporting: block specs rendered from synthetic results files, checked against numpy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp.recipes.reporting import load, pages, tables

PAPER = yaml.safe_load((Path(tables.PAPER_SETTINGS)).read_text())


def _run(root: Path, method: str, seed: int, summary: dict, config: dict | None = None, history=None) -> None:
    run = root / method / f"seed{seed}"
    run.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps(summary))
    (run / "history.json").write_text(json.dumps({"history": history or []}))
    cfg = config or {"algorithm": "sac", "silp": {"demos": False, "bc": False}, "exploration": {"mode": "random"},
                     **PAPER}
    (run / "config.yaml").write_text(yaml.safe_dump({**cfg, "seed": seed, "run_dir": str(run),
                                                     "logger": {"exp_name": method}}))


def _rows(text: str) -> dict[str, list[str]]:
    out = {}
    for line in text.splitlines():
        if line.startswith("| ") and "(`" in line:
            cells = [c.strip() for c in line.strip("|").split("|")]
            out[cells[0].rsplit("(`", 1)[1].rstrip("`)")] = cells
    return out


def _paper_sac(**changes) -> dict:
    config = {"algorithm": "sac", "silp": {"demos": False, "bc": False}, "exploration": {"mode": "random"},
              **json.loads(json.dumps(PAPER)), "optim": {**PAPER["optim"], "utd_ratio": 0.25}}
    for dotted, value in changes.items():
        section, key = dotted.split("__")
        config.setdefault(section, {})[key] = value
    return config


def test_a_new_study_is_a_block_spec_and_its_table_is_the_summary_files(tmp_path):
    """What results/README.md says: a study's table comes from a block spec alone."""
    rng = np.random.default_rng(0)
    values = {m: rng.uniform(0, 1, 3).round(4) for m in ("sac", "sac_no_warmup", "sac_utd1")}
    changes = {"sac": {}, "sac_no_warmup": {"collector__init_random_frames": 0}, "sac_utd1": {"optim__utd_ratio": 1.0}}
    for method, successes in values.items():
        for seed, v in enumerate(successes):
            history = [{"frames": f, "episodes": f // 50, "success_rate": float(v) * f / 60_000}
                       for f in (20_000, 40_000, 60_000)]
            _run(tmp_path, method, seed, {"success_rate": float(v), "validation_success_rate": float(v) / 2,
                                          "frames": 60_000, "test_collision_rate": 0.01 * seed},
                 _paper_sac(**{"collector__init_random_frames": 800, **changes[method]}), history)
    spec = {"kind": "runs", "title": "a study", "results": str(tmp_path), "name": "SAC", "baseline": "sac",
            "columns": ["method", "changed", "seeds", "success", "validation", "delta:validation_success_rate",
                        "test_collision"],
            "by_frames": {"every": 20_000},
            "checks": [{"text": "more updates help", "all": [{"order": ["sac_utd1", "sac"]}]}]}
    text = pages.render_block("a_study", spec, tmp_path / "page.md")
    rows = _rows(text)
    assert list(rows) == ["sac", "sac_no_warmup", "sac_utd1"]  # rows: all, by name
    for method, cells in rows.items():
        v = values[method]
        assert cells[0].startswith("the paper's SAC as written")
        assert cells[3] == f"{v.mean():.3f} ({v.std():.3f})" and cells[2] == "3"
        assert cells[4] == f"{(v / 2).mean():.3f} ({(v / 2).std():.3f})"
    assert rows["sac"][1] == "none (the baseline)" and rows["sac"][5] == ""
    assert rows["sac_utd1"][1] == "`optim.utd_ratio=1.0`"
    assert rows["sac_no_warmup"][1] == "`collector.init_random_frames=0`"
    assert rows["sac_utd1"][5] == f"{(values['sac_utd1'] / 2).mean() - (values['sac'] / 2).mean():+.3f}"
    holds = values["sac_utd1"].mean() >= values["sac"].mean()
    assert f"- {'holds' if holds else 'does not hold'}: more updates help (`sac_utd1` {values['sac_utd1'].mean():.3f}" in text
    curve = next(line for line in text.splitlines() if line.startswith("| `sac_utd1` |"))
    at_40k = values["sac_utd1"] * 40_000 / 60_000
    assert curve.split("|")[3].strip() == f"{at_40k.mean():.3f} ({at_40k.std():.3f})"
    assert f"Runs: `{tmp_path}/<method>/seed<k>/`" in text and "--block a_study" in text


def test_a_switch_the_baseline_s_config_predates_counts_as_a_change(tmp_path):
    """A baseline saved before a switch existed ran at the switch's absent value (paper.yaml's settings.absent)."""
    old = _paper_sac()
    old["replay_buffer"] = {k: v for k, v in old["replay_buffer"].items() if k != "collision_terminal"}
    _run(tmp_path, "sac", 0, {"success_rate": 0.05, "validation_success_rate": 0.05}, old)
    _run(tmp_path, "sac_terminal", 0, {"success_rate": 0.1, "validation_success_rate": 0.1},
         _paper_sac(replay_buffer__collision_terminal=True))
    _run(tmp_path, "sac_same", 0, {"success_rate": 0.05, "validation_success_rate": 0.05},
         _paper_sac(replay_buffer__collision_terminal=False))
    spec = {"kind": "runs", "title": "t", "results": str(tmp_path), "name": "SAC", "baseline": "sac",
            "columns": ["method", "changed", "seeds"]}
    rows = _rows(pages.render_block("t", spec, tmp_path / "p.md"))
    assert rows["sac_terminal"][1] == "`replay_buffer.collision_terminal=true`"
    assert rows["sac_same"][1] == "none (the baseline)"


def test_rows_not_run_fewer_seeds_and_orderings_that_cannot_be_read(tmp_path):
    _run(tmp_path, "sac", 0, {"success_rate": 0.5})
    _run(tmp_path, "sac", 1, {"success_rate": 0.7})
    _run(tmp_path, "sac_demon", 0, {"success_rate": 0.9})
    spec = {"kind": "runs", "title": "t", "results": str(tmp_path), "rows": ["sac_silp_plus", "sac_demon", "sac"],
            "columns": ["method", "success", "seeds"], "seed_notes": 3,
            "checks": [{"text": "a", "all": [{"order": ["sac_silp_plus", "sac_demon", "sac"]}]},
                       {"text": "b", "all": [{"order": ["sac_demon", "sac"], "strict": True}]},
                       {"text": "c", "all": [{"order": ["sac", "sac_demon"]}]}]}
    text = pages.render_block("t", spec, tmp_path / "p.md")
    rows = _rows(text)
    assert rows["sac_silp_plus"][1:] == ["not run", "0"] and rows["sac"][1] == "0.600 (0.100)"
    assert "- `sac_silp_plus`: not run" in text and "- `sac`: 2 of 3 seeds (seeds 0, 1)" in text
    assert "- not run: a (missing: `sac_silp_plus`)" in text
    assert "- holds: b (`sac_demon` 0.900 > `sac` 0.600 (+0.300))" in text
    assert "- does not hold: c (`sac` 0.600 ≥ `sac_demon` 0.900 (-0.300))" in text


def test_a_staged_study_renders_its_rows_as_not_run_until_its_first_run_and_any_other_study_refuses(tmp_path):
    empty = tmp_path / "staged"
    empty.mkdir()
    spec = {"kind": "runs", "title": "t", "results": str(empty), "rows": ["sac", "ddpg"],
            "columns": ["method", "success", "seeds"], "seed_notes": 3}
    with pytest.raises(FileNotFoundError, match="no <method>/seed"):  # a mistyped folder is not a staged study
        pages.render_block("t", spec, tmp_path / "p.md")
    text = pages.render_block("t", {**spec, "staged": True}, tmp_path / "p.md")
    rows = _rows(text)
    assert rows["sac"][1:] == ["not run", "0"] and rows["ddpg"][1:] == ["not run", "0"]
    _run(empty, "sac", 0, {"success_rate": 0.25})
    rows = _rows(pages.render_block("t", {**spec, "staged": True}, tmp_path / "p.md"))
    assert rows["sac"][1:] == ["0.250", "1"] and rows["ddpg"][1:] == ["not run", "0"]


def test_settings_name_each_addition_a_run_had_on():
    run = {**PAPER, "algorithm": "sac", "silp": {**PAPER["silp"], "demos": True, "bc": True}}
    assert tables.additions(run) == []
    # no BC filter is ours; SILP's Q-filter is the paper's too (its SAC-SILP row, Table 4); without BC neither acts
    assert tables.additions({**run, "silp": {**run["silp"], "filter": "none"}}) == ["no BC filter"]
    assert tables.additions({**run, "silp": {**run["silp"], "filter": "q"}}) == []
    assert tables.additions({**run, "silp": {**run["silp"], "filter": "none", "bc": False}}) == []
    run["network"] = {**PAPER["network"], "goal_relative": True}
    run["eval"] = {"actor_average_decay": 0.99}
    assert tables.additions(run) == ["goal-relative input", "averaged actor"]
    # without demonstrations the planner's settings do not act, nor the entropy target in DDPG, nor the
    # candidates' mask without the GP
    plain = {**run, "algorithm": "ddpg", "silp": {"demos": False, "bc": False}, "exploration": {"mode": "random"},
             "planner": {"method": "exact"}, "optim": {"target_entropy": -6}}
    assert tables.additions(plain) == ["goal-relative input", "averaged actor"]
    # a switch an older config lacks takes paper.yaml's settings.absent value (ours: own query, equal, masking)
    old = {k: v for k, v in run.items() if k not in ("planner", "exploration")}
    old["planner"] = {k: v for k, v in PAPER["planner"].items() if k not in ("insert_nodes", "own_query")}
    old["exploration"] = {"mode": "gp"}
    assert tables.additions(old) == ["own query", "equal InsertNodes", "goal-relative input", "averaged actor",
                                     "masked GP candidates"]
    assert tables.additions({"source": "prm"}) is None
    # any other setting a config lacks is never guessed
    with pytest.raises(KeyError, match="silp.filter"):
        tables.additions({**run, "silp": {k: v for k, v in run["silp"].items() if k != "filter"}})


def test_success_by_frames_takes_each_runs_last_evaluation_up_to_the_column(tmp_path):
    ends, curves = [120_000, 120_000, 96_000], []
    for seed, end in enumerate(ends):
        points = [{"frames": f, "success_rate": round(0.5 + f / 400_000 + 0.01 * seed, 4)} for f in range(8000, end + 1, 8000)]
        curves.append({p["frames"]: p["success_rate"] for p in points})
        _run(tmp_path, "ours", seed, {"success_rate": 0.9}, history=points)
    runs = load.load_runs(tmp_path)["ours"]
    lines = tables.success_by_frames({"ours": runs}, every=40_000).splitlines()
    assert lines[0] == "| Frames | 40k | 80k | 96k | 120k |"
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    at = lambda f, seeds: np.array([curves[s][f] for s in seeds])  # noqa: E731
    for i, f in ((1, 40_000), (2, 80_000), (3, 96_000)):
        assert cells[i] == f"{at(f, [0, 1, 2]).mean():.3f} ({at(f, [0, 1, 2]).std():.3f})"
    assert cells[4] == f"{at(120_000, [0, 1]).mean():.3f} ({at(120_000, [0, 1]).std():.3f}) (2 run(s))"


def test_the_command_renders_a_sweeps_own_table1_into_its_page(tmp_path):
    for seed, v in enumerate((0.2, 0.4)):
        _run(tmp_path / "results", "sac", seed, {"success_rate": v, "train_wall_s": 60.0 * (seed + 1), "frames": 100,
                                                 "episodes": 10, "rollout_time_per_episode_s": 0.002})
    md = tmp_path / "docs" / "r.md"
    md.parent.mkdir()
    md.write_text("# r\n\n<!-- table1:begin -->\nold\n<!-- table1:end -->\n\nafter\n")
    text = pages.main(["--results", str(tmp_path / "results"), "--out", str(md), "--figure", str(tmp_path / "c.png")])
    assert md.read_text() == f"# r\n\n{text}\n\nafter\n"
    cells = _rows(text)["sac"]
    assert cells[2] == "0.300 (0.100)" and cells[5] == "0:01:30 (0:00:30)" and cells[3] == "0.864 (0.066)"
    assert cells[4] == f"{0.3 - 0.864:+.3f}"
    assert f"python recipes/report.py --results {tmp_path / 'results'}" in text
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"no <method>/seed\*/summary.json under .*empty"):
        pages.main(["--results", str(tmp_path / "empty"), "--out", str(tmp_path / "x.md")])
    assert not (tmp_path / "x.md").exists()


def test_benchmark_outputs_parse_into_figures(tmp_path):
    out = tmp_path / "update_step.txt"
    out.write_text("$ python benchmarks/update_step.py --threads 1   # note\n"
                   "torch 2.13.0+cpu, 1 thread(s), x86_64, 2 CPUs; ur5e_reach, batch 256\n"
                   "                  part      eager   compiled  (compile)\n"
                   "                update   10.66 ms    6.03 ms  (5 s)\n"
                   "matmul floor of update    5.49 ms  (its matrix products)\n"
                   "with compile.guards=all    6.31 ms  (1.09x)\n")
    bench = load.load_benchmark(out)
    assert bench.command == "python benchmarks/update_step.py --threads 1"
    assert bench.machine == "torch 2.13.0+cpu, 1 thread(s), x86_64, 2 CPUs"
    assert bench.runs == [{"update_eager_ms": 10.66, "update_compiled_ms": 6.03, "update_compile_s": 5.0,
                           "matmul_floor_of_update_ms": 5.49, "with_compile_guards_all_ms": 6.31,
                           "with_compile_guards_all_ratio": 1.09}]
    times = []
    for seed, seconds in enumerate((240.0, 300.0)):
        path = tmp_path / f"tts{seed}.txt"
        path.write_text(f"$ python benchmarks/time_to_success.py --seed {seed}\n  time_to_095_s: {seconds}\n"
                        f"  frames: 104000\nmachine: x86_64, 2 CPUs, threads 2\n")
        times.append(path)
    figures = tables.benchmark_figures(times)
    assert f"{figures['time_to_095_s']:min}" == f"{np.mean([4.0, 5.0]):.1f} min ({np.std([4.0, 5.0]):.1f} min)"
    with pytest.raises(ValueError, match="starts with its command"):
        (tmp_path / "bad.txt").write_text("no command\n")
        load.load_benchmark(tmp_path / "bad.txt")


def test_the_transfer_table_means_over_seeds_beside_the_papers_scenarios(tmp_path):
    perception = {"obstacle_noise": 0.01, "latency_steps": 1, "joint_noise": 1e-4}
    for seed, (free, block) in enumerate([(1.0, 0.9), (0.96, 0.8)]):
        rows = [{"scenario": sc, "noise": "paper", "n_tasks": 100, "success_rate": v, "collision_rate": 1 - v,
                 "time_to_success_s": 1.2 + seed, "perception": perception} for sc, v in (("free", free), ("block", block))]
        result = {"checkpoint": f"runs/x/seed{seed}", "method": "sac_silp_plus", "seed": seed, "trained_episodes": 10_000,
                  "control_dt": 0.1, "max_steps": 50, "rows": rows}
        (tmp_path / "sac_silp_plus" / f"seed{seed}").mkdir(parents=True)
        (tmp_path / "sac_silp_plus" / f"seed{seed}" / "scenarios.json").write_text(json.dumps(result))
    spec = {"kind": "transfer", "title": "t5", "results": str(tmp_path), "scenarios": ["free", "block", "change"],
            "noises": ["none", "paper"], "methods": ["sac_silp_plus"], "paper_rows": ["sac_silp_plus"],
            "labels": {"sac_silp_plus": "the paper's SAC-SILP+ as written (`sac_silp_plus`)"}}
    text = pages.render_block("t5", spec, tmp_path / "p.md")
    free = next(line for line in text.splitlines() if "| free | paper |" in line)
    cells = [c.strip() for c in free.strip("|").split("|")]
    assert cells[3] == f"{np.mean([1.0, 0.96]):.3f} ({np.std([1.0, 0.96]):.3f})"
    assert cells[5] == f"{np.mean([1.2, 2.2]):.2f} ({np.std([1.2, 2.2]):.2f})" and cells[6] == "2"
    assert cells[7:] == ["0.94", "0.92"]  # the paper: 3 and 4 failures in 50 Free trials
    assert "| block | none |" not in text and "box noise 0.01 m, latency 1 step(s)" in text
    with pytest.raises(FileNotFoundError, match="transfer"):
        load.load_transfer(tmp_path / "none")


def test_replacing_a_block_keeps_the_page_around_it():
    page = "# p\n\nprose\n\n<!-- b:begin -->\nold\n<!-- b:end -->\n\nmore\n"
    new = pages.replace_block(page, "b", "<!-- b:begin -->\nnew\n<!-- b:end -->")
    assert new == "# p\n\nprose\n\n<!-- b:begin -->\nnew\n<!-- b:end -->\n\nmore\n"
    assert pages.committed_block(new, "b") == "<!-- b:begin -->\nnew\n<!-- b:end -->"
    assert pages.replace_block("# p\n", "c", "X") == "# p\n\nX\n" and pages.committed_block("# p\n", "c") is None


def test_gaps_to_the_paper_group_rows_by_cause_and_name_rows_without_one(tmp_path):
    for seed, v in enumerate((0.2, 0.3)):
        _run(tmp_path, "sac", seed, {"success_rate": v})
    _run(tmp_path, "ddpg", 0, {"success_rate": 0.1})
    _run(tmp_path, "sac_her", 0, {"success_rate": 0.85})
    _run(tmp_path, "sac_demon", 0, {"success_rate": 0.5})
    paper = tables.paper()["table1"]
    spec = {"kind": "runs", "title": "t", "results": str(tmp_path), "paper": "table1",
            "rows": ["sac", "ddpg", "sac_her", "sac_demon"], "columns": ["method", "success", "paper_gap"],
            "gaps": {"threshold": 0.1, "causes": {"sac": "Cause A.", "ddpg": "Cause A."}}}
    text = pages.render_block("t", spec, tmp_path / "p.md")
    gap = {m: v - paper[m]["success"][0] for m, v in {"sac": 0.25, "ddpg": 0.1, "sac_her": 0.85, "sac_demon": 0.5}.items()}
    rows = _rows(text)
    assert [rows[m][2] for m in gap] == [f"{g:+.3f}" for g in gap.values()]
    assert f"- `sac` ({gap['sac']:+.3f}), `ddpg` ({gap['ddpg']:+.3f}): Cause A." in text
    assert f"- `sac_demon` ({gap['sac_demon']:+.3f}): No cause measured or stated." in text
    assert abs(gap["sac_her"]) <= 0.1 and "`sac_her` (" not in text  # within the threshold: no cause asked


def _checked(root: Path, success: dict[str, np.ndarray], checks: list[dict]) -> str:
    """A runs block of one row per method, its seeds' test success as given, rendered with ``checks``."""
    for method, values in success.items():
        for seed, value in enumerate(values):
            _run(root, method, seed, {"success_rate": float(value)})
    spec = {"kind": "runs", "title": "t", "results": str(root), "rows": list(success),
            "columns": ["method", "success"], "checks": checks}
    return pages.render_block("t", spec, root / "p.md")


def test_an_ordering_of_spreads_reads_each_rows_std_over_seeds(tmp_path):
    wide, narrow = np.array([0.2, 0.6, 0.9]), np.array([0.5, 0.52, 0.55])
    text = _checked(tmp_path, {"ddpg_her": wide, "ddpg": narrow},
                    [{"text": "HER spreads most", "all": [{"order": ["ddpg_her", "ddpg"], "stat": "std", "strict": True}]},
                     {"text": "HER on top", "all": [{"order": ["ddpg_her", "ddpg"], "strict": True}]},
                     {"text": "HER at 0.6 or more", "all": [{"order": ["ddpg_her", 0.6]}]}])
    assert f"- holds: HER spreads most (`ddpg_her` (std) {wide.std():.3f} > `ddpg` (std) {narrow.std():.3f})" in text
    # the difference of the means lies within the wider row's spread, and the line says so
    diff = wide.mean() - narrow.mean()
    assert 0 < diff < wide.std()
    assert (f"- holds: HER on top (`ddpg_her` {wide.mean():.3f} > `ddpg` {narrow.mean():.3f} ({diff:+.3f}, within "
            f"the seeds' spread: std up to {wide.std():.3f}))") in text
    assert wide.mean() < 0.6 and f"- does not hold: HER at 0.6 or more (`ddpg_her` {wide.mean():.3f} ≥ 0.600)" in text


def test_a_runs_block_bounds_a_difference_with_the_same_judge_as_table5(tmp_path):
    a, b = np.array([0.90, 0.92, 0.88]), np.array([0.70, 0.80, 0.75])
    pair = ["sac_silp_plus", "sac_demon"]
    text = _checked(tmp_path, dict(zip(pair, (a, b))),
                    [{"text": "close", "all": [{"order": pair, "max_difference": 0.1}]},
                     {"text": "on top and close", "all": [{"order": pair}, {"order": pair, "max_difference": 0.2}]}])
    gap = a.mean() - b.mean()  # 0.15
    assert (f"- does not hold: close (`sac_silp_plus` {a.mean():.3f} − `sac_demon` {b.mean():.3f} = {gap:.3f} > 0.100)"
            in text)
    assert (f"- holds: on top and close (`sac_silp_plus` {a.mean():.3f} ≥ `sac_demon` {b.mean():.3f} ({gap:+.3f}); "
            f"`sac_silp_plus` {a.mean():.3f} − `sac_demon` {b.mean():.3f} = {gap:.3f} ≤ 0.200)") in text


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=2, max_size=5), st.booleans())
def test_an_ordering_holds_exactly_when_each_value_is_at_least_the_next(values, strict):
    names = [f"m{i}" for i in range(len(values))]
    line = tables.judge({"text": "t", "all": [{"order": names, "strict": strict}]},
                        lambda m, key, stat: values[names.index(m)])
    pairs = list(zip(values, values[1:]))
    expected = all(x > y for x, y in pairs) if strict else all(x >= y for x, y in pairs)
    assert line.startswith("- holds: t (" if expected else "- does not hold: t (")
    missing = tables.judge({"text": "t", "all": [{"order": names}]}, lambda m, key, stat: None if m == "m1" else 0.5)
    assert missing == "- not run: t (missing: `m1`)"


def test_the_planning_rows_read_the_benchmarks_table_and_check_each_trend(tmp_path):
    bench = tmp_path / "planner.txt"
    rows = [("random", "0.10", "0.900", "2.50", "0.20"), ("random", "0.20", "0.950", "1.50", "0.30"),
            ("scripted", "0.10", "0.700", "3.00", "0.10"), ("scripted", "0.20", "0.650", "2.00", "0.05")]
    bench.write_text("$ python benchmarks/planner.py --threads 1\ntorch 2.13.0+cpu, cpu; seed 0\n\n"
                     "### Planning vs the roadmap distance d (Table A.1), B = 4\n\n"
                     "| rollouts | d (m) | SR pairs | path edges | ms/plan |\n|:--|--:|--:|--:|--:|\n"
                     + "".join(f"| {' | '.join(r)} |\n" for r in rows) + "\nnotes\n")
    spec = {"file": str(bench), "table": "Planning vs the roadmap distance d", "kind_column": "rollouts",
            "parameter_column": "d (m)", "paper": "tableA1",
            "columns": {"0.10": "sac_silp_plus_d0.10", "0.20": "sac_silp_plus_d0.20"},
            "measures": {"SR pairs": ["SR", "planning_success", ".3f"], "ms/plan": ["time (s)", "plan_s", ".4f", 0.001]},
            "trends": [{"text": "SR rises", "measure": "SR pairs", "order": "increasing"},
                       {"text": "time falls", "measure": "ms/plan", "order": "decreasing"}]}
    text = "\n".join(tables.planning_table(spec))
    paper = tables.paper()["tableA1"]
    assert "| SR | random | 0.900 | 0.950 |" in text and "| SR | scripted | 0.700 | 0.650 |" in text
    assert f"| SR | the paper | {paper['sac_silp_plus_d0.10']['planning_success']:.3f} | " \
           f"{paper['sac_silp_plus_d0.20']['planning_success']:.3f} |" in text
    assert "| time (s) | random | 0.0002 | 0.0003 |" in text  # ms to the paper's seconds
    assert f"| time (s) | the paper | {paper['sac_silp_plus_d0.10']['plan_s'][0]:.4f} |" in text
    assert "- holds: SR rises, random roadmaps (SR pairs: 0.900 ≤ 0.950)" in text
    assert "- does not hold: SR rises, scripted roadmaps (SR pairs: 0.700 ≤ 0.650)" in text
    assert "- does not hold: time falls, random roadmaps (ms/plan: 0.20 ≥ 0.30)" in text
    assert "- holds: time falls, scripted roadmaps (ms/plan: 0.10 ≥ 0.05)" in text
    assert "Made by: `python benchmarks/planner.py --threads 1`" in text


def test_table5_means_each_policys_reaching_trials_over_seeds_and_checks_the_papers_order(tmp_path):
    rng = np.random.default_rng(1)
    shares = {}
    for method in ("table5_a", "table5_b"):
        for seed in range(3):
            per = rng.integers(0, 11, 10) / 10  # ten scenarios of ten trials
            shares[method, seed] = per
            row = {"scenario": "reaching", "noise": "paper", "n_tasks": 100, "success_rate": float(per.mean()),
                   "collision_rate": 0.01 * seed, "scenario_success": per.tolist()}
            run = tmp_path / method / f"seed{seed}"
            run.mkdir(parents=True)
            (run / "summary.json").write_text(json.dumps({"method": method, "seed": seed, "rows": [row]}))
    spec = {"kind": "reaching", "title": "t5", "results": str(tmp_path), "sweep_config": "s.yaml", "paper": "table5",
            "noises": ["none", "paper"],
            "rows": [{"method": "table5_a", "paper": "sac_silp_plus", "label": "A"},
                     {"method": "table5_b", "paper": "sac_demon", "label": "B"}],
            "checks": [{"text": "A ≥ B", "noise": "paper", "order": ["table5_a", "table5_b"]},
                       {"text": "A ≥ B unnoised", "noise": "none", "order": ["table5_a", "table5_b"]},
                       {"text": "A near B", "noise": "paper", "order": ["table5_a", "table5_b"], "max_difference": 0.05},
                       {"text": "A far from B", "noise": "paper", "order": ["table5_a", "table5_b"], "max_difference": 1.0}]}
    text = pages.render_block("table5", spec, tmp_path / "p.md")
    success = {m: np.array([shares[m, s].mean() for s in range(3)]) for m in ("table5_a", "table5_b")}
    paper = tables.paper()["table5"]
    assert (f"| A | paper | {success['table5_a'].mean():.3f} ({success['table5_a'].std():.3f}) | 0.010 (0.008) | 3 | "
            f"{paper['sac_silp_plus']['simulation'][0]:.3f} | {paper['sac_silp_plus']['real'][0]:.3f} |") in text
    assert "| A | none | not run | — | 0 |" in text
    per_a = np.mean([shares["table5_a", s] for s in range(3)], axis=0)
    assert "| A | paper | " + " | ".join(f"{x:.2f}" for x in per_a) + " |" in text
    holds = success["table5_a"].mean() >= success["table5_b"].mean()
    assert f"- {'holds' if holds else 'does not hold'}: A ≥ B (`table5_a` {success['table5_a'].mean():.3f}" in text
    assert "- not run: A ≥ B unnoised" in text
    gap = success["table5_a"].mean() - success["table5_b"].mean()
    near = "holds" if gap <= 0.05 else "does not hold"
    assert f"- {near}: A near B (`table5_a` {success['table5_a'].mean():.3f} − `table5_b` {success['table5_b'].mean():.3f}" in text
    assert f"- holds: A far from B (`table5_a` {success['table5_a'].mean():.3f} − `table5_b` {success['table5_b'].mean():.3f} = {gap:.3f} ≤ 1.000)" in text
    bad = dict(spec, checks=[{"text": "x", "noise": "paper", "order": ["table5_a", "table5_b", "table5_a"], "max_difference": 0.1}])
    with pytest.raises(ValueError, match="compares two rows"):
        pages.render_block("table5", bad, tmp_path / "p.md")


def test_orderings_of_times_are_judged_only_on_one_machine_kind_with_as_many_runs_at_once():
    values = {"sac": 2000.0, "sac_silp_plus": 1800.0}
    check = {"text": "less time", "all": [{"order": ["sac", "sac_silp_plus"], "key": "train_wall_s", "strict": True}]}
    same = tables.judge(check, lambda m, key, stat: values[m] if stat == "mean" else 0.0, lambda m: {"xeon, 1 at once"})
    assert same == "- holds: less time (`sac` 2,000 > `sac_silp_plus` 1,800 (10% less))"
    where = {"sac": {"xeon, 1 at once"}, "sac_silp_plus": {"epyc, 2 at once"}}
    unlike = tables.judge(check, lambda m, key, stat: values[m] if stat == "mean" else 0.0, where.__getitem__)
    assert unlike.startswith("- not judged, the runs' machines differ: less time (")
    assert "`sac` on xeon, 1 at once" in unlike and "`sac_silp_plus` on epyc, 2 at once" in unlike
    # a row whose own runs ran on two kinds is not judged either; success rates are judged wherever they ran
    mixed = tables.judge(check, lambda m, key, stat: values[m], lambda m: {"xeon, 1 at once", "epyc, 2 at once"})
    assert mixed.startswith("- not judged")
    success = {"text": "s", "all": [{"order": ["sac", "sac_silp_plus"]}]}
    assert tables.judge(success, lambda m, key, stat: 0.5, where.__getitem__).startswith("- holds: s (")


def test_a_rows_label_names_the_random_recovery_the_paper_does_not_run(tmp_path):
    checked = _paper_sac(exploration__mode="random", exploration__mask_colliding_candidates=True)
    unchecked = _paper_sac(exploration__mode="random", exploration__mask_colliding_candidates=False)
    type0 = _paper_sac(exploration__mode="random", exploration__mask_colliding_candidates=False, env__collision_type=0)
    for method, config in (("sac", checked), ("sac_unchecked", unchecked), ("sac_type0", type0)):
        _run(tmp_path, method, 0, {"success_rate": 0.5}, config)
    runs = load.load_runs(tmp_path)
    assert tables.method_label("sac", runs["sac"], "SAC") == "the paper's SAC as written (`sac`)"
    assert (tables.method_label("sac_unchecked", runs["sac_unchecked"], "SAC")
            == "the paper's SAC with an unchecked random recovery action (`sac_unchecked`)")
    # type 0 ends the episode at a collision: no recovery action follows, none is named
    assert tables.method_label("sac_type0", runs["sac_type0"], "SAC") == "the paper's SAC as written (`sac_type0`)"
    ours = _paper_sac(exploration__mode="random", exploration__mask_colliding_candidates=False, network__goal_relative=True)
    assert tables.additions(ours) == ["goal-relative input", "an unchecked random recovery action"]


def test_a_value_after_n_episodes_is_the_first_evaluation_past_them(tmp_path):
    history = [{"episodes": 400, "success_rate": 0.1}, {"episodes": 1010, "success_rate": 0.4},
               {"episodes": 1500, "success_rate": 0.7}]
    _run(tmp_path, "sac", 0, {"success_rate": 0.9}, history=history)
    run = load.load_runs(tmp_path)["sac"][0]
    assert run.value("success_rate@episodes=1000") == 0.4 and run.value("success_rate@episodes=1500") == 0.7
    assert run.value("success_rate@episodes=1501") is None and run.value("success_rate") == 0.9



def test_the_split_and_sampled_action_columns_average_each_kind_over_the_runs(tmp_path):
    splits = [(0.6, 1.0, 0.25, 0.5), (0.7, 0.9, 0.35, 0.7)]  # free share, free success, blocked success, sampled
    for seed, (share, free, blocked, sampled) in enumerate(splits):
        _run(tmp_path, "sac", seed, {"success_rate": share * free + (1 - share) * blocked, "test_free_task_share": share,
                                     "test_free_success_rate": free, "test_blocked_success_rate": blocked,
                                     "sampling_success_rate": sampled})
    _run(tmp_path, "sac_old", 0, {"success_rate": 0.5})  # a run from before the split: no figure, no guess
    _run(tmp_path, "sac_mixed", 0, {"success_rate": 0.5})  # a row with one run from before the split, one after
    _run(tmp_path, "sac_mixed", 1, {"success_rate": 0.5, "test_free_task_share": 0.5, "test_free_success_rate": 0.75,
                                    "test_blocked_success_rate": 0.25, "sampling_success_rate": 0.4})
    spec = {"kind": "runs", "title": "a split", "results": str(tmp_path), "name": "SAC",
            "columns": ["method", "sampling", "free_blocked"]}
    rows = _rows(pages.render_block("a_split", spec, tmp_path / "page.md"))
    mean = np.mean(splits, axis=0)
    assert rows["sac"][1] == f"{mean[3]:.3f} ({np.std([s[3] for s in splits]):.3f})"
    assert rows["sac"][2] == f"{mean[1]:.3f} / {mean[2]:.3f} ({mean[0]:.3f} free)"
    assert rows["sac_old"][1:] == ["—", "—"]
    assert rows["sac_mixed"][1:] == ["0.400 (1 of 2 runs)", "0.750 / 0.250 (0.500 free) (1 of 2 runs)"]
