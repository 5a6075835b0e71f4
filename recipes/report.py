"""The paper's Table 1 from a sweep's results: the table beside the paper's, the learning curves, the ordering checks.

    python recipes/report.py                     # --results results/table1 --out docs/results.md
                                                 # --figure docs/table1_curves.png
    python recipes/report.py --block table1_40k  # the earlier 40k-frame runs (results/table1_40k)
    python recipes/report.py --block tasks       # SILP+ on both task models (results/tasks)
    python recipes/report.py --block speed       # the benchmarks' outputs (results/benchmarks)

Reads every ``<results>/<method>/seed*/summary.json`` (and ``history.json``,
``config.yaml``, ``sweep.json`` beside it: what ``recipes/sweep.py`` and the
recipes write) and writes, between the markers ``<!-- <block>:begin -->`` and
``<!-- <block>:end -->`` of ``--out`` (appended at its end when they are
missing; the rest of the file is left as it is):

* Table 1 in the paper's columns: success rate, training time (h:mm:ss) and
  planning time per rollout (s), each as mean (std) over the seeds, the
  paper's figures beside ours, the number of seeds, and a line for every row
  with fewer than 3 seeds; each row's settings, read from its runs' configs:
  the paper's, or which of our additions were on;
* the learning curves (``--figure``): the periodic evaluations' success rate
  against training episodes, mean ± std over the seeds, for every method with a history (the
  paper's "Success rates during training");
* the orderings the paper reports, each evaluated on our means as holds /
  does not hold / not run;
* the command, the results directory, the training budget
  (``collector.total_episodes`` / ``total_frames`` of the runs' ``config.yaml``) and the machine
  (from the runs' ``sweep.json``).

Std is over the seeds with ddof=0 (as ``compare_runs.py``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import os
import re
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_runs import mean_std  # noqa: E402

BEGIN, END = "<!-- table1:begin -->", "<!-- table1:end -->"  # the default block's markers (see markers())
TASKS_BEGIN, TASKS_END = "<!-- tasks:begin -->", "<!-- tasks:end -->"
SPEED_BEGIN, SPEED_END = "<!-- speed:begin -->", "<!-- speed:end -->"  # = markers("speed")
# the acceptance figures of the task-model redesign: the Panda's bar and the UR5e default before it
PANDA_TARGET, PANDA_FRAMES = 0.90, 300_000
UR5E_BEFORE, UR5E_TOLERANCE = 0.970, 0.01
PAPER_SEEDS = 3
# the speed issue's accuracy figure: the main job's default config, test success at the end of its own budget
DEFAULT_CONFIG_METHOD, DEFAULT_CONFIG_TARGET = "sac_silp_plus_ext", 0.98


def _hms(text: str) -> int:
    h, m, s = (int(x) for x in re.split(r"[.:]", text))
    return 3600 * h + 60 * m + s


# Table 1 of S. Luo and L. Schomaker, "Reinforcement Learning in Robotic Motion Planning by
# Combined Experience-based Planning and Self-Imitation Learning", Robotics and Autonomous
# Systems (the paper's source: /work/shared/paper/000_e96ab39deae2517e.txt, table "tab:bl"):
# mean (std) over 3 seeds of the success rate on 1000 test reaches, the training wall time of
# 1K epochs of 10 episodes (h:m:s; none for the PRM planners) and the planning time per rollout (s).
PAPER_TABLE1 = {
    "ddpg": {"label": "DDPG", "success": (0.763, 0.046), "train_s": (_hms("08:17:53"), _hms("00:23:26")), "plan_s": (0.110, 0.017)},
    "ddpg_her": {"label": "DDPG-HER", "success": (0.532, 0.257), "train_s": (_hms("11:15:01"), _hms("03:18:38")), "plan_s": (0.126, 0.024)},
    "ddpg_demon": {"label": "DDPG-Demon", "success": (0.707, 0.039), "train_s": (_hms("08:07:51"), _hms("00:13:21")), "plan_s": (0.107, 0.007)},
    "ddpg_silp_plus": {"label": "DDPG-SILP+ (paper's)", "success": (0.954, 0.021), "train_s": (_hms("07:35:11"), _hms("00:13:50")), "plan_s": (0.114, 0.009)},
    "sac": {"label": "SAC", "success": (0.864, 0.066), "train_s": (_hms("07:15:24"), _hms("00:48:00")), "plan_s": (0.116, 0.010)},
    "sac_her": {"label": "SAC-HER", "success": (0.902, 0.008), "train_s": (_hms("07:25:42"), _hms("01:04:36")), "plan_s": (0.113, 0.012)},
    "sac_demon": {"label": "SAC-Demon", "success": (0.925, 0.021), "train_s": (_hms("05:19:24"), _hms("00:06:45")), "plan_s": (0.121, 0.008)},
    "sac_silp": {"label": "SAC-SILP", "success": (0.944, 0.004), "train_s": (_hms("06:35:07"), _hms("00:09:25")), "plan_s": (0.118, 0.003)},
    "sac_silp_plus": {"label": "SAC-SILP+ (paper's)", "success": (0.973, 0.002), "train_s": (_hms("05:22:58"), _hms("00:04:26")), "plan_s": (0.130, 0.008)},
    "prm_0.1": {"label": "PRM-0.1", "success": (0.749, 0.038), "train_s": None, "plan_s": (0.134, 0.004)},
    "prm_1": {"label": "PRM-1", "success": (0.772, 0.067), "train_s": None, "plan_s": (1.028, 0.005)},
    "bc_sac_silp_plus": {"label": "BC-SAC-SILP+ (paper's)", "success": (0.967, 0.003), "train_s": (_hms("00:38:03"), _hms("00:02:25")), "plan_s": (0.137, 0.008)},
    "bc_prm": {"label": "BC-PRM", "success": (0.464, 0.015), "train_s": (_hms("01:32:56"), _hms("00:01:59")), "plan_s": (0.144, 0.010)},
}
# the extended rows (ours): the paper's figures beside them are those of its own method's row
for _name in ("ddpg_silp_plus", "sac_silp_plus", "bc_sac_silp_plus"):
    PAPER_TABLE1[_name + "_ext"] = {**PAPER_TABLE1[_name],
                                    "label": PAPER_TABLE1[_name]["label"].replace("(paper's)", "extended (ours)")}
ROW_ORDER = ["ddpg", "ddpg_her", "ddpg_demon", "ddpg_silp_plus", "ddpg_silp_plus_ext", "sac", "sac_her", "sac_demon",
             "sac_silp", "sac_silp_plus", "sac_silp_plus_ext", "prm_0.1", "prm_1", "bc_sac_silp_plus",
             "bc_sac_silp_plus_ext", "bc_prm"]
# a row run with the other variant's name cannot hide: the Settings column reads each run's config.yaml
PAPER_SETTINGS = Path(__file__).resolve().parent / "config" / "paper_settings.yaml"
SETTING_NAMES = {  # how the Settings column names each of our additions
    "planner.goal_node": "goal node", "planner.own_query": "own query", "planner.method": "exact search",
    "planner.insert_nodes": "equal InsertNodes", "network.goal_relative": "goal-relative input",
    "network.next_tcp_feature": "next-TCP critic input", "eval.actor_average_decay": "averaged actor",
    "optim.target_entropy": "entropy target", "exploration.mask_colliding_candidates": "masked GP candidates",
    "silp.filter": "no BC filter",
}
# values of a setting that differ from paper_settings.yaml's and are still the paper's: its SILP row
# (SAC-SILP) and Table 4 use SILP's Q-filter
PAPER_ALTERNATIVES = {"silp.filter": ("q",)}


def _flatten(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


@functools.cache
def _paper_settings() -> dict:
    from omegaconf import OmegaConf

    return _flatten(OmegaConf.to_container(OmegaConf.load(PAPER_SETTINGS)))


@functools.cache
def _schema_defaults() -> dict:
    import schema

    return _flatten(dataclasses.asdict(schema.TrainConfig()))


def _relevant(config: dict, key: str) -> bool:
    """Whether a setting acts in a run of this config (the planner's without demonstrations does not, ...)."""
    if key.startswith("planner."):
        return bool(_get(config, "silp.demos"))
    if key == "exploration.mask_colliding_candidates":
        return _get(config, "exploration.mode") == "gp"
    if key == "optim.target_entropy":
        return _get(config, "algorithm") == "sac"
    if key == "silp.filter":
        return bool(_get(config, "silp.bc"))
    return True


# switches added after runs were committed, each with the behaviour before it as its schema default: a run
# config that lacks one ran with that default. Any other paper setting a config lacks is an error, since the
# defaults of some (silp.filter) have changed since.
SWITCHES_ADDED_LATER = ("planner.own_query", "planner.insert_nodes", "exploration.mask_colliding_candidates")


def additions(config: dict | None) -> list[str] | None:
    """Our additions a training run's config turns on, named as in ``SETTING_NAMES``: ``[]`` is the paper's
    SILP+ as written; ``None``: not a training run (BC, PRM) or no config.

    A key of ``SWITCHES_ADDED_LATER`` that the config lacks takes the schema's default; any other
    setting that acts in the run must be in its config.
    """
    if config is None or _get(config, "algorithm") is None:
        return None
    given = _flatten(config)
    out = []
    for key, paper in _paper_settings().items():
        if not _relevant(config, key):
            continue
        if key in given:
            value = given[key]
        elif key in SWITCHES_ADDED_LATER:
            value = _schema_defaults()[key]
        else:
            raise KeyError(f"the run's config has no {key!r}, and its value cannot be inferred: the default has "
                           f"changed since some runs were made")
        if value != paper and value not in PAPER_ALTERNATIVES.get(key, ()):
            out.append(SETTING_NAMES.get(key, key))
    return out


def settings_text(runs: list[dict]) -> str:
    """The Settings cell of a row: ``paper's``, or ``ours: +a, +b`` (each of its runs' configs, joined)."""
    texts = []
    for r in runs:
        added = additions(r["config"])
        text = "—" if added is None else "paper's" if not added else "ours: " + ", ".join(f"+{a}" for a in added)
        if text not in texts:
            texts.append(text)
    return "; ".join(texts) or "—"


OTHER_LABELS = {  # rows outside the paper's Table 1 names
    "ur5e_sac_silp_plus_ext": "SAC-SILP+ extended (ours; the main job, 160k frames)",
    "prm_0.1_replanned": "PRM-0.1, replanned every control step",
}


def label(method: str) -> str:
    return PAPER_TABLE1.get(method, {}).get("label", OTHER_LABELS.get(method, method))


# ----------------------------------------------------------------- loading
def _seed_of(path: Path) -> int:
    match = re.fullmatch(r"seed(\d+)", path.name)
    return int(match.group(1)) if match else -1


def load_results(results: Path) -> dict[str, list[dict]]:
    """``{method: [run, ...]}``, a run being ``{"seed", "dir", "summary", "history", "config", "sweep"}``.

    Methods in the paper's order, then the others by name. Raises
    ``FileNotFoundError`` when no run has a summary.
    """
    runs: dict[str, list[dict]] = {}
    for summary_path in sorted(Path(results).glob("*/seed*/summary.json"), key=lambda p: (p.parents[1].name, _seed_of(p.parent))):
        run_dir = summary_path.parent
        history_path, config_path, sweep_path = (run_dir / n for n in ("history.json", "config.yaml", "sweep.json"))
        runs.setdefault(run_dir.parent.name, []).append({
            "seed": _seed_of(run_dir),
            "dir": run_dir,
            "summary": json.loads(summary_path.read_text()),
            "history": json.loads(history_path.read_text()).get("history", []) if history_path.exists() else [],
            "config": _load_yaml(config_path),
            "sweep": json.loads(sweep_path.read_text()) if sweep_path.exists() else None,
        })
    if not runs:
        raise FileNotFoundError(f"no <method>/seed*/summary.json under {results}: run recipes/sweep.py "
                                f"with results_dir={results} first")
    order = [m for m in ROW_ORDER if m in runs] + sorted(m for m in runs if m not in ROW_ORDER)
    return {m: runs[m] for m in order}


def _load_yaml(path: Path) -> dict | None:
    if not path.exists():
        return None
    from omegaconf import OmegaConf

    return OmegaConf.to_container(OmegaConf.load(path))


def _values(runs: list[dict], key: str) -> list[float]:
    return [r["summary"][key] for r in runs if isinstance(r["summary"].get(key), (int, float))
            and not isinstance(r["summary"].get(key), bool) and not math.isnan(r["summary"][key])]


def _mean(runs: list[dict], key: str) -> float | None:
    values = _values(runs, key)
    return float(np.mean(values)) if values else None


# ----------------------------------------------------------------- formatting
def hms(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


def _mean_std_with(values: list[float], fmt) -> str:
    if not values:
        return "—"
    arr = np.asarray(values, dtype=float)
    return fmt(arr.mean()) if len(arr) == 1 else f"{fmt(arr.mean())} ({fmt(arr.std())})"


def _seconds_fmt(values: list[float]):
    """Three significant digits of the mean (at least 3 decimals): 0.134, 0.00123."""
    top = max(abs(float(np.mean(values))), 1e-12)
    decimals = max(3, 2 - math.floor(math.log10(top)))
    return lambda x: f"{x:.{decimals}f}"


def _paper(method: str, key: str, fmt) -> str:
    paper = PAPER_TABLE1.get(method)
    if paper is None:
        return "—"
    if paper[key] is None:
        return "*"
    mean, std = paper[key]
    return f"{fmt(mean)} ({fmt(std)})"


def _rows(runs: dict[str, list[dict]], every_row: bool) -> list[str]:
    """The rows of a table: every method of the paper's table (``every_row``: those not run say so) or those run."""
    return [m for m in ROW_ORDER if every_row or m in runs] + [m for m in runs if m not in ROW_ORDER]


def table(runs: dict[str, list[dict]], every_row: bool = True) -> str:
    rows = [
        "| Method | Settings | Success rate | paper | Training time (h:mm:ss) | paper | Planning time per rollout (s) "
        "| paper | Seeds | Test collision rate | Training episodes (frames) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for method in _rows(runs, every_row):
        ours = runs.get(method, [])
        success = mean_std(_values(ours, "success_rate")) if ours else "not run"
        train = _values(ours, "train_wall_s")
        train = _mean_std_with(train, hms) if train else ("*" if ours else "—")
        plan = _values(ours, "rollout_time_per_episode_s")
        plan = _mean_std_with(plan, _seconds_fmt(plan)) if plan else "—"
        episodes, frames = _mean(ours, "episodes"), _mean(ours, "frames")
        budget = ("—" if not episodes else f"{episodes:,.0f}" + ("" if frames is None else f" ({frames:,.0f})"))  # PRM, BC: no RL episodes
        rows.append(
            f"| {label(method)} | {settings_text(ours)} | {success} | {_paper(method, 'success', lambda x: f'{x:.3f}')} "
            f"| {train} | {_paper(method, 'train_s', hms)} "
            f"| {plan} | {_paper(method, 'plan_s', lambda x: f'{x:.3f}')} "
            f"| {len(ours)} | {mean_std(_values(ours, 'test_collision_rate')) if ours else '—'} | {budget} |"
        )
    return "\n".join(rows)


def seed_notes(runs: dict[str, list[dict]], every_row: bool = True) -> list[str]:
    notes = []
    for method in _rows(runs, every_row):
        ours = runs.get(method, [])
        if not ours:
            notes.append(f"- {label(method)}: not run")
        elif len(ours) < PAPER_SEEDS:
            seeds = ", ".join(str(r["seed"]) for r in ours)
            notes.append(f"- {label(method)}: {len(ours)} seed{'s' if len(ours) > 1 else ''} ({seeds}); "
                         f"the paper used {PAPER_SEEDS}")
    return notes


# ------------------------------------------------------------ ordering checks
def _success(runs, method):
    return _mean(runs.get(method, []), "success_rate")


def _rollout(runs, method):
    return _mean(runs.get(method, []), "rollout_time_per_episode_s")


def _chain(runs, methods, strict: bool):
    """``a ≥ b ≥ c`` (or ``>``) on the mean success rates, with the numbers."""
    values = [_success(runs, m) for m in methods]
    holds = all((a > b) if strict else (a >= b) for a, b in zip(values, values[1:]))
    sign = " > " if strict else " ≥ "
    return holds, sign.join(f"{label(m)} {v:.3f}" for m, v in zip(methods, values))


def _beats_prm(runs, silp_rows):
    prm_success, prm_time = _success(runs, "prm_0.1"), _rollout(runs, "prm_0.1")
    holds, parts = True, []
    for method in silp_rows:
        success, time = _success(runs, method), _rollout(runs, method)
        if prm_time is None or time is None:
            return None, "no planning time per rollout recorded"
        holds &= success > prm_success and time <= prm_time
        parts.append(f"{label(method)} {success:.3f} in {time:.3g} s")
    return holds, f"{'; '.join(parts)}; PRM-0.1 {prm_success:.3f} in {prm_time:.3g} s"


def _checks_of(suffix: str) -> list:
    """The paper's orderings for its SILP+ rows (``suffix=""``) or for the extended ones (``"_ext"``)."""
    sac, ddpg, bc = f"sac_silp_plus{suffix}", f"ddpg_silp_plus{suffix}", f"bc_sac_silp_plus{suffix}"
    name = "" if not suffix else " extended"
    return [
        (f"SAC-SILP+{name} ≥ SAC-Demon ≥ SAC (success rate)", (sac, "sac_demon", "sac"),
         lambda runs: _chain(runs, (sac, "sac_demon", "sac"), strict=False)),
        (f"DDPG-SILP+{name} > DDPG (success rate)", (ddpg, "ddpg"),
         lambda runs: _chain(runs, (ddpg, "ddpg"), strict=True)),
        (f"the learned planners SAC-SILP+{name} and DDPG-SILP+{name} beat PRM-0.1 at a similar time per rollout "
         "(a higher success rate, in at most PRM-0.1's time per rollout)", (sac, ddpg, "prm_0.1"),
         lambda runs: _beats_prm(runs, (sac, ddpg))),
        (f"BC-SAC-SILP+{name} > BC-PRM (success rate)", (bc, "bc_prm"),
         lambda runs: _chain(runs, (bc, "bc_prm"), strict=True)),
    ]


CHECKS = _checks_of("")


def checks(runs: dict[str, list[dict]], every_row: bool = True) -> list[tuple[str, str, str]]:
    """``[(check, "holds" | "does not hold" | "not run", the numbers)]``, on the means over seeds: the paper's
    orderings for its SILP+ rows (unless none ran and not ``every_row``), and again for the extended rows
    where any of them ran."""
    out = []
    paper = every_row or any(m in runs for m in ("sac_silp_plus", "ddpg_silp_plus", "bc_sac_silp_plus"))
    extended = any(m.endswith("_ext") for m in runs)
    for text, needs, evaluate in (CHECKS if paper else []) + (_checks_of("_ext") if extended else []):
        missing = [label(m) for m in needs if _success(runs, m) is None]
        if missing:
            out.append((text, "not run", f"missing: {', '.join(missing)}"))
            continue
        holds, numbers = evaluate(runs)
        out.append((text, "not run" if holds is None else "holds" if holds else "does not hold", numbers))
    return out


# --------------------------------------------------------------- the curves
def mean_std_curve(histories: list[list[dict]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Success rate against training episodes, mean and std over the seeds at common points.

    Seeds evaluated at the same episodes are averaged there; otherwise each seed
    is interpolated (linearly, in episodes) onto the union of all the seeds'
    points inside the range every seed covers.

    Examples:
        >>> a = [{"episodes": 10, "success_rate": 0.2}, {"episodes": 20, "success_rate": 0.6}]
        >>> b = [{"episodes": 10, "success_rate": 0.4}, {"episodes": 20, "success_rate": 0.8}]
        >>> x, mean, std = mean_std_curve([a, b])
        >>> x.tolist(), mean.round(3).tolist(), std.round(3).tolist()
        ([10.0, 20.0], [0.3, 0.7], [0.1, 0.1])
    """
    series = []
    for history in histories:
        points = sorted((p["episodes"], p["success_rate"]) for p in history
                        if p.get("episodes") is not None and p.get("success_rate") is not None)
        if points:
            series.append(np.asarray(points, dtype=float).T)
    if not series:
        raise ValueError("no history point holds both episodes and success_rate")
    if all(len(x) == len(series[0][0]) and np.array_equal(x, series[0][0]) for x, _ in series):
        grid = series[0][0]
        ys = np.stack([y for _, y in series])
    else:
        lo, hi = max(x[0] for x, _ in series), min(x[-1] for x, _ in series)
        grid = np.unique(np.concatenate([x for x, _ in series]))
        grid = grid[(grid >= lo) & (grid <= hi)]
        ys = np.stack([np.interp(grid, x, y) for x, y in series])
    return grid, ys.mean(0), ys.std(0)


def _save_figure(fig, ax, path: Path, legend: str) -> None:
    """The report's figures all end alike: grid, legend, tight layout, saved at 120 dpi, closed."""
    import matplotlib.pyplot as plt

    ax.grid(alpha=0.3)
    ax.legend(loc=legend, fontsize="small")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_curves(runs: dict[str, list[dict]], path: Path) -> list[str]:
    """The learning-curve PNG; returns the methods it plots (those with a history), none: no PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {}
    for method, method_runs in runs.items():
        with contextlib.suppress(ValueError):  # no history (PRM), or none with episodes
            curves[method] = mean_std_curve([r["history"] for r in method_runs])
    if not curves:
        return []
    fig, ax = plt.subplots(figsize=(8, 5))
    for method, (x, mean, std) in curves.items():
        n = sum(any(p.get("episodes") is not None for p in r["history"]) for r in runs[method])
        (line,) = ax.plot(x, mean, marker="." if len(x) < 30 else None, label=f"{label(method)} ({n} seed{'s' if n > 1 else ''})")
        ax.fill_between(x, np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1), color=line.get_color(), alpha=0.2)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("success rate (periodic evaluations)")
    ax.set_ylim(0, 1.02)
    # the paper's x axis: epochs of 10 episodes
    ax.secondary_xaxis("top", functions=(lambda e: e / 10, lambda p: p * 10)).set_xlabel("paper's epochs (10 episodes)")
    ax.set_title("Success rates during training: mean ± std over seeds")
    _save_figure(fig, ax, path, "lower right")
    return list(curves)


# ------------------------------------------------------- budget and machine
def _get(tree: dict | None, dotted: str):
    for key in dotted.split("."):
        if not isinstance(tree, dict) or key not in tree:
            return None
        tree = tree[key]
    return tree


# the budget of a run, as its config.yaml states it (each key where a recipe's config has it)
BUDGET_KEYS = {
    "collector.total_episodes": "training episodes (the RL methods; the run stops after the batch that completes them)",
    "collector.total_frames": "training env steps (the RL methods; a cap where total_episodes is set)",
    "n_demos": "demonstration episodes attempted (BC)",
    "optim.n_updates": "gradient updates (BC)",
    "budget_s": "planning time per task, s (PRM)",
    "eval.n_tasks": "test tasks of the final evaluation",
}


def config_values(runs: dict[str, list[dict]], key: str) -> str | None:
    """``` `40000` (ddpg, sac); `160000` (sac_silp_plus)```: a config key's values over the runs that have it."""
    groups: dict[str, list[str]] = {}
    for method, method_runs in runs.items():
        for value in dict.fromkeys(_get(r["config"], key) for r in method_runs):
            if value is not None:
                groups.setdefault(str(value), []).append(method)
    return "; ".join(f"`{v}` ({', '.join(ms)})" for v, ms in groups.items()) or None


def machine_lines(runs: dict[str, list[dict]]) -> list[str]:
    groups: dict[str, list[str]] = {}
    for method, method_runs in runs.items():
        for r in method_runs:
            device, threads = _get(r["config"], "device"), _get(r["config"], "threads")
            own = f"device `{device}`, `threads={threads}`" if device is not None else "no device in the config"
            sweep = r["sweep"]
            if sweep is None:
                text = f"not recorded (the run was not started by recipes/sweep.py); {own}"
            else:
                m, per_run, cluster = sweep.get("machine", {}), sweep.get("resources_per_run", {}), sweep.get("ray_cluster", {})
                gpus = f", GPU {', '.join(m['gpus'])}" if m.get("gpus") else ""
                text = (f"{m.get('cpu')} ({m.get('cpu_count')} CPUs{gpus}), torch {m.get('torch')} with "
                        f"{m.get('torch_threads')} thread(s); {own}; Ray: {per_run.get('num_cpus')} CPU / "
                        f"{per_run.get('num_gpus')} GPU per run, {cluster.get('CPU')} CPUs / {cluster.get('GPU')} GPUs "
                        f"in the cluster (runs in parallel share the machine)")
            label_ = f"{method}/seed{r['seed']}"
            if label_ not in groups.setdefault(text, []):
                groups[text].append(label_)
    return [f"- {text}: {_compact(names)}" for text, names in groups.items()]


def _compact(names: list[str]) -> str:
    seeds: dict[str, list[str]] = {}
    for name in names:
        method, seed = name.split("/seed")
        seeds.setdefault(method, []).append(seed)
    return ", ".join(f"{m} (seeds {', '.join(s)})" if len(s) > 1 else f"{m} (seed {s[0]})" for m, s in seeds.items())


def sweep_commands(runs: dict[str, list[dict]]) -> list[str]:
    commands = {r["sweep"].get("sweep_command") for rs in runs.values() for r in rs if r["sweep"]}
    return sorted(c for c in commands if c)


def provenance_lines(runs: dict[str, list[dict]], budget_heading: str) -> list[str]:
    """The budget, machine and sweep-command lines every block ends with."""
    budget = [(key, text, config_values(runs, key)) for key, text in BUDGET_KEYS.items()]
    lines = [budget_heading, ""]
    lines += [f"- `{key}`, {text}: {values}" for key, text, values in budget if values is not None]
    lines += ["", "Machine (each run's sweep.json and config.yaml):", "", *machine_lines(runs), ""]
    commands = sweep_commands(runs)
    if commands:
        lines += ["Sweep command(s):", "", *[f"- `{c}`" for c in commands], ""]
    return lines


def closed_block(lines: list[str], runs: dict[str, list[dict]], end: str) -> str:
    """A block's text: ``lines``, then its runs' :func:`provenance_lines` and its ``end`` marker."""
    return "\n".join([*lines, *provenance_lines(runs, "Budget (the runs' config.yaml):"), end])


# ------------------------------------------------------------------ the block
TABLE1_HEADINGS = {
    "table1": "### Table 1 at the paper's budget: success rate, training time, planning time (generated)",
    "table1_40k": "### Table 1 at 40k frames (a record of the earlier, shorter runs; generated)",
}


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def block(runs: dict[str, list[dict]], results: Path, figure: Path | None, out: Path, command: str,
          plotted: list[str], name: str = "table1") -> str:
    begin, end = markers(name)
    every_row = name == "table1"  # the table at the paper's budget lists what is still to run
    lines = [
        begin,
        TABLE1_HEADINGS.get(name, f"### {name} (generated)"),
        "",
        f"Generated by `{command}` from the runs in `{results}` (every number below is read from their "
        "`summary.json`, `history.json`, `config.yaml` and `sweep.json`, except the paper's columns: Table 1 "
        "of Luo & Schomaker, three seeds each, 1000 test reaches, 1K epochs of 10 episodes).",
        "",
        table(runs, every_row),
        "",
        "Mean (std) over the seeds (std with ddof=0; one seed: its value). Training time is the run's "
        "`train_wall_s` (* : the PRM planners do not train); planning time per rollout is "
        "`rollout_time_per_episode_s`, the wall time of the batched evaluation rollout divided by its tasks. "
        "Settings, read from each run's `config.yaml`: *paper's* is the paper's SILP+ as written "
        "(`recipes/config/paper_settings.yaml`); *ours* lists each of our additions the run had on "
        "(`docs/paper_vs_ours.md`). The paper's figures beside an extended row are those of its own method.",
        "",
    ]
    gaps = [f"{label(m + '_ext')} − {label(m)}: {_success(runs, m + '_ext') - _success(runs, m):+.3f} success rate "
            f"({len(runs[m + '_ext'])} and {len(runs[m])} seeds)"
            for m in ("sac_silp_plus", "ddpg_silp_plus", "bc_sac_silp_plus")
            if _success(runs, m) is not None and _success(runs, m + "_ext") is not None]
    if gaps:
        lines += ["Ours against the paper's SILP+ (means over seeds; section 2's ablations say which addition "
                  "accounts for it):", "", *[f"- {g}" for g in gaps], ""]
    notes = seed_notes(runs, every_row)
    if notes:
        lines += [f"Rows with fewer than {PAPER_SEEDS} seeds:", "", *notes, ""]
    lines += ["Orderings reported by the paper, on our means:", ""]
    lines += [f"- {status}: {text} ({numbers})" for text, status, numbers in checks(runs, every_row)]
    lines += ["", *provenance_lines(runs, "Budget (the runs' config.yaml; the paper: 1K epochs of 10 episodes):")]
    if figure is not None and plotted:
        rel = os.path.relpath(figure, out.parent)
        lines += [f"![Success rates during training]({rel})", "",
                  f"Success rate of the periodic evaluations (the tasks of each run's `eval.seed`) against training episodes, mean ± std over seeds ({', '.join(label(m) for m in plotted)}).", ""]
    elif figure is not None:
        lines += ["No run has a training history: no learning-curve figure.", ""]
    lines.append(end)
    return "\n".join(lines)


# ------------------------------------------- Tables 2, 3, 4 and A.1 of the paper
# Each row: (method in the results dir, label, the paper's figures: success (mean, std), training time (s),
# collisions during training), from the paper's tables (the LaTeX source: tab:ce-type, tab:gp, tab:rfilters,
# tab:prm-dis). A std the paper does not give is None; so is a figure it does not give.
PAPER_TABLES = {
    "table2": {
        "title": "Table 2: collision handling (type 0: the episode ends; type 1: the arm stays, the episode goes on; "
                 "type 2: the arm stays, a recovery action follows)",
        "rows": [
            ("sac_collision0", "SAC, type-0", (0.819, 0.079), (_hms("06:18:07"), _hms("00:40:44")), None),
            ("sac_collision1", "SAC, type-1", (0.423, 0.113), (_hms("10:43:53"), _hms("00:22:14")), None),
            ("sac", "SAC, type-2", (0.865, 0.021), (_hms("07:12:06"), _hms("00:05:08")), None),
            ("sac_silp_plus_collision0", "SAC-SILP+ (paper's), type-0", (0.952, 0.027),
             (_hms("04:59:39"), _hms("00:06:08")), None),
            ("sac_silp_plus_collision1", "SAC-SILP+ (paper's), type-1", (0.942, 0.015),
             (_hms("06:45:16"), _hms("00:32:18")), None),
            ("sac_silp_plus", "SAC-SILP+ (paper's), type-2", (0.971, 0.010), (_hms("06:10:02"), _hms("00:14:13")), None),
        ],
        # the paper: type-2 best for both, type-1 worst ("we selected type-2"; Table 2)
        "orderings": [("SAC: type-2 ≥ type-0 ≥ type-1", ("sac", "sac_collision0", "sac_collision1")),
                      ("SAC-SILP+: type-2 ≥ type-0 ≥ type-1",
                       ("sac_silp_plus", "sac_silp_plus_collision0", "sac_silp_plus_collision1"))],
    },
    "table3": {
        "title": "Table 3: GP-guided recovery against random recovery (the paper's SAC-SILP+)",
        "rows": [
            ("sac_silp_plus_random_recovery", "SAC-SILP+ (paper's), random recovery", (0.973, None),
             (_hms("06:28:50"), None), 30844),
            ("sac_silp_plus", "SAC-SILP+ (paper's), GP recovery", (0.973, None), (_hms("05:22:58"), None), 6153),
        ],
        "orderings": [("GP recovery: fewer collisions during training than random recovery",
                       ("sac_silp_plus_random_recovery", "sac_silp_plus"), "collisions_during_training"),
                      ("GP recovery: a success rate at least that of random recovery",
                       ("sac_silp_plus", "sac_silp_plus_random_recovery"))],
    },
    "table4": {
        "title": "Table 4: the BC filter (reward filter, SILP+; Q-filter, SILP's; none)",
        "rows": [
            ("sac_silp_plus", "SAC-SILP+ (paper's), reward filter", (0.973, None), (_hms("05:22:58"), None), None),
            ("sac_silp_plus_q_filter", "SAC-SILP+ (paper's), Q-filter", (0.966, None), (_hms("06:07:47"), None), None),
            ("sac_silp_plus_no_filter", "SAC-SILP+ (paper's), no filter", None, None, None),
        ],
        "orderings": [("reward filter ≥ Q-filter (success rate)", ("sac_silp_plus", "sac_silp_plus_q_filter"))],
    },
    "tableA1": {
        "title": "Table A.1: SILP+'s success rate against the roadmap distance d",
        "rows": [
            ("sac_silp_plus_d0.10", "SAC-SILP+ (paper's), d = 0.10", (0.961, None), None, None),
            ("sac_silp_plus", "SAC-SILP+ (paper's), d = 0.15", (0.965, None), None, None),
            ("sac_silp_plus_d0.20", "SAC-SILP+ (paper's), d = 0.20", (0.933, None), None, None),
            ("sac_silp_plus_d0.30", "SAC-SILP+ (paper's), d = 0.30", (0.782, None), None, None),
            ("sac_silp_plus_d0.40", "SAC-SILP+ (paper's), d = 0.40", (0.663, None), None, None),
        ],
        # the paper: best at 0.15, falling from 0.15 on ("we choose the final distance of 0.15m")
        "orderings": [("d = 0.15 ≥ 0.20 ≥ 0.30 ≥ 0.40", ("sac_silp_plus", "sac_silp_plus_d0.20", "sac_silp_plus_d0.30",
                                                     "sac_silp_plus_d0.40")),
                      ("d = 0.15 ≥ 0.10", ("sac_silp_plus", "sac_silp_plus_d0.10"))],
    },
}
ABLATIONS = {  # sweep_ablations.yaml: ours with one setting at the paper's value (or lambda2 at 1)
    "sac_silp_plus_ext_no_goal_node": "planner.goal_node=false",
    "sac_silp_plus_ext_no_own_query": "planner.own_query=false",
    "sac_silp_plus_ext_greedy_search": "planner.method=greedy",
    "sac_silp_plus_ext_halving_insert_nodes": "planner.insert_nodes=halving",
    "sac_silp_plus_ext_no_goal_relative": "network.goal_relative=false",
    "sac_silp_plus_ext_no_next_tcp": "network.next_tcp_feature=false",
    "sac_silp_plus_ext_no_averaged_actor": "eval.actor_average_decay=null",
    "sac_silp_plus_ext_auto_entropy": "optim.target_entropy=auto",
    "sac_silp_plus_ext_unmasked_candidates": "exploration.mask_colliding_candidates=false",
    "sac_silp_plus_ext_lambda2_1": "silp.lambda2=1",
}


def _cell(values: list[float], fmt) -> str:
    return _mean_std_with(values, fmt) if values else "—"


def _paper_cell(figure, fmt) -> str:
    if figure is None:
        return "—"
    if isinstance(figure, tuple):
        mean, std = figure
        return fmt(mean) if std is None else f"{fmt(mean)} ({fmt(std)})"
    return fmt(figure)


def paper_table_rows(runs: dict[str, list[dict]], name: str) -> list[str]:
    spec = PAPER_TABLES[name]
    rows = ["| Method | Settings | Success rate | paper | Test collision rate | Training time (h:mm:ss) | paper "
            "| Collisions during training | paper | Seeds | Training episodes (frames) |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for method, text, success, train_s, collisions in spec["rows"]:
        ours = runs.get(method, [])
        episodes, frames = _mean(ours, "episodes"), _mean(ours, "frames")
        budget = "—" if episodes is None else f"{episodes:,.0f} ({frames:,.0f})"
        rows.append(
            f"| {text} (`{method}`) | {settings_text(ours)} | {mean_std(_values(ours, 'success_rate')) if ours else 'not run'} "
            f"| {_paper_cell(success, lambda x: f'{x:.3f}')} "
            f"| {_cell(_values(ours, 'test_collision_rate'), lambda x: f'{x:.3f}')} "
            f"| {_cell(_values(ours, 'train_wall_s'), hms)} "
            f"| {_paper_cell(train_s, hms)} | {_cell(_values(ours, 'collisions_during_training'), lambda x: f'{x:,.0f}')} "
            f"| {_paper_cell(collisions, lambda x: f'{x:,}')} | {len(ours)} | {budget} |")
    return rows


def paper_table_checks(runs: dict[str, list[dict]], name: str) -> list[str]:
    out = []
    for ordering in PAPER_TABLES[name]["orderings"]:
        text, methods = ordering[0], ordering[1]
        key = ordering[2] if len(ordering) > 2 else "success_rate"
        values = [_mean(runs.get(m, []), key) for m in methods]
        if any(v is None for v in values):
            missing = [m for m, v in zip(methods, values) if v is None]
            out.append(f"- not run: {text} (missing: {', '.join(missing)})")
            continue
        holds = all(a >= b for a, b in zip(values, values[1:]))
        fmt = (lambda v: f"{v:,.0f}") if key != "success_rate" else (lambda v: f"{v:.3f}")
        out.append(f"- {'holds' if holds else 'does not hold'}: {text} "
                   f"({' ≥ '.join(f'{m} {fmt(v)}' for m, v in zip(methods, values))})")
    return out


def filter_share_figure(runs: dict[str, list[dict]], path: Path) -> list[str]:
    """Fig. 7 as we measure it: the share of demo actions the BC filter keeps, against training episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plotted = []
    fig, ax = plt.subplots(figsize=(7, 4))
    for method, text, *_ in PAPER_TABLES["table4"]["rows"]:
        histories = [[{"episodes": p["episodes"], "success_rate": p["bc_filter_fraction"]} for p in r["history"]
                      if p.get("bc_filter_fraction") is not None] for r in runs.get(method, [])]
        histories = [h for h in histories if h]
        if not histories:
            continue
        x, mean, std = mean_std_curve(histories)
        (line,) = ax.plot(x, mean, label=f"{text} ({len(histories)} seed{'s' if len(histories) > 1 else ''})")
        ax.fill_between(x, np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1), color=line.get_color(), alpha=0.2)
        plotted.append(method)
    if not plotted:
        plt.close(fig)
        return plotted
    ax.set_xlabel("training episodes")
    ax.set_ylabel("share of demo actions the filter keeps")
    ax.set_ylim(0, 1.02)
    _save_figure(fig, ax, path, "upper right")
    return plotted


def paper_table_block(runs: dict[str, list[dict]], name: str, results: Path, figure: Path | None, out: Path,
                      command: str, plot_to: Path | None = None) -> str:
    begin, end = markers(name)
    spec = PAPER_TABLES[name]
    mine = {m: runs[m] for m, *_ in spec["rows"] if m in runs}
    lines = [begin, f"### {spec['title']} (generated)", "",
             f"Generated by `{command}` from the runs in `{results}` (their `summary.json`, `history.json`, "
             "`config.yaml`, `sweep.json`); the paper's columns are its own table's figures. Success rate: the 1000 "
             "test tasks, mean (std) over seeds (ddof=0); test collision rate: the share of them that end in a collision "
             "(the rest of the failures run out of steps; the paper gives no such figure). Collisions during training: "
             "the run's count of colliding steps. A row shared with another table is the same runs.", "",
             *paper_table_rows(runs, name), "", "Orderings reported by the paper, on our means:", "",
             *paper_table_checks(runs, name), ""]
    if name == "table4" and figure is not None:
        plotted = filter_share_figure(runs, plot_to or figure)
        if plotted:
            lines += [f"![The share of demo actions the BC filter keeps]({os.path.relpath(figure, out.parent)})", "",
                      "Fig. 7 as we measure it: the share of the demo actions of each batch that the filter keeps "
                      "(`bc_filter_fraction` of the history points, mean over the updates since the previous point), "
                      "mean ± std over seeds. The paper plots the number of demo actions better than the policy's.", ""]
    if mine:
        lines += provenance_lines(mine, "Budget (the runs' config.yaml; the paper: 1K epochs of 10 episodes):")
    lines.append(end)
    return "\n".join(lines)


def _seed0(runs: dict[str, list[dict]], method: str) -> dict | None:
    """The seed-0 run of ``method`` (the ablations' one seed), None if it has not run."""
    return next((r for r in runs.get(method, []) if r["seed"] == 0), None)


def _validation(run: dict | None) -> float | None:
    """A run's validation success rate; None for a run that has not run or did not record it."""
    return run["summary"].get("validation_success_rate") if run else None


def _ablation_noise_lines(runs: dict[str, list[dict]], base: dict | None) -> list[str]:
    """Which ablations move validation success by more than twice ours' seed-to-seed spread."""
    ours = _values(runs.get("sac_silp_plus_ext", []), "validation_success_rate")
    if len(ours) < 2 or base is None:
        return []
    spread = float(np.std(ours))
    reference = base["summary"]["validation_success_rate"]
    beyond, within = [], []
    for method in ABLATIONS:
        value = _validation(_seed0(runs, method))
        if value is None:
            continue
        (beyond if abs(value - reference) > 2 * spread else within).append(f"`{method}` ({value - reference:+.3f})")
    if not beyond and not within:
        return []
    return [f"Ours over its {len(ours)} seeds: validation success {np.mean(ours):.3f}, std {spread:.3f}. "
            f"Beyond twice that std from ours' seed 0: {', '.join(beyond) or 'none'}. "
            f"Within it: {', '.join(within) or 'none'}.", ""]


def ablations_block(runs: dict[str, list[dict]], results: Path, command: str) -> str:
    """Ours (sac_silp_plus_ext, seed 0) against itself with one setting set back, on the validation tasks."""
    begin, end = markers("ablations")
    base = _seed0(runs, "sac_silp_plus_ext")
    rows = ["| Run | Changed setting | Validation success | vs ours | Test success | Training episodes (frames) "
            "| Training time |", "|---|---|---:|---:|---:|---:|---:|"]
    for method, change in [("sac_silp_plus_ext", "— (ours, all additions)")] + list(ABLATIONS.items()):
        run = _seed0(runs, method)
        if run is None:
            rows.append(f"| `{method}` | `{change}` | not run | | | | |")
            continue
        v, b, summ = _validation(run), _validation(base), run["summary"]
        delta = f"{v - b:+.3f}" if v is not None and b is not None and method != "sac_silp_plus_ext" else ""
        rows.append(f"| `{method}` | `{change}` | {'—' if v is None else f'{v:.3f}'} | {delta} "
                    f"| {summ['success_rate']:.3f} | {summ['episodes']:,} ({summ['frames']:,}) "
                    f"| {hms(summ['train_wall_s'])} |")
    mine = {m: rs for m, rs in runs.items() if m in ABLATIONS or m == "sac_silp_plus_ext"}
    lines = [begin, "### Which addition matters: ours minus one at a time, seed 0 (generated)", "",
             f"Generated by `{command}` from the seed-0 runs in `{results}`. Validation success: the last periodic "
             "evaluation, on the validation tasks (`eval.seed`), the figure the defaults are judged by; vs ours: "
             "its difference from ours (all additions, seed 0). Test success: the 1000 test tasks, read once at "
             "the end. One seed each: a difference within a few hundredths is within seed noise (compare the "
             "spread of ours over its 3 seeds in Table 1).", "", *rows, ""]
    lines += _ablation_noise_lines(runs, base)
    if mine:
        lines += provenance_lines(mine, "Budget (the runs' config.yaml):")
    lines.append(end)
    return "\n".join(lines)


# ------------------------------------------------ Table 5 in simulation: the MuJoCo twin
# The paper's SAC-SILP+ in its three real-robot scenarios, 50 trials each (sec. 4.5, Fig. 8's text): Free, "three
# and four failure trials in simulation and the real test"; Block, "four and seven failure cases"; Change, "five
# failures were found in both", plus "two failures in simulation that were not the case in the real test" and
# "seven failures in the physical experiments that did not happen in simulations".
PAPER_TABLE5 = {"free": (1 - 3 / 50, 1 - 4 / 50), "block": (1 - 4 / 50, 1 - 7 / 50),
                "change": (1 - 7 / 50, 1 - 12 / 50)}
TRANSFER_SCENARIOS, TRANSFER_NOISES = ("free", "block", "change"), ("none", "paper", "double")


def load_transfer(results: Path) -> dict[str, list[dict]]:
    """``{method: [result, ...]}`` from ``<results>/*.json`` (what ``recipes/transfer.py`` writes), one per run."""
    out: dict[str, list[dict]] = {}
    for path in sorted(Path(results).glob("*.json")):
        result = json.loads(path.read_text())
        result["file"] = path.name
        out.setdefault(result["method"], []).append(result)
    if not out:
        raise FileNotFoundError(f"no transfer results (*.json) under {results}: run recipes/transfer.py first")
    return {m: sorted(rs, key=lambda r: r["seed"]) for m, rs in sorted(out.items())}


def table5_block(results_by_method: dict[str, list[dict]], results: Path, command: str) -> str:
    begin, end = markers("table5")
    rows = ["| Method | Scenario | Noise | Success | Collisions | Time to success (s) | Seeds | paper, simulation "
            "| paper, real UR5e |", "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for method, results_ in results_by_method.items():
        for scenario in TRANSFER_SCENARIOS:
            for noise in TRANSFER_NOISES:
                cells = [row for r in results_ for row in r["rows"] if row["scenario"] == scenario and row["noise"] == noise]
                if not cells:
                    continue
                times = [c["time_to_success_s"] for c in cells if c["time_to_success_s"] is not None]
                sim, real = PAPER_TABLE5[scenario] if "sac_silp_plus" in method else ("—", "—")
                fmt = (lambda x: f"{x:.2f}") if sim != "—" else str
                rows.append(f"| {label(method)} | {scenario} | {noise} | {mean_std([c['success_rate'] for c in cells])} "
                            f"| {mean_std([c['collision_rate'] for c in cells])} | {_cell(times, lambda x: f'{x:.2f}')} "
                            f"| {len(cells)} | {fmt(sim)} | {fmt(real)} |")
    first = next(iter(results_by_method.values()))[0]
    runs = _transfer_runs(results_by_method, TRANSFER_SCENARIOS)
    levels = "; ".join(f"{name}: box noise {p['obstacle_noise']} m, latency {p['latency_steps']} step(s), "
                       f"encoders {p['joint_noise']} rad" for name, p in _perceptions(results_by_method).items())
    lines = [begin, "### Table 5 in simulation: the paper's scenarios on the MuJoCo twin (generated)", "",
             f"Generated by `{command}` from `{results}/*.json` (each written by `python recipes/transfer.py "
             "checkpoint=RUN_DIR`). Success and collisions are MuJoCo's: the TCP within the task's 0.05 m of the "
             "goal after a control step, and any contact of the arm with the table, the box or itself (a "
             f"collision ends the task as a failure). {first['rows'][0]['n_tasks']} seeded tasks per scenario, "
             f"control period {first['control_dt']} s, at most {first['max_steps']} steps; mean (std) over the "
             "runs' seeds. Time to success: simulated seconds, over the tasks that succeed.", "",
             *rows, "", f"Noise levels: {levels}.", "",
             "The paper's columns are its SAC-SILP+ in 50 trials per scenario (sec. 4.5): in Gazebo and on the "
             "real UR5e, a pick-and-place with an ArUco-marker perception, not our reach tasks.", "",
             f"Runs: {runs}.", "", end]
    return "\n".join(lines)


PICK_PLACE_STAGES = ("pre_grasp", "grasp", "carry", "place")


def pick_place_block(results_by_method: dict[str, list[dict]], results: Path, command: str) -> str:
    """The pick-and-place pipeline (Fig. 9) per method and noise level: the share of trials through each stage."""
    begin, end = markers("pick_place")
    rows = ["| Method | Noise | Pre-grasp reached | Grasped | Carried to the basket | Placed (success) | Collisions "
            "| Seeds |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    n_tasks = None
    for method, results_ in results_by_method.items():
        for noise in TRANSFER_NOISES:
            cells = [row for r in results_ for row in r["rows"] if row["scenario"] == "pick_place" and row["noise"] == noise]
            if not cells:
                continue
            n_tasks = cells[0]["n_tasks"]
            stages = " | ".join(mean_std([c[f"{s}_rate"] for c in cells]) for s in PICK_PLACE_STAGES)
            rows.append(f"| {label(method)} | {noise} | {stages} | {mean_std([c['collision_rate'] for c in cells])} "
                        f"| {len(cells)} |")
    if n_tasks is None:
        body = ["No pick-and-place run yet (`python recipes/transfer.py checkpoint=RUN_DIR scenario=pick_place`)."]
    else:
        body = [f"{n_tasks} seeded trials per run (`torchrl_silp.sim.pick_place`): perceive the cube, the basket "
                "and the box (with the noise level's box noise); reach 20 cm above the cube with the policy; a "
                "scripted vertical descent until the fingertips are just above the cube; the grasp, a MuJoCo weld "
                "switched on if the fingertips ended within 2 cm of their grasp pose (no finger model); the "
                "scripted ascent; carry with the policy to 20 cm above the basket; release. Placed: the cube rests "
                "inside the basket 1 s later. Each stage's share counts the trials through it and every stage "
                "before; a collision (MuJoCo contact of the arm, or of the carried cube with the box) ends a "
                "trial. The paper ran its pipeline 50 times per scenario on the real robot, with the figures of "
                "the Table 5 block.", "", *rows]
    lines = [begin, "### Pick-and-place in simulation (Fig. 9's pipeline; generated)", "",
             f"Generated by `{command}` from `{results}/*.json`.", "", *body, "", end]
    return "\n".join(lines)


def _transfer_runs(results_by_method: dict[str, list[dict]], scenarios) -> str:
    """Each method's policies behind the rows of ``scenarios``, once each (a run's scenario file and its
    pick-and-place file share the checkpoint), named as the table names them."""
    parts = []
    for method, results_ in results_by_method.items():
        named = []
        for r in results_:
            if not any(row["scenario"] in scenarios for row in r["rows"]):
                continue
            name = (f"seed {r['seed']} ({r['trained_episodes']:,} episodes, `{r['checkpoint']}`)" if r["checkpoint"]
                    else f"seed {r['seed']} (a planner, no training)")
            if name not in named:
                named.append(name)
        if named:
            parts.append(f"{label(method)}: {', '.join(named)}")
    return "; ".join(parts)


def _perceptions(results_by_method: dict[str, list[dict]]) -> dict[str, dict]:
    out = {}
    for rs in results_by_method.values():
        for r in rs:
            for row in r["rows"]:
                out.setdefault(row["noise"], row["perception"])
    return {k: out[k] for k in TRANSFER_NOISES if k in out}


# ------------------------------------------------ appendix B: the learned collision model
PAPER_COLLISION_NET = {"n": 485_000, "accuracy": 0.991, "recall": 0.984, "precision": 0.989, "specificity": 0.995}


def load_collision_nets(results: Path) -> list[dict]:
    found = [json.loads(p.read_text()) for p in sorted(Path(results).glob("*.json"))]
    if not found:
        raise FileNotFoundError(f"no collision-model results (*.json) under {results}: run recipes/collision_net.py")
    return found


def roc_figure(nets: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    for net in nets:
        roc = net["roc"]
        ax.plot(roc["fpr"], roc["tpr"], label=f"labels: {net['labeller']} (AUC {roc['auc']:.4f})")
    ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--")
    ax.set_xlabel("false positive rate (1 - specificity)")
    ax.set_ylabel("true positive rate (recall)")
    ax.set_title("ROC of the collision model on its test split")
    _save_figure(fig, ax, path, "lower right")


def collision_net_block(nets: list[dict], results: Path, figure: Path | None, out: Path, command: str,
                        runs: dict[str, list[dict]] | None = None, plot_to: Path | None = None) -> str:
    begin, end = markers("collision_net")
    p = PAPER_COLLISION_NET
    rows = ["| Labels | Configurations | Collision share | Accuracy | Recall | Precision | Specificity | ROC AUC |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
            f"| the paper's (appendix B) | {p['n']:,} | — | {p['accuracy']:.3f} | {p['recall']:.3f} "
            f"| {p['precision']:.3f} | {p['specificity']:.3f} | — |"]
    for net in nets:
        m = net["metrics"]
        rows.append(f"| {net['labeller']} | {net['n']:,} | {net['collision_share']:.3f} | {m['accuracy']:.3f} "
                    f"| {m['recall']:.3f} | {m['precision']:.3f} | {m['specificity']:.3f} | {net['roc']['auc']:.4f} |")
    lines = [begin, "### Appendix B: the learned collision model (generated)", "",
             f"Generated by `{command}` from `{results}/*.json`, each written by its command: "
             + "; ".join(f"`{n['command']}`" for n in nets) + ". CollisionNet (512-256-64, the paper's sizes) "
             "on 90 % of the configurations, the metrics on the other 10 % at a threshold of 0.5; collision is "
             "the positive class. *exact*: the task model's checker (its sphere cover, every reason: box, "
             "table, self, workspace); *mujoco*: the twin's contacts on the URDF's primitives (no workspace "
             "bound). Configurations: uniform in the task's joint box, each in a scene of the task distribution.",
             "", *rows, ""]
    if figure is not None:
        roc_figure(nets, plot_to or figure)
        lines += [f"![ROC of the collision model]({os.path.relpath(figure, out.parent)})", ""]
    runs = runs or {}
    lines += ["SILP+ with the learned edge check (`planner.collision_net`), beside the exact one, at the paper's "
              f"budget (`{RESULTS_OF['table1']}`): test success, mean (std) over seeds.", "",
              "| Method | Edge check | Success rate | Seeds |", "|---|---|---:|---:|"]
    for method, check in (("sac_silp_plus", "exact (the task model's motion check)"),
                          ("sac_silp_plus_learned_edges", "learned (`results/collision_net/exact.pt`)")):
        ours = runs.get(method, [])
        lines.append(f"| SAC-SILP+ (paper's) | {check} | {mean_std(_values(ours, 'success_rate')) if ours else 'not run'} "
                     f"| {len(ours)} |")
    lines += ["", end]
    return "\n".join(lines)


def tasks_table(runs: dict[str, list[dict]]) -> str:
    rows = ["| Task | Method | Success rate | Seeds | Frames | Training time | Time to 0.95 | Collisions in training "
            "| of which swept |", "|---|---|---|---|---|---|---|---|---|"]
    for method, method_runs in runs.items():
        task = _get(method_runs[0]["config"], "env.name") or "?"
        success = mean_std(_values(method_runs, "success_rate"))
        frames = ", ".join(sorted({str(r["summary"].get("frames")) for r in method_runs}))
        reached = _values(method_runs, "time_to_095_s")
        to_095 = (f"{hms(float(np.mean(reached)))} ({len(reached)}/{len(method_runs)} reached)" if reached
                  else f"(0/{len(method_runs)} reached)")
        collisions = _mean(method_runs, "collisions_during_training")
        swept = _mean(method_runs, "swept_collisions_during_training")
        rows.append(
            f"| {task} | {method} | {success} | {len(method_runs)} | {frames} | "
            f"{hms(_mean(method_runs, 'train_wall_s') or 0.0)} | {to_095} | "
            f"{collisions:.0f} | {swept:.0f} ({swept / max(collisions, 1):.1%}) |"
        )
    return "\n".join(rows)


def tasks_checks(runs: dict[str, list[dict]]) -> list[str]:
    out = []
    panda = runs.get("panda_sac_silp_plus_ext", [])
    if panda:
        values = _values(panda, "success_rate")
        frames = max(r["summary"].get("frames", 0) for r in panda)
        holds = len(values) >= PAPER_SEEDS and min(values) >= PANDA_TARGET and frames <= PANDA_FRAMES
        out.append(f"- {'holds' if holds else 'does not hold (yet)'}: Panda SAC-SILP+ extended reaches >= {PANDA_TARGET} on "
                   f"every one of {PAPER_SEEDS} seeds within {PANDA_FRAMES} frames (seeds run: {len(values)}, "
                   f"success {', '.join(f'{v:.3f}' for v in values)})")
    else:
        out.append("- not run: Panda SAC-SILP+ extended")
    ur5e = runs.get("ur5e_sac_silp_plus_ext", [])
    if ur5e:
        values = _values(ur5e, "success_rate")
        mean = float(np.mean(values))
        holds = len(values) >= PAPER_SEEDS and mean >= UR5E_BEFORE - UR5E_TOLERANCE
        out.append(f"- {'holds' if holds else 'does not hold (yet)'}: no regression of the UR5e default config, its "
                   f"mean over {PAPER_SEEDS} seeds at least {UR5E_BEFORE} - {UR5E_TOLERANCE} ({UR5E_BEFORE}: the "
                   f"figure before the redesign, end-state collision check): {mean:.3f} over {len(values)} seed(s), "
                   f"{mean - UR5E_BEFORE:+.3f}")
    else:
        out.append("- not run: the UR5e default config")
    return out


def tasks_block(runs: dict[str, list[dict]], results: Path, figure: Path | None, out: Path, command: str,
                plotted: list[str]) -> str:
    lines = [
        TASKS_BEGIN,
        "### SILP+ on two task models (generated)",
        "",
        f"Generated by `{command}` from the runs in `{results}` (every number is read from their `summary.json`, "
        "`history.json`, `config.yaml` and `sweep.json`). Method names: `*_sac_silp_plus_ext` is the main job's default "
        "config (`recipes/config/sac_silp.yaml`, SAC-SILP+ extended: the paper's SILP+ with our additions), `*_sac` plain SAC with random recovery; "
        "the task is the run's `env.name`. Success rate: the 1000 test tasks of the run's task model "
        "(`eval.test_seed`), mean (std) over seeds. Swept collisions: collisions of a motion whose reached state is "
        "free (the motion passes through an obstacle, or within the motion check's margin of one), which the "
        "check of the reached state alone (the env before the redesign) let pass.",
        "",
        tasks_table(runs),
        "",
        "Acceptance figures:",
        "",
        *tasks_checks(runs),
        "",
    ]
    lines += provenance_lines(runs, "Budget (the runs' config.yaml):")
    if figure is not None and plotted:
        rel = os.path.relpath(figure, out.parent)
        lines += [f"![Success rates during training, both tasks]({rel})", "",
                  f"Test success rate against training episodes, mean ± std over seeds ({', '.join(plotted)}).", ""]
    lines.append(TASKS_END)
    return "\n".join(lines)


def default_config_checks(runs: dict[str, list[dict]]) -> list[str]:
    method_runs = runs.get(DEFAULT_CONFIG_METHOD, [])
    if not method_runs:
        return [f"- not run: {DEFAULT_CONFIG_METHOD}, the default config"]
    values = _values(method_runs, "success_rate")
    mean = float(np.mean(values))
    verdict = ("not yet (fewer seeds than that)" if len(values) < PAPER_SEEDS
               else "holds" if mean >= DEFAULT_CONFIG_TARGET else "does not hold")
    return [f"- {verdict}: the default config's test success at the end of its "
            f"budget, mean over {PAPER_SEEDS} seeds, at least {DEFAULT_CONFIG_TARGET}: {mean:.3f} over "
            f"{len(values)} seed(s) ({', '.join(f'{v:.3f}' for v in values)})"]


def _evaluated_on(method_runs: list[dict]) -> str:
    """Which tasks the runs' periodic evaluations (and so their time to 0.95) read: validation or test."""
    kinds = set()
    for run in method_runs:
        seed, test_seed = _get(run["config"], "eval.seed"), _get(run["config"], "eval.test_seed")
        kinds.add("?" if seed is None or test_seed is None else "test" if seed == test_seed else "validation")
    return " and ".join(sorted(kinds))


def success_by_frames(method_runs: list[dict], every: int = 40_000) -> str:
    """The runs' periodic-evaluation success (``history.json``) at every ``every`` frames and at the end:
    per column, each run's last point at or below that many frames, mean (std) over the runs that trained
    that far. The figures a setting is chosen on; the final test evaluation is not among them."""
    return success_by_frames_rows({"Success rate": method_runs}, every)


def _history_end(run: dict) -> int:
    return max((p["frames"] for p in run["history"] if "frames" in p), default=0)


def success_by_frames_rows(groups: dict[str, list[dict]], every: int = 40_000, until: int | None = None) -> str:
    """``success_by_frames`` with a row per labelled group of runs, on common columns: every ``every``
    frames and each run's end, up to ``until`` (the end of the longest run by default)."""
    ends = {label: [min(_history_end(r), until or math.inf) for r in runs] for label, runs in groups.items()}
    if not groups or not all(ends.values()) or min(min(e) for e in ends.values()) == 0:
        return ""
    last = max(max(e) for e in ends.values())
    columns = sorted({*range(every, int(last) + 1, every), *(int(e) for es in ends.values() for e in es)})
    rows = []
    for label, runs in groups.items():
        cells = []
        for frames in columns:
            values = []
            for run, end in zip(runs, ends[label]):
                if end < frames:
                    continue
                below = [p for p in run["history"] if p.get("frames", math.inf) <= frames and "success_rate" in p]
                if below:
                    values.append(max(below, key=lambda p: p["frames"])["success_rate"])
            cells.append(_mean_std_with(values, lambda v: f"{v:.3f}")
                         + ("" if len(values) == len(runs) else f" ({len(values)} run(s))"))
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    header = "| Frames | " + " | ".join(f"{f // 1000}k" if f % 1000 == 0 else str(f) for f in columns) + " |"
    return "\n".join([header, "|---|" + "---:|" * len(columns), *rows])


def success_by_frames_caption(method_runs: list[dict]) -> str:
    return (f"Success on the {_evaluated_on(method_runs) or '?'} tasks during training (the periodic evaluations "
            "of `history.json`: each run's last one at or below the column's frames), mean (std) over seeds:")


def default_config_block(runs: dict[str, list[dict]], results: Path, command: str) -> str:
    """The main job as a user runs it (``recipes/config/sweep_default.yaml``): the speed issue's end-of-budget
    test success over seeds, and each run's time to 0.95 on the tasks its periodic evaluations read."""
    begin, end = markers("default_config")
    method_runs = runs.get(DEFAULT_CONFIG_METHOD, [])
    lines = [
        begin,
        "### The main job's default config at its own budget (generated)",
        "",
        f"Generated by `{command}` from the runs in `{results}` (every number is read from their `summary.json`, "
        "`config.yaml` and `sweep.json`). Success rate: the 1000 test tasks (`eval.test_seed`), once, at the end "
        "of the budget, mean (std) over seeds. Time to 0.95: training wall time to the first periodic evaluation "
        f"at 0.95 or more, on the {_evaluated_on(method_runs) or '?'} tasks (`eval.seed`); a sweep's runs may "
        "share the machine, so the main job's time alone is `time_to_success_seed*.txt` of the speed block.",
        "",
        tasks_table(runs),
        "",
        f"Settings: {settings_text(method_runs) if method_runs else '—'}.",
        "",
        "Acceptance figure:",
        "",
        *default_config_checks(runs),
        "",
    ]
    curve = success_by_frames(method_runs)
    if curve:
        lines += [success_by_frames_caption(method_runs), "", curve, ""]
    return closed_block(lines, runs, end)


# the runs a setting of the default config was chosen on, read on the validation tasks (recipes/config/sweep_default.yaml
# with an override): block name -> (results dir, how their config differs from today's default)
DEFAULT_CONFIG_VARIANTS = {
    "budget_choice": ("results/default_config_320k",
                      "a larger frame budget and the reward filter (`silp.filter=reward`, the default when it ran)"),
    "filter_choice": ("results/default_config_reward_filter", "the reward filter (`silp.filter=reward`, the default before)"),
}


def default_config_variant_block(name: str, runs: dict[str, list[dict]], results: Path, command: str) -> str:
    """The main job's default config with the settings of ``DEFAULT_CONFIG_VARIANTS`` changed: the validation
    success by frames that a setting was chosen on, and the runs' test success at their end, read once,
    after the choice."""
    begin, end = markers(name)
    method_runs = runs.get(DEFAULT_CONFIG_METHOD, [])
    frames = sorted({v for r in method_runs if (v := _get(r["config"], "collector.total_frames")) is not None})
    lines = [
        begin,
        f"### The main job's default config with {DEFAULT_CONFIG_VARIANTS[name][1]}, "
        f"{', '.join(f'{f:,}' for f in frames) or '?'} frames (generated)",
        "",
        f"Generated by `{command}` from the runs in `{results}` (their `summary.json`, `history.json`, "
        "`config.yaml` and `sweep.json`; each run's overrides are its sweep command's).",
        "",
        success_by_frames_caption(method_runs),
        "",
        success_by_frames(method_runs) or "—",
        "",
        "At the end of the budget, the 1000 test tasks (`eval.test_seed`), once:",
        "",
        tasks_table(runs),
        "",
    ]
    return closed_block(lines, runs, end)


UTD_BASELINE = "sac"  # Table 1's plain SAC (results/paper_budget), beside the sweep_utd runs


def _is_setting(key: str) -> bool:
    """Whether a flattened config key is a setting a run is compared on: not its name, directory or seed."""
    return key not in ("run_dir", "seed") and not key.startswith("logger.")


def _differing_settings(runs: dict[str, list[dict]]) -> list[str]:
    """The config keys whose values differ between the runs, the run's name, directory and seed aside."""
    flats = [_flatten(r["config"] or {}) for rs in runs.values() for r in rs]
    keys = set().union(*flats) if flats else set()
    return sorted(k for k in keys if _is_setting(k) and len({repr(f.get(k)) for f in flats}) > 1)


def sac_utd_block(runs: dict[str, list[dict]], baseline: list[dict], results: Path, command: str) -> str:
    """Plain SAC at several gradient-update ratios (``recipes/config/sweep_utd.yaml``), equal frames: the
    validation success by frames, Table 1's SAC runs beside them up to the same frames, and each row's
    validation and test success at its end."""
    begin, end = markers("sac_utd")
    groups = {f"`{m}`, {_get(rs[0]['config'], 'optim.utd_ratio')} updates per transition": rs
              for m, rs in runs.items()}
    until = max((_history_end(r) for rs in runs.values() for r in rs), default=0)
    if baseline:
        groups[f"Table 1's `{UTD_BASELINE}` (older code), "
               f"{_get(baseline[0]['config'], 'optim.utd_ratio')} updates per transition"] = baseline
    rows = ["| Method | Updates per transition | Seeds | Frames | Gradient updates | Training time "
            "| Validation success at the end | Test success at the end | Test collision rate |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for method, method_runs in runs.items():
        ratios = sorted({_get(r["config"], "optim.utd_ratio") for r in method_runs}, key=str)
        rows.append(
            f"| `{method}` | {', '.join(map(str, ratios))} | {len(method_runs)} | "
            f"{', '.join(sorted({str(r['summary'].get('frames')) for r in method_runs}))} | "
            f"{', '.join(sorted({str(r['summary'].get('updates')) for r in method_runs}))} | "
            f"{hms(_mean(method_runs, 'train_wall_s') or 0.0)} | "
            f"{mean_std(_values(method_runs, 'validation_success_rate'))} | {mean_std(_values(method_runs, 'success_rate'))} | "
            f"{mean_std(_values(method_runs, 'test_collision_rate'))} |")
    lines = [
        begin,
        "### Plain SAC against the number of gradient updates per collected transition (generated)",
        "",
        f"Generated by `{command}` from the runs in `{results}` and Table 1's `{UTD_BASELINE}` runs in "
        f"`{RESULTS_OF['table1']}` (their `summary.json`, `history.json`, `config.yaml` and `sweep.json`). "
        f"The settings this sweep's runs differ in (their `config.yaml`, names and paths aside): "
        f"{', '.join(f'`{k}`' for k in _differing_settings(runs)) or 'none'}.",
        "",
        f"Success on the validation tasks during training (each run's last periodic evaluation at or below the "
        f"column's frames), mean (std) over seeds, up to {until:,} frames:",
        "",
        success_by_frames_rows(groups, every=20_000, until=until) or "—",
        "",
        "At the end of each run's budget: the validation tasks' last periodic evaluation, and the 1000 test tasks "
        "(`eval.test_seed`), once:",
        "",
        "\n".join(rows),
        "",
    ]
    return closed_block(lines, runs, end)


TUNING_BASELINES = ("tune_default", "tune_default_again")  # sweep_speed_tuning's unchanged default, first and last


def _changed_settings(config: dict | None, baseline: dict | None) -> str:
    """``key=value`` for each config key whose value differs from ``baseline``'s (names, paths and the seed aside)."""
    flat, base = _flatten(config or {}), _flatten(baseline or {})
    keys = sorted(k for k in set(flat) | set(base) if _is_setting(k) and flat.get(k) != base.get(k))
    return ", ".join(f"`{k}={flat.get(k)}`" for k in keys) or "none (the default)"


def speed_tuning_block(runs: dict[str, list[dict]], results: Path, command: str) -> str:
    """The re-tuning of ``recipes/config/sweep_speed_tuning.yaml``: the main job's default config with one
    setting changed per row, each run stopped at its first periodic evaluation at 0.95 or more on the
    validation tasks; frames, updates and training time to that point, fastest first after the default's rows."""
    begin, end = markers("speed_tuning")
    baseline = next((rs[0]["config"] for m in TUNING_BASELINES for rs in [runs.get(m)] if rs), None)
    reached = lambda r: r["summary"].get("time_to_095_s") is not None  # noqa: E731
    order = [m for m in TUNING_BASELINES if m in runs] + sorted(
        (m for m in runs if m not in TUNING_BASELINES),
        key=lambda m: (not all(map(reached, runs[m])), _mean(runs[m], "time_to_095_s") or math.inf, m))
    rows = ["| Row | Setting changed | Seeds | Reached 0.95 | Frames | Gradient updates | Training time "
            "| Time to 0.95 | Validation success at the stop |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for method in order:
        method_runs = runs[method]
        rows.append(
            f"| `{method}` | {_changed_settings(method_runs[0]['config'], baseline)} | {len(method_runs)} | "
            f"{sum(map(reached, method_runs))} of {len(method_runs)} | "
            f"{_mean_std_with(_values(method_runs, 'frames'), lambda v: f'{v:,.0f}')} | "
            f"{_mean_std_with(_values(method_runs, 'updates'), lambda v: f'{v:,.0f}')} | "
            f"{_mean_std_with(_values(method_runs, 'train_wall_s'), hms)} | "
            f"{_mean_std_with(_values(method_runs, 'time_to_095_s'), hms)} | "
            f"{mean_std(_values(method_runs, 'validation_success_rate'))} |")
    # the test tasks are those of the schema's eval.test_seed; these runs set their own test_seed to eval.seed
    test_tasks = _schema_defaults()["eval.test_seed"]
    read = {_get(r["config"], key) for rs in runs.values() for r in rs for key in ("eval.seed", "eval.test_seed")}
    evaluated = "test" if test_tasks in read else "validation"
    test_seeds = sorted({str(_get(r["config"], "eval.test_seed")) for rs in runs.values() for r in rs})
    seeds = sorted({str(_get(r["config"], "eval.seed")) for rs in runs.values() for r in rs})
    lines = [
        begin,
        "### Re-tuning for the fast update: time to 0.95 on the validation tasks (generated)",
        "",
        f"Generated by `{command}` from the runs in `{results}` (their `summary.json`, `config.yaml` and "
        "`sweep.json`). Each row is the main job's default config with the settings named changed; a run stops "
        "at its first periodic evaluation at 0.95 or more, or at its training-time limit. Its periodic "
        f"evaluations read the tasks of `eval.seed` {', '.join(seeds)}, and so does its final evaluation "
        f"(`eval.test_seed` {', '.join(test_seeds)}): "
        + ("no tuning run reads the test tasks " if evaluated == "validation" else "**some read the test tasks** ")
        + f"(`eval.test_seed` {test_tasks} by default). "
        "Frames, gradient updates and training time are at the run's stop, mean (std) over seeds. Training "
        "time is wall time without the evaluations, the update's compilation included; time to 0.95 is the "
        "training time at the first evaluation at 0.95 or more, over the runs that reached it. The default's "
        "own rows, first and last in the sweep, show how far the machine's speed moved in between.",
        "",
        "\n".join(rows),
        "",
    ]
    return closed_block(lines, runs, end)


def speed_block(results: Path, command: str) -> str:
    """The benchmarks' outputs under ``results`` (``<name>.txt``: the command on the first line,
    prefixed ``$``, then what it printed), each as it was printed; and whether a GPU figure exists."""
    files = sorted(results.glob("*.txt"))
    if not files:
        raise FileNotFoundError(f"no benchmark output (*.txt) under {results}")
    lines = [SPEED_BEGIN, "### Speed: the benchmarks' outputs (generated)", "",
             f"Regenerated by `{command}` from `{results}/`; each file is a benchmark's output, its first line "
             "the command. A line `(not alone: load average ...)` says the machine was running other jobs.", ""]
    gpu = False
    for path in files:
        text = path.read_text().rstrip("\n")
        gpu = gpu or "cuda" in text.lower()
        lines += [f"`{path.name}`:", "", "```", text, "```", ""]
    if not gpu:
        lines += ["No GPU figure yet: no GPU machine has been lent to this project's sessions.", ""]
    elif any(path.name.startswith("gpu_") for path in files):
        lines += ["The `gpu_*.txt` files come from `bash benchmarks/gpu.sh` (its parts one after another, each "
                  "under its own time limit) on a lent GPU machine, under that machine's own torch build, "
                  "named on each file's second line. There a load average counts the previous part's compile "
                  "workers winding down on that machine's cores, not another job.", ""]
    lines.append(SPEED_END)
    return "\n".join(lines)


def write_block(path: Path, text: str, begin: str = BEGIN, end_marker: str = END) -> None:
    """Replace the block between the markers of ``path``, or append it when they are missing."""
    old = path.read_text() if path.exists() else ""
    start, end = old.find(begin), old.find(end_marker)
    if start != -1 and end > start:
        new = old[:start] + text + old[end + len(end_marker):]
    else:
        new = (old.rstrip("\n") + "\n\n" if old.strip() else "") + text + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(new)


RESULTS_OF = {"speed": "results/benchmarks", **{n: d for n, (d, _) in DEFAULT_CONFIG_VARIANTS.items()},
              "tasks": "results/tasks", "sac_utd": "results/sac_utd", "speed_tuning": "results/speed_tuning",
              "table1_40k": "results/table1_40k",
              "table5": "results/transfer", "pick_place": "results/transfer", "collision_net": "results/collision_net",
              **{name: "results/paper_budget" for name in ("table1", "table2", "table3", "table4", "tableA1", "ablations")}}


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--block", choices=BLOCKS, default="table1",
                        help="table1-4, tableA1: the paper's tables at its budget (results/paper_budget); ablations: "
                             "ours minus one addition at a time; table1_40k: the earlier 40k-frame runs; "
                             "tasks: SILP+ on the UR5e and Panda task models; default_config: the main job's "
                             "default config at its own budget (results/default_config); budget_choice, filter_choice: the "
                             "earlier default config with the setting changed, the figures each was chosen on; sac_utd: plain SAC at "
                             "several update ratios (results/sac_utd) beside Table 1's; speed_tuning: the "
                             "default config with one setting changed, time to 0.95 on the validation tasks "
                             "(results/speed_tuning); table5: the MuJoCo transfer; "
                             "speed: the benchmarks' outputs (results/benchmarks)")
    parser.add_argument("--results", type=Path, default=None,
                        help="the sweep's results_dir (results/paper_budget, results/tasks, ... by --block)")
    parser.add_argument("--out", type=Path, default=Path("docs/results.md"), help="the markdown file to update")
    parser.add_argument("--figure", type=Path, default=None,
                        help="the figure (docs/<block>_curves.png: Table 1's and the tasks' learning curves, "
                             "Table 4's filter share)")
    args = parser.parse_args(argv)
    args.results = args.results or Path(RESULTS_OF.get(args.block, f"results/{args.block}"))
    args.figure = args.figure or Path(f"docs/{args.block}_curves.png")
    given = sys.argv[1:] if argv is None else argv
    command = " ".join(["python recipes/report.py", *map(shlex.quote, given)])
    text = render(args.block, args.results, args.figure, args.out, command)
    write_block(args.out, text, *markers(args.block))
    print(text)
    print(f"wrote {args.out}")
    return text


def render(name: str, results: Path, figure: Path, out: Path, command: str, plot_to: Path | None = None) -> str:
    """The text of block ``name`` from ``results``, its figure (if it has one) drawn to ``plot_to`` (``figure``
    by default) and linked from ``out`` as ``figure``."""
    plot_to = plot_to or figure
    if name == "speed":
        return speed_block(results, command)
    if name == "collision_net":
        budget = Path(RESULTS_OF["table1"])
        runs = load_results(budget) if any(budget.glob("*/seed*/summary.json")) else {}
        return collision_net_block(load_collision_nets(results), results, figure, out, command, runs, plot_to)
    if name in ("table5", "pick_place"):
        return (table5_block if name == "table5" else pick_place_block)(load_transfer(results), results, command)
    runs = load_results(results)
    if name in PAPER_TABLES:
        return paper_table_block(runs, name, results, figure if name == "table4" else None, out, command, plot_to)
    if name == "ablations":
        return ablations_block(runs, results, command)
    if name == "default_config":
        return default_config_block(runs, results, command)
    if name in DEFAULT_CONFIG_VARIANTS:
        return default_config_variant_block(name, runs, results, command)
    if name == "sac_utd":
        budget = Path(RESULTS_OF["table1"])
        baseline = load_results(budget).get(UTD_BASELINE, []) if budget.is_dir() else []
        return sac_utd_block(runs, baseline, results, command)
    if name == "speed_tuning":
        return speed_tuning_block(runs, results, command)
    if name == "table1":  # the paper's Table 1 rows; the other tables' runs share the results dir
        runs = {m: rs for m, rs in runs.items() if m in ROW_ORDER}
    plotted = plot_curves(runs, plot_to)
    if name == "tasks":
        return tasks_block(runs, results, figure, out, command, plotted)
    return block(runs, results, figure, out, command, plotted, name)


BLOCKS = ("table1", "ablations", "table2", "table3", "table4", "tableA1", "collision_net", "tasks", "default_config",
          *DEFAULT_CONFIG_VARIANTS, "sac_utd", "speed_tuning", "speed", "table5", "pick_place", "table1_40k")


if __name__ == "__main__":
    try:
        main()
    except FileNotFoundError as exc:
        sys.exit(f"report.py: {exc}")
