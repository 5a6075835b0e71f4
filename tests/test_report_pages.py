"""The results pages: every generated block is what the committed results files give, its tables agree
with figures computed here from those files, and the pages stay short and their links resolve."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from torchrl_silp.recipes.reporting import pages

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    monkeypatch.chdir(ROOT)  # the pages' paths are the command's, relative to the repository root


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _block_rows(path: str, name: str) -> dict[str, list[str]]:
    """The first table of a committed block: ``{run folder: cells}`` by the row's `(method)` name."""
    text = pages.committed_block((ROOT / path).read_text(), name)
    assert text is not None, f"{path} holds no {name} block"
    rows = {}
    for line in text.splitlines():
        match = re.search(r"\(`([^`]+)`\) \|", line)
        if line.startswith("| ") and match and match.group(1) not in rows:
            rows[match.group(1)] = _cells(line)
    return rows


def _summaries(folder: str, method: str) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((ROOT / folder / method).glob("seed*/summary.json"))]


def _mean_std(values, decimals=3) -> str:
    arr = np.asarray(values, dtype=float)
    return f"{arr.mean():.{decimals}f}" if arr.size == 1 else f"{arr.mean():.{decimals}f} ({arr.std():.{decimals}f})"


def test_every_page_block_regenerates_byte_for_byte_from_the_committed_results():
    assert pages.check() == []
    with pytest.raises(SystemExit) as exit_:
        pages.main(["--check"])
    assert exit_.value.code == 0


def test_a_changed_page_block_fails_the_check(tmp_path, monkeypatch):
    page = ROOT / "docs" / "results" / "tasks.md"
    text = page.read_text()
    tampered = tmp_path / "tasks.md"
    tampered.write_text(text.replace("| panda_reach |", "| panda_reach_x |", 1))
    monkeypatch.setitem(pages.spec()["pages"], "tasks", {"path": str(tampered), "blocks": ["tasks"]})
    problems = pages.check()
    # the block differs, and the figure it links is not beside this copy of the page
    assert problems == [f"{tampered}: block tasks differs from what `python recipes/report.py --block tasks` writes",
                        f"{tampered}: block tasks links img/tasks_curves.png, which does not exist"]
    tampered.write_text(text.replace("<!-- tasks:begin -->", ""))
    assert any("no tasks block" in p for p in pages.check())


def test_table1_rows_are_the_means_of_the_summary_files():
    rows = _block_rows("docs/results/table1.md", "table1")
    assert len(rows) == 16
    for method, cells in rows.items():
        runs = _summaries("results/paper_budget", method)
        assert cells[9] == str(len(runs)) == "3"
        assert cells[2] == _mean_std([r["success_rate"] for r in runs]), method
        assert cells[10] == _mean_std([r["test_collision_rate"] for r in runs]), method
    # the paper's column is the paper's Table 1 (tab:bl), the extended rows beside their own method's
    assert rows["sac_silp_plus"][3] == rows["sac_silp_plus_ext"][3] == "0.973 (0.002)"
    assert rows["bc_prm"][3] == "0.464 (0.015)" and rows["prm_1"][5] == rows["prm_1"][6] == "*"
    assert rows["sac_silp_plus"][0].startswith("the paper's SAC-SILP+ as written")
    assert rows["sac_silp_plus_ext"][0].startswith("ours: SAC-SILP+ + additions")


def test_table1_differences_and_orderings_follow_the_summary_files():
    text = pages.committed_block((ROOT / "docs/results/table1.md").read_text(), "table1")
    success = {m: np.mean([r["success_rate"] for r in _summaries("results/paper_budget", m)])
               for m in ("sac_silp_plus", "sac_silp_plus_ext", "sac_demon", "sac", "prm_0.1")}
    assert f"`sac_silp_plus_ext` − `sac_silp_plus`: {success['sac_silp_plus_ext'] - success['sac_silp_plus']:+.3f}" in text
    holds = success["sac_silp_plus"] >= success["sac_demon"] >= success["sac"]
    assert f"- {'holds' if holds else 'does not hold'}: SAC-SILP+ ≥ SAC-Demon ≥ SAC (" in text


def test_table1_states_each_rows_gap_to_the_paper_and_the_cause_beyond_a_tenth():
    """Every row further than 0.1 from the paper's test success names a cause (none may say it has none)."""
    paper = yaml.safe_load((ROOT / "recipes/reporting/paper.yaml").read_text())["table1"]
    block = pages.spec()["blocks"]["table1"]
    rows = _block_rows("docs/results/table1.md", "table1")
    text = pages.committed_block((ROOT / "docs/results/table1.md").read_text(), "table1")
    beyond = []
    for spec in block["rows"]:
        method, entry = (spec, spec) if isinstance(spec, str) else (spec["method"], spec.get("paper", spec["method"]))
        gap = np.mean([r["success_rate"] for r in _summaries("results/paper_budget", method)]) - paper[entry]["success"][0]
        assert rows[method][4] == f"{gap:+.3f}", method
        if abs(gap) > 0.1:
            beyond.append(method)
            line = next(line for line in text.splitlines() if f"`{method}` ({gap:+.3f})" in line)
            assert method in block["gaps"]["causes"] and "No cause measured" not in line, method
    assert {"sac", "ddpg"} <= set(beyond)  # the baselines' gaps the issue asks to explain


def test_table2_ordering_for_sac_fails_as_its_summary_files_say():
    rows = _block_rows("docs/results/paper_tables.md", "table2")
    means = {m: np.mean([r["success_rate"] for r in _summaries("results/paper_budget", m)]) for m in rows}
    assert not means["sac"] >= means["sac_collision0"] >= means["sac_collision1"]
    text = pages.committed_block((ROOT / "docs/results/paper_tables.md").read_text(), "table2")
    assert "- does not hold: SAC: type-2 ≥ type-0 ≥ type-1" in text
    for method, cells in rows.items():
        collisions = [r["collisions_during_training"] for r in _summaries("results/paper_budget", method)]
        assert cells[7] == f"{np.mean(collisions):,.0f} ({np.std(collisions):,.0f})"


def test_ablations_sort_each_change_by_twice_ours_seed_spread():
    rows = _block_rows("docs/results/ablations.md", "ablations")
    ours = [r["validation_success_rate"] for r in _summaries("results/paper_budget", "sac_silp_plus_ext")]
    seed0 = json.loads((ROOT / "results/paper_budget/sac_silp_plus_ext/seed0/summary.json").read_text())
    for method, cells in rows.items():
        if method == "sac_silp_plus_ext":
            continue
        value = json.loads((ROOT / f"results/paper_budget/{method}/seed0/summary.json").read_text())["validation_success_rate"]
        delta = value - seed0["validation_success_rate"]
        assert cells[2] == f"{value:.3f}" and cells[3] == f"{delta:+.3f}"
        assert cells[4] == ("beyond" if abs(delta) > 2 * np.std(ours) else "within"), method


def test_the_headline_is_the_summary_files_and_the_benchmark_outputs():
    block = pages.committed_block((ROOT / "docs/results/index.md").read_text(), "headline")
    lines = [line for line in block.splitlines() if line.startswith("| ")][1:]  # past the header
    for line, method in zip(lines, ("sac_silp_plus", "sac_silp_plus_ext")):
        assert _cells(line)[2] == _mean_std([r["success_rate"] for r in _summaries("results/paper_budget", method)])
    seconds = [float(re.search(r"time_to_095_s: ([\d.]+)", (ROOT / f"results/benchmarks/time_to_success_seed{k}.txt")
                               .read_text()).group(1)) for k in range(3)]
    minutes = np.asarray(seconds) / 60
    assert _cells(lines[2])[2] == f"{minutes.mean():.1f} min ({minutes.std():.1f} min)"
    # README.md holds the same table
    assert pages.committed_block((ROOT / "README.md").read_text(), "headline") == block


def test_the_speed_table_reads_each_benchmark_file():
    block = pages.committed_block((ROOT / "docs/results/speed.md").read_text(), "speed")
    for name in ("update_step.txt", "update_step_sac.txt", "gpu_update_step.txt"):
        text = (ROOT / "results/benchmarks" / name).read_text()
        compiled = re.search(r"^\s+update\s+[\d.]+ ms\s+([\d.]+) ms", text, flags=re.M).group(1)
        line = next(l for l in block.splitlines() if f"[{name}]" in l)
        assert _cells(line)[2] == f"{compiled} ms"
    # every file under results/benchmarks is one row's output or peer, and each is linked
    for path in (ROOT / "results/benchmarks").glob("*.txt"):
        assert f"[{path.name}](../../results/benchmarks/{path.name})" in block


def test_the_transfer_table_is_the_mean_over_the_policies_json():
    block = pages.committed_block((ROOT / "docs/results/transfer.md").read_text(), "fig9")
    files = sorted((ROOT / "results/transfer/sac_silp_plus_ext").glob("seed*/scenarios.json"))
    cells = [row for f in files for row in json.loads(f.read_text())["rows"]
             if row["scenario"] == "change" and row["noise"] == "paper"]
    line = next(l for l in block.splitlines() if "(`sac_silp_plus_ext`) | change | paper |" in l)
    assert _cells(line)[3] == _mean_std([c["success_rate"] for c in cells]) and _cells(line)[6] == "3"
    assert _cells(line)[7:] == ["0.86", "0.76"]  # the paper: 7 and 12 failures in 50 Change trials


def test_no_docs_page_is_over_400_lines():
    for page in (ROOT / "docs").rglob("*.md"):
        assert len(page.read_text().splitlines()) <= 400, page


def test_the_docs_links_resolve():
    for page in [*(ROOT / "docs").rglob("*.md"), ROOT / "results" / "README.md"]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.relative_to(ROOT)} links {target}"
