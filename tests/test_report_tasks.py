"""recipes/report.py --block tasks: the two-task table and the redesign's acceptance figures from results files."""

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


def _run(root: Path, method: str, seed: int, task: str, success: float, frames: int, collisions: int, swept: int):
    run = root / method / f"seed{seed}"
    run.mkdir(parents=True)
    summary = {"success_rate": success, "frames": frames, "train_wall_s": 600.0 + seed, "time_to_095_s": None,
               "collisions_during_training": collisions, "swept_collisions_during_training": swept}
    (run / "summary.json").write_text(json.dumps(summary))
    history = [{"episodes": e, "success_rate": success * e / 300, "frames": 50 * e} for e in (100, 200, 300)]
    (run / "history.json").write_text(json.dumps({"history": history}))
    (run / "config.yaml").write_text(yaml.safe_dump({"env": {"name": task}, "collector": {"total_frames": frames},
                                                     "device": "cpu", "threads": 1}))


def test_tasks_block_reports_both_tasks_and_the_acceptance_figures(tmp_path):
    results = tmp_path / "results"
    panda = [0.93, 0.91, 0.95]
    ur5e = [0.965, 0.975]
    for seed, s in enumerate(panda):
        _run(results, "panda_sac_silp_plus_ext", seed, "panda_reach", s, 300_000, 1000, 100 + seed)
    for seed, s in enumerate(ur5e):
        _run(results, "ur5e_sac_silp_plus_ext", seed, "ur5e_reach", s, 160_000, 500, 20)
    md, png = tmp_path / "results.md", tmp_path / "curves.png"
    md.write_text("# results\n\nkept\n")
    text = report.main(["--block", "tasks", "--results", str(results), "--out", str(md), "--figure", str(png)])
    rows = {line.split("|")[2].strip(): line for line in text.splitlines() if line.startswith("| panda") or line.startswith("| ur5e")}
    assert f"{np.mean(panda):.3f} ({np.std(panda):.3f})" in rows["panda_sac_silp_plus_ext"]
    assert f"{np.mean([101, 102, 100]):.0f} ({np.mean([100, 101, 102]) / 1000:.1%})" in rows["panda_sac_silp_plus_ext"]
    assert "| ur5e_reach | ur5e_sac_silp_plus_ext |" in rows["ur5e_sac_silp_plus_ext"]
    # three Panda seeds all >= 0.90 within 300k frames: holds; two UR5e seeds: not yet
    assert "- holds: Panda SAC-SILP+ extended" in text
    assert "- does not hold (yet): no regression of the UR5e default config" in text
    assert f"{np.mean(ur5e):.3f} over 2 seed(s)" in text
    page = md.read_text()
    assert page.startswith("# results\n\nkept\n") and report.TASKS_BEGIN in page and png.stat().st_size > 0
    # regenerating replaces the block byte for byte
    report.main(["--block", "tasks", "--results", str(results), "--out", str(md), "--figure", str(png)])
    assert md.read_text() == page


def test_speed_block_holds_the_benchmark_outputs_verbatim(tmp_path):
    import report

    results = tmp_path / "benchmarks"
    results.mkdir()
    (results / "rollout_time.txt").write_text("$ python benchmarks/rollout_time.py RUN\n  compiled: 3.1 ms\n")
    out = tmp_path / "results.md"
    out.write_text("# page\n\nkept\n")
    text = report.main(["--block", "speed", "--results", str(results), "--out", str(out)])
    page = out.read_text()
    assert page.startswith("# page\n\nkept\n") and text in page
    assert "```\n$ python benchmarks/rollout_time.py RUN\n  compiled: 3.1 ms\n```" in page
    assert "No GPU figure yet" in page
    # regenerated in place, not appended twice
    report.main(["--block", "speed", "--results", str(results), "--out", str(out)])
    assert out.read_text().count("<!-- speed:begin -->") == 1
    with pytest.raises(FileNotFoundError, match="no benchmark output"):
        report.speed_block(tmp_path / "empty", "cmd")
    # a GPU run's output replaces the line saying there is none, and says where it came from
    (results / "gpu_update_step.txt").write_text("$ python benchmarks/update_step.py device=cuda\ntorch 2.11.0+cu130\n")
    block = report.speed_block(results, "cmd")
    assert "No GPU figure yet" not in block and "benchmarks/gpu.sh" in block
    assert "```\n$ python benchmarks/update_step.py device=cuda\ntorch 2.11.0+cu130\n```" in block


def test_settings_name_each_addition_a_run_had_on():
    from omegaconf import OmegaConf

    paper = OmegaConf.to_container(OmegaConf.load(RECIPES / "config" / "paper_settings.yaml"))
    run = {**paper, "algorithm": "sac", "silp": {**paper["silp"], "demos": True, "bc": True}}
    assert report.additions(run) == []
    # no BC filter is ours; SILP's Q-filter is the paper's too (its SAC-SILP row, Table 4); without BC neither acts
    assert report.additions({**run, "silp": {**run["silp"], "filter": "none"}}) == ["no BC filter"]
    assert report.additions({**run, "silp": {**run["silp"], "filter": "q"}}) == []
    assert report.additions({**run, "silp": {**run["silp"], "filter": "none", "bc": False}}) == []
    run["network"] = {**paper["network"], "goal_relative": True}
    run["eval"] = {"actor_average_decay": 0.99}
    assert report.additions(run) == ["goal-relative input", "averaged actor"]
    # without demonstrations the planner's settings do not act, nor the entropy target in DDPG,
    # nor the candidates' mask without the GP
    plain = {**run, "algorithm": "ddpg", "silp": {"demos": False, "bc": False}, "exploration": {"mode": "random"},
             "planner": {"method": "exact"}, "optim": {"target_entropy": -6}}
    assert report.additions(plain) == ["goal-relative input", "averaged actor"]
    # the switches an older run's config lacks take the schema's defaults (ours: equal InsertNodes, own query, masking)
    old = {k: v for k, v in run.items() if k not in ("planner", "exploration")}
    old["planner"] = {k: v for k, v in paper["planner"].items() if k not in ("insert_nodes", "own_query")}
    old["exploration"] = {"mode": "gp"}
    assert report.additions(old) == ["own query", "equal InsertNodes", "goal-relative input", "averaged actor",
                                     "masked GP candidates"]
    assert report.additions({"source": "prm"}) is None
    # a setting whose default has changed (no BC filter since the reward filter) is never guessed
    unknown_filter = {**run, "silp": {k: v for k, v in run["silp"].items() if k != "filter"}}
    with pytest.raises(KeyError, match="silp.filter"):
        report.additions(unknown_filter)
    assert report.settings_text([{"config": run}, {"config": {**run, "eval": {"actor_average_decay": None}}}]) == (
        "ours: +goal-relative input, +averaged actor; ours: +goal-relative input")


@pytest.mark.parametrize("name", report.BLOCKS)
def test_the_page_blocks_regenerate_from_the_committed_results(name, tmp_path, monkeypatch):
    """docs/results.md's generated blocks are what recipes/report.py makes of results/ (byte for byte)."""
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)  # the paths in the blocks are the CLI's, relative to the repository root
    page = Path("docs/results.md").read_text()
    begin, end = report.markers(name)
    assert page.count(begin) == 1 and page.count(end) == 1, f"docs/results.md holds the {name} block once"
    command = "python recipes/report.py" + ("" if name == "table1" else f" --block {name}")
    results = Path(report.RESULTS_OF.get(name, f"results/{name}"))
    text = report.render(name, results, Path(f"docs/{name}_curves.png"), Path("docs/results.md"), command,
                         plot_to=tmp_path / "figure.png")  # the committed picture is left alone
    assert text in page


def _main_job_config(*overrides: str) -> dict:
    """The resolved config the main job saves with a run, as ``recipes/sac_silp.py`` composes it."""
    from hydra import compose
    from omegaconf import OmegaConf
    import sweep

    with sweep.config_context():
        return OmegaConf.to_container(compose(config_name="sac_silp", overrides=list(overrides)), resolve=True)


def _default_config_run(results: Path, seed: int, summary: dict, total_frames: int, history=None) -> Path:
    """A run of the main job's default config (sac_silp_plus_ext on the UR5e, validation-task evaluations)."""
    run = results / "sac_silp_plus_ext" / f"seed{seed}"
    run.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps(
        {"collisions_during_training": 3000, "swept_collisions_during_training": 1500, **summary}))
    (run / "config.yaml").write_text(yaml.safe_dump(_main_job_config(f"collector.total_frames={total_frames}")))
    if history is not None:
        (run / "history.json").write_text(json.dumps({"history": history}))
    return run


def test_default_config_block_checks_the_end_of_budget_success_over_seeds(tmp_path):
    results = tmp_path / "default_config"
    for seed, (success, reached) in enumerate([(0.984, 300.0), (0.978, None)]):
        _default_config_run(results, seed, {"success_rate": success, "frames": 160_000,
                                            "train_wall_s": 1500.0 + seed, "time_to_095_s": reached}, 160_000)
    out = tmp_path / "results.md"
    text = report.main(["--block", "default_config", "--results", str(results), "--out", str(out)])
    row = next(line for line in text.splitlines() if line.startswith("| ur5e_reach |"))
    assert "0.981 (0.003)" in row and "| 2 | 160000 |" in row
    assert "0:05:00 (1/2 reached)" in row  # the mean over the seeds that reached it
    assert "on the validation tasks" in text
    # two seeds of three: not yet, whatever the mean
    assert "- not yet (fewer seeds than that): the default config's test success" in text
    assert "0.981 over 2 seed(s)" in text
    run = results / "sac_silp_plus_ext" / "seed2"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"success_rate": 0.986, "frames": 160_000, "train_wall_s": 1490.0,
                                                  "time_to_095_s": 280.0}))
    (run / "config.yaml").write_text((results / "sac_silp_plus_ext" / "seed0" / "config.yaml").read_text())
    text = report.main(["--block", "default_config", "--results", str(results), "--out", str(out)])
    assert "- holds: the default config's test success" in text and f"{np.mean([0.984, 0.978, 0.986]):.3f} over 3" in text
    assert out.read_text().count("<!-- default_config:begin -->") == 1
    # a mean below 0.98 over 3 seeds does not hold
    (run / "summary.json").write_text(json.dumps({"success_rate": 0.95, "frames": 160_000, "train_wall_s": 1490.0}))
    text = report.main(["--block", "default_config", "--results", str(results), "--out", str(out)])
    assert "- does not hold: the default config's test success" in text


def test_default_config_block_gives_the_validation_success_at_every_40k_frames(tmp_path):
    results = tmp_path / "default_config"
    ends = [120_000, 120_000, 96_000]  # the third run stopped early: the 120k column has two runs
    curves = []
    for seed, end in enumerate(ends):
        points = [{"frames": f, "success_rate": round(0.5 + f / 400_000 + 0.01 * seed, 4)}
                  for f in range(8000, end + 1, 8000)]
        curves.append({p["frames"]: p["success_rate"] for p in points})
        _default_config_run(results, seed, {"success_rate": 0.97, "frames": end, "train_wall_s": 900.0},
                            120_000, history=points)
    text = report.main(["--block", "default_config", "--results", str(results), "--out", str(tmp_path / "r.md")])
    lines = text.splitlines()
    header = lines.index("| Frames | 40k | 80k | 96k | 120k |")
    cells = [c.strip() for c in lines[header + 2].strip("|").split("|")]
    assert cells[0] == "Success rate"
    # 40k and 80k are history points of every run; 96k is the third run's last point; 120k has two runs
    at = lambda f, seeds: np.array([curves[s][f] for s in seeds])
    assert cells[1] == f"{at(40_000, [0, 1, 2]).mean():.3f} ({at(40_000, [0, 1, 2]).std():.3f})"
    assert cells[2] == f"{at(80_000, [0, 1, 2]).mean():.3f} ({at(80_000, [0, 1, 2]).std():.3f})"
    assert cells[3] == f"{at(96_000, [0, 1, 2]).mean():.3f} ({at(96_000, [0, 1, 2]).std():.3f})"
    assert cells[4] == f"{at(120_000, [0, 1]).mean():.3f} ({at(120_000, [0, 1]).std():.3f}) (2 run(s))"
    assert "Success on the validation tasks during training" in text


def test_budget_choice_block_gives_the_validation_curve_and_the_test_success_of_the_longer_runs(tmp_path):
    results = tmp_path / "default_config_320k"
    final = {0: 0.975, 1: 0.985}
    for seed, test_success in final.items():
        points = [{"frames": f, "success_rate": 0.9 + seed * 0.02} for f in range(8000, 80_001, 8000)]
        _default_config_run(results, seed, {"success_rate": test_success, "frames": 80_000, "train_wall_s": 600.0,
                                            "time_to_095_s": None}, 80_000, history=points)
    out = tmp_path / "results.md"
    text = report.main(["--block", "budget_choice", "--results", str(results), "--out", str(out)])
    assert ("### The main job's default config with a larger frame budget and the reward filter "
            "(`silp.filter=reward`, the default when it ran), 80,000 frames (generated)") in text
    assert "| Frames | 40k | 80k |" in text
    assert "| Success rate | 0.910 (0.010) | 0.910 (0.010) |" in text  # seeds at 0.90 and 0.92 throughout
    row = next(line for line in text.splitlines() if line.startswith("| ur5e_reach |"))
    assert f"| {np.mean(list(final.values())):.3f} ({np.std(list(final.values())):.3f}) | 2 | 80000 |" in row
    assert out.read_text().count("<!-- budget_choice:begin -->") == 1
