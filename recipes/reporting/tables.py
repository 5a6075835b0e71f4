"""Records -> markdown: the tables of the results pages, each from a block spec of ``pages.yaml``.

Every number is a mean (std) over seeds with ddof=0 (one seed: its value). A row names its method:
*the paper's X as written* when its runs' configs have none of our additions
(``recipes/config/paper_settings.yaml``), *ours: X + additions* otherwise, the Settings column
listing which.

Examples:
    >>> mean_std([0.9, 0.92]), mean_std([0.9]), mean_std([])
    ('0.910 (0.010)', '0.900', '—')
    >>> hms(3723.4), mean_std([60.0, 120.0], hms)
    ('1:02:03', '0:01:30 (0:00:30)')
    >>> seconds3([0.00159, 0.00161])(0.0016)
    '0.00160'
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import re
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from . import load
from .load import Run, flatten, get

DATA = Path(__file__).resolve().parent
PAPER_SETTINGS = DATA.parent / "config" / "paper_settings.yaml"


# ----------------------------------------------------------------------------------------- formatting
def rate(x: float) -> str:
    return f"{x:.3f}"


def count(x: float) -> str:
    return f"{x:,.0f}"


def hms(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


def seconds3(values: list[float]) -> Callable[[float], str]:
    """Three significant digits of the values' mean, at least three decimals: 0.134, 0.00123."""
    top = max(abs(float(np.mean(values))), 1e-12)
    decimals = max(3, 2 - math.floor(math.log10(top)))
    return lambda x: f"{x:.{decimals}f}"


def mean_std(values: Iterable[float], fmt: Callable[[float], str] = rate) -> str:
    """``mean (std)`` over the values (ddof=0), the value alone for one, ``—`` for none."""
    arr = np.asarray([v for v in values if v is not None], dtype=float)
    if arr.size == 0:
        return "—"
    return fmt(arr.mean()) if arr.size == 1 else f"{fmt(arr.mean())} ({fmt(arr.std())})"


def paper_cell(figure, fmt: Callable[[float], str] = rate) -> str:
    """A figure of paper.yaml: ``[mean, std]``, ``[mean]`` or a number; ``—`` where the paper gives none."""
    if figure is None:
        return "—"
    figure = figure if isinstance(figure, list) else [figure]
    figure = [_seconds(f) if isinstance(f, str) else f for f in figure]
    return fmt(figure[0]) if len(figure) == 1 else f"{fmt(figure[0])} ({fmt(figure[1])})"


def _seconds(text: str) -> int:
    """``"5:22:58"`` -> 19378."""
    h, m, s = (int(x) for x in text.split(":"))
    return 3600 * h + 60 * m + s


def table(header: list[str], rows: list[list[str]], align: list[str]) -> str:
    """A markdown table; ``align`` holds ``"l"`` or ``"r"`` per column."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" if a == "r" else "---" for a in align) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def seeds_text(seeds: list[int]) -> str:
    """``[0, 1, 2]`` -> ``seeds 0-2``; ``[0, 2]`` -> ``seeds 0, 2``; ``[1]`` -> ``seed 1``."""
    seeds = sorted(seeds)
    if len(seeds) == 1:
        return f"seed {seeds[0]}"
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"seeds {seeds[0]}-{seeds[-1]}"
    return "seeds " + ", ".join(map(str, seeds))


# ------------------------------------------------------------------------------------------ the data
@functools.cache
def paper() -> dict:
    """The paper's figures and method names (``paper.yaml``)."""
    import yaml

    return yaml.safe_load((DATA / "paper.yaml").read_text())


@functools.cache
def _paper_settings() -> dict:
    import yaml

    return flatten(yaml.safe_load(PAPER_SETTINGS.read_text()))


def _acts(config: dict, key: str) -> bool:
    """Whether a setting acts in a run of this config (the planner's does not without demonstrations, ...)."""
    if key.startswith("planner."):
        return bool(get(config, "silp.demos"))
    if key == "exploration.mask_colliding_candidates":  # the recovery action's: GP candidates or a random one
        # (type 0 ends the episode at a collision: no recovery action follows)
        return get(config, "exploration.mode") in ("gp", "random") and get(config, "env.collision_type") != 0
    if key == "optim.target_entropy":
        return get(config, "algorithm") == "sac"
    if key == "silp.filter":
        return bool(get(config, "silp.bc"))
    return True


def additions(config: dict | None) -> list[str] | None:
    """Our additions a training run's config turns on, named as paper.yaml's ``settings.names``: ``[]`` is the
    paper's method as written; None: not a training run (BC, PRM) or no config.

    A setting a config lacks takes the value paper.yaml's ``settings.absent`` gives it (runs made before
    its switch existed behaved so); any other setting that acts in the run must be in its config.
    """
    if config is None or get(config, "algorithm") is None:
        return None
    spec = paper()["settings"]
    given = flatten(config)
    out = []
    for key, value_of_paper in _paper_settings().items():
        if not _acts(config, key):
            continue
        if key in given:
            value = given[key]
        elif key in spec["absent"]:
            value = spec["absent"][key]
        else:
            raise KeyError(f"the run's config has no {key!r}, and paper.yaml's settings.absent gives no value for it")
        name = spec["names"].get(key, key)
        # a setting whose paper value depends on the exploration mode (the random recovery is collision-free)
        by_mode = spec.get("by_mode", {}).get(key, {}).get(get(config, "exploration.mode"))
        if by_mode is not None:
            value_of_paper, name = by_mode["paper"], by_mode["name"]
        if value != value_of_paper and value not in spec["also_paper"].get(key, ()):
            out.append(name)
    return out


def settings_text(runs: list[Run]) -> str:
    """The Settings cell: ``paper's``, ``ours: +a, +b``, or ``—`` (not a training run); runs that differ, joined."""
    texts = []
    for run in runs:
        added = additions(run.config)
        text = "—" if added is None else "paper's" if not added else "ours: " + ", ".join(f"+{a}" for a in added)
        if text not in texts:
            texts.append(text)
    return "; ".join(texts) or "—"


def method_label(method: str, runs: list[Run], name: str | None = None, qualifier: str = "",
                 ours: bool | None = None) -> str:
    """*the paper's X as written* or *ours: X + additions*, from the runs' configs (else ``ours``, else
    paper.yaml's ``methods`` entry), then the qualifier and the run folder's name."""
    entry = paper()["methods"].get(method, {})
    entry = {"name": entry} if isinstance(entry, str) else entry
    name = name or entry.get("name", method)
    found = [a for a in (additions(r.config) for r in runs) if a is not None]
    # settings that depart from the paper without being additions of ours (an unchecked recovery action)
    not_ours = {m["name"] for modes in paper()["settings"].get("by_mode", {}).values() for m in modes.values()
                if not m.get("ours", True)}
    departures = sorted({a for added in found for a in added if a in not_ours})
    if found:
        is_ours = any(a not in not_ours for added in found for a in added)
    else:
        is_ours = bool(entry.get("ours", False) if ours is None else ours)
    if is_ours:
        text = f"ours: {name} + additions"
    elif departures:
        text = f"the paper's {name} with {', '.join(departures)}"
    else:
        text = f"the paper's {name} as written"
    return f"{text}{qualifier} (`{method}`)"


# ------------------------------------------------------------------------------------ a block of runs
@dataclasses.dataclass
class Row:
    """A row of a runs table: its spec, its runs (seed filter applied) and every run of its method."""

    id: str
    method: str
    spec: dict
    runs: list[Run]
    all_runs: list[Run]
    folder: str

    def values(self, key: str) -> list[float]:
        return [v for v in (r.value(key) for r in self.runs) if v is not None]

    def mean(self, key: str) -> float | None:
        values = self.values(key)
        return float(np.mean(values)) if values else None

    def std(self, key: str) -> float | None:
        values = self.values(key)
        return float(np.std(values)) if values else None


def build_rows(spec: dict, loader: Callable[[str], dict[str, list[Run]]]) -> list[Row]:
    """The block's rows: its ``rows`` list (or ``all``: every method of its results folder, by name)."""
    rows_spec = spec.get("rows", "all")
    if rows_spec == "all":
        rows_spec = [{"method": m} for m in loader(spec["results"])]
    rows = []
    for item in rows_spec:
        item = {"method": item} if isinstance(item, str) else item
        folder = item.get("results", spec["results"])
        all_runs = loader(folder).get(item["method"], [])
        seeds = item.get("seeds", spec.get("seeds"))
        runs = [r for r in all_runs if seeds is None or r.seed in seeds]
        rows.append(Row(item.get("id", item["method"]), item["method"], item, runs, all_runs, folder))
    return rows


class Context:
    """What a column needs besides its row: the block spec, every row by id, the paper's table."""

    def __init__(self, spec: dict, rows: list[Row]):
        self.spec, self.rows = spec, rows
        self.by_id = {r.id: r for r in rows}
        self.paper = paper().get(spec["paper"], {}) if spec.get("paper") else {}
        self.baseline = self.by_id.get(spec["baseline"]) if spec.get("baseline") else None

    def label(self, row: Row) -> str:
        if "label" in row.spec:
            return row.spec["label"]
        return method_label(row.method, row.runs, row.spec.get("name", self.spec.get("name")),
                            row.spec.get("qualifier", ""), row.spec.get("ours"))

    def figures(self, row: Row) -> dict:
        return self.paper.get(row.spec.get("paper", row.method), {}) or {}


def _key_cell(key: str, fmt=rate) -> Callable[[Context, Row], str]:
    """The mean (std) of a summary key over the row's runs, with how many of them give it where some do not (runs
    from before the key); a row with no run: ``not run`` in its success column."""
    def cell(ctx: Context, row: Row) -> str:
        if not row.runs:
            return "not run" if key == "success_rate" else "—"
        return mean_std(row.values(key), fmt) + _of_runs(row, key)
    return cell


def _of_runs(row: Row, key: str) -> str:
    """`` (k of n runs)`` when only some of the row's ``n`` runs give ``key``, else nothing."""
    k = len(row.values(key))
    return f" ({k} of {len(row.runs)} runs)" if 0 < k < len(row.runs) else ""


def _free_blocked(ctx: Context, row: Row) -> str:
    """``free / blocked (share free)``: the means of the split's success rates over the row's runs."""
    share = row.mean("test_free_task_share")
    if share is None:
        return "—"
    free, blocked = (row.mean(f"test_{kind}_success_rate") for kind in ("free", "blocked"))
    cells = " / ".join("—" if v is None else rate(v) for v in (free, blocked))
    return f"{cells} ({rate(share)} free){_of_runs(row, 'test_free_task_share')}"


def _changed(ctx: Context, row: Row) -> str:
    """``key=value`` for each setting in which the row's config differs from the baseline row's."""
    if ctx.baseline is None or not ctx.baseline.runs or not row.runs:
        return "—"
    absent = paper()["settings"]["absent"]  # a switch's value in a config that predates it
    mine = {**absent, **flatten(row.runs[0].config or {})}
    base = {**absent, **flatten(ctx.baseline.runs[0].config or {})}
    keys = sorted(k for k in set(mine) & set(base) if _is_setting(k) and mine[k] != base[k])
    return ", ".join(f"`{k}={_yaml(mine[k])}`" for k in keys) or "none (the baseline)"


def _is_setting(key: str) -> bool:
    return key not in ("run_dir", "seed") and not key.startswith("logger.")


def _yaml(value) -> str:
    return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def _config(key: str) -> Callable[[Context, Row], str]:
    def cell(ctx: Context, row: Row) -> str:
        values = list(dict.fromkeys(_yaml(get(r.config, key)) for r in row.runs))
        return ", ".join(values) or "—"
    return cell


def _delta(key: str) -> Callable[[Context, Row], str]:
    def cell(ctx: Context, row: Row) -> str:
        if ctx.baseline is None or row is ctx.baseline or not row.runs or ctx.baseline.mean(key) is None:
            return ""
        return f"{row.mean(key) - ctx.baseline.mean(key):+.3f}"
    return cell


def _noise(key: str) -> Callable[[Context, Row], str]:
    """Whether the row's difference from the baseline is beyond twice the baseline's std over all its seeds."""
    def cell(ctx: Context, row: Row) -> str:
        base = ctx.baseline
        spread = [v for v in (r.value(key) for r in base.all_runs) if v is not None] if base else []
        if base is None or row is base or not row.runs or len(spread) < 2 or base.mean(key) is None:
            return ""
        return "beyond" if abs(row.mean(key) - base.mean(key)) > 2 * float(np.std(spread)) else "within"
    return cell


def _time_to_095(ctx: Context, row: Row) -> str:
    if not row.runs:
        return "not run"
    reached = row.values("time_to_095_s")
    text = f"({len(reached)}/{len(row.runs)} reached)"
    return f"{hms(float(np.mean(reached)))} {text}" if reached else text


def first_reaching(run, level: float) -> dict | None:
    """The first periodic evaluation (a ``history.json`` point) at ``level`` or more, or None."""
    return next((p for p in run.history if (p.get("success_rate") or 0.0) >= level), None)


def _to_level(level: float) -> Callable[[Context, Row], str]:
    def cell(ctx: Context, row: Row) -> str:
        if not row.runs:
            return "not run"
        points = [p for p in (first_reaching(r, level) for r in row.runs) if p is not None]
        text = f"({len(points)}/{len(row.runs)} reached)"
        if not points:
            return text
        time, frames = np.mean([p["train_wall_s"] for p in points]), np.mean([p["frames"] for p in points])
        return f"{hms(float(time))}, {count(float(frames))} frames {text}"
    return cell


def _plan_time(ctx: Context, row: Row) -> str:
    values = row.values("rollout_time_per_episode_s")
    return mean_std(values, seconds3(values)) if values else "—"


def _episodes_frames(ctx: Context, row: Row) -> str:
    episodes, frames = row.mean("episodes"), row.mean("frames")
    if not episodes:
        return "—"
    return count(episodes) + ("" if frames is None else f" ({count(frames)})")


def _swept(ctx: Context, row: Row) -> str:
    collisions, swept = row.mean("collisions_during_training"), row.mean("swept_collisions_during_training")
    if collisions is None or swept is None:
        return "—"
    return f"{count(swept)} ({swept / max(collisions, 1):.1%})"


def _train_time(ctx: Context, row: Row) -> str:
    values = row.values("train_wall_s")
    return mean_std(values, hms) if values else ("*" if row.runs else "—")


def _paper_key(key: str, fmt) -> Callable[[Context, Row], str]:
    def cell(ctx: Context, row: Row) -> str:
        figures = ctx.figures(row)
        if key == "train" and figures and figures.get("train") is None and "success" in figures:
            return "*"  # a planner: nothing to train
        return paper_cell(figures.get(key), fmt)
    return cell


@dataclasses.dataclass
class Column:
    header: str
    align: str
    cell: Callable[[Context, Row], str]
    about: str = ""


COLUMNS = {
    "method": Column("Method", "l", lambda ctx, row: ctx.label(row)),
    "task": Column("Task", "l", _config("env.name")),
    "settings": Column("Settings", "l", lambda ctx, row: settings_text(row.runs) if row.runs else "—",
                       "*paper's*: the paper's settings (`recipes/config/paper_settings.yaml`); *ours*: each of "
                       "our additions the runs' `config.yaml` turns on (`docs/paper_vs_ours.md`)"),
    "changed": Column("Changed from the baseline", "l", _changed,
                      "the settings in which a row's `config.yaml` differs from the baseline row's (a switch a "
                      "config predates counts at the value runs without it had; other keys only one of them has, "
                      "added to the code later, aside)"),
    "seeds": Column("Seeds", "r", lambda ctx, row: str(len(row.runs))),
    "success": Column("Test success", "r", _key_cell("success_rate"),
                      "the 1000 test tasks (`eval.test_seed`), read once at the end"),
    "validation": Column("Validation success", "r", _key_cell("validation_success_rate"),
                         "the last periodic evaluation, on the validation tasks (`eval.seed`)"),
    "test_collision": Column("Test collision rate", "r", _key_cell("test_collision_rate"),
                             "the share of the test tasks that end in a collision (the other failures run out of "
                             "steps)"),
    "sampling": Column("Test success, sampled actions", "r", _key_cell("sampling_success_rate"),
                       "SAC's policy on the test tasks acting as it does in training, its actions sampled (the "
                       "other success columns take its mean action, as the paper tests)"),
    "free_blocked": Column("Test success: straight path free / blocked", "r", _free_blocked,
                           "the test tasks split by whether the straight joint path to the goal solves them "
                           "(`torchrl_silp.eval.straight_path_free`), and the share of the free ones"),
    "train_time": Column("Training time", "r", _train_time,
                         "`train_wall_s`, wall time without the evaluations (*: a planner, nothing to train)"),
    "time_to_095": Column("Time to 0.95", "r", _time_to_095,
                          "training time to the first periodic evaluation at 0.95 or more, over the runs that "
                          "reached it"),
    "to_090": Column("Time, frames to 0.9", "r", _to_level(0.9),
                     "training time and frames to the first periodic evaluation at 0.9 or more (the validation "
                     "tasks), over the runs that reached it"),
    "to_095": Column("Time, frames to 0.95", "r", _to_level(0.95),
                     "training time and frames to the first periodic evaluation at 0.95 or more, over the runs "
                     "that reached it"),
    "reached": Column("Reached 0.95", "r",
                      lambda ctx, row: f"{len(row.values('time_to_095_s'))} of {len(row.runs)}"),
    "plan_time": Column("Planning time per rollout (s)", "r", _plan_time,
                        "`rollout_time_per_episode_s`, the batched evaluation rollout's wall time over its tasks"),
    "frames": Column("Frames", "r", lambda ctx, row: mean_std(row.values("frames"), count)),
    "updates": Column("Gradient updates", "r", lambda ctx, row: mean_std(row.values("updates"), count)),
    "episodes_frames": Column("Training episodes (frames)", "r", _episodes_frames),
    "collisions": Column("Collisions in training", "r",
                         lambda ctx, row: mean_std(row.values("collisions_during_training"), count),
                         "colliding steps during training"),
    "swept": Column("of which swept", "r", _swept,
                    "collisions of a motion whose end state is free, which a check of the end state alone lets pass"),
    "demos_stored": Column("Demos stored", "r", lambda ctx, row: mean_std(row.values("demos_stored"), count),
                           "transitions in the demonstration buffer at the end"),
    "note": Column("", "l", lambda ctx, row: row.spec.get("note", "")),
    "paper_success": Column("paper", "r", _paper_key("success", rate)),
    "paper_gap": Column("vs paper", "r",
                        lambda ctx, row: "—" if (g := _paper_gap(ctx, row)) is None else f"{g:+.3f}",
                        "the row's mean test success minus the paper's figure for its method"),
    "paper_train_time": Column("paper", "r", _paper_key("train", hms)),
    "paper_plan_time": Column("paper", "r", _paper_key("plan_s", rate)),
    "paper_collisions": Column("paper", "r", _paper_key("collisions", count)),
}


def column(name: str, spec: dict) -> Column:
    """A column by name: one of ``COLUMNS``, ``config:<key>``, ``delta:<summary key>``, ``noise:<summary key>``."""
    headers = spec.get("headers", {})
    kind, _, arg = name.partition(":")
    if kind == "config":
        base = Column(f"`{arg}`", "l", _config(arg))
    elif kind == "delta":
        base = Column("vs the baseline", "r", _delta(arg), "the row's mean minus the baseline row's")
    elif kind == "noise":
        base = Column("Beyond 2 std?", "r", _noise(arg),
                      "whether that difference exceeds twice the std of the baseline over all its seeds")
    elif name in COLUMNS:
        base = COLUMNS[name]
    else:
        raise KeyError(f"no column {name!r}: one of {', '.join(COLUMNS)}, config:<key>, delta:<key>, noise:<key>")
    return dataclasses.replace(base, header=headers.get(name, base.header))


def runs_table(ctx: Context) -> tuple[str, list[str]]:
    """The block's table and the descriptions of its columns."""
    columns = [column(n, ctx.spec) for n in ctx.spec["columns"]]
    rows = [[c.cell(ctx, row) for c in columns] for row in ctx.rows]
    about = [f"*{c.header}*: {c.about}" for c in columns if c.about]
    return table([c.header for c in columns], rows, [c.align for c in columns]), about


# ------------------------------------------------------------------------- orderings and differences
# summary keys that are times: an ordering of them compares like with like only on one machine kind, with the
# same number of runs at once
TIME_KEYS = ("train_wall_s", "rollout_time_per_episode_s", "time_to_095_s", "planning_s")


def checks(ctx: Context) -> list[str]:
    """The block's ``checks`` on its rows (``judge``); a list in ``checks`` (a YAML alias of a list of checks)
    counts as its items."""
    def value(m: str, key: str, stat: str) -> float | None:
        return getattr(ctx.by_id[m], stat)(key) if m in ctx.by_id else None

    def machines(m: str) -> set[str]:
        return {_machine(run) for run in ctx.by_id[m].runs} if m in ctx.by_id else set()

    listed = ctx.spec.get("checks", [])
    return [judge(c, value, machines) for item in listed for c in (item if isinstance(item, list) else [item])]


def _is_rate(key: str) -> bool:
    """A summary key that is a share (``success_rate``, ``success_rate@episodes=1000``)."""
    return key.split("@")[0].endswith("rate")


def _size(values: list[float], key: str, fmt: Callable[[float], str], spread: list[float | None]) -> str:
    """How far apart two rows are: a time's relative difference, else the difference, with whether it lies
    within the seeds' spread (the larger std of the two)."""
    a, b = values
    if key in TIME_KEYS:
        return f"{abs(a - b) / a:.0%} {'less' if b < a else 'more'}" if a else ""
    size = f"{a - b:+.3f}" if _is_rate(key) else f"{a - b:+,.0f}"
    stds = [s for s in spread if s is not None]
    if stds and abs(a - b) <= max(stds):
        size += f", within the seeds' spread: std up to {fmt(max(stds))}"
    return size


def judge(check: dict, value: Callable[[str, str, str], float | None],
          machines: Callable[[str], set[str]] | None = None) -> str:
    """One line: whether ``check`` holds, with the figures it was judged on.

    A check holds when every one of its orderings (``check["all"]``) holds. An ordering
    ``{order: [a, b, c], key: success_rate, strict: false}`` reads ``a ≥ b ≥ c`` of ``value(m, key, stat)``
    (``stat``: ``mean`` by default, ``std`` for the spread over seeds); a number in ``order`` is a threshold
    the rows are held to. With ``max_difference: d`` an ordering of two rows reads ``a − b ≤ d`` instead.
    ``value`` gives ``None`` for a row that was not run. An ordering of two rows also gives its size: a
    time's relative difference, else the difference and whether it lies within the seeds' spread.

    ``machines(m)``: the machines row ``m``'s runs ran on (with how many runs at once). A check that
    orders times (:data:`TIME_KEYS`) of rows that ran on different machines, or not as many at once, is
    not judged: the line says which ran where.
    """
    parts, holds, missing, unlike = [], True, [], {}
    for ordering in check["all"]:
        key, strict = ordering.get("key", "success_rate"), ordering.get("strict", False)
        stat, order = ordering.get("stat", "mean"), ordering["order"]
        values = [float(m) if isinstance(m, (int, float)) else value(m, key, stat) for m in order]
        missing += [m for m, v in zip(order, values) if v is None and m not in missing]
        if "max_difference" in ordering and len(order) != 2:
            raise ValueError(f"{check['text']!r}: a max_difference check compares two rows, got order={order}")
        if any(v is None for v in values):
            continue
        fmt = rate if max(abs(v) for v in values) < 1 and _is_rate(key) else (
            count if max(values) >= 100 else seconds3(values))
        of = " (std)" if stat == "std" else ""
        named = [fmt(v) if isinstance(m, (int, float)) else f"`{m}`{of} {fmt(v)}" for m, v in zip(order, values)]
        if "max_difference" in ordering:
            bound = ordering["max_difference"]
            ok = values[0] - values[1] <= bound
            parts.append(f"{named[0]} − {named[1]} = {fmt(values[0] - values[1])} {'≤' if ok else '>'} {fmt(bound)}")
        else:
            ok = all((a > b) if strict else (a >= b) for a, b in zip(values, values[1:]))
            part = (" > " if strict else " ≥ ").join(named)
            rows = [m for m in order if not isinstance(m, (int, float))]
            if len(order) == 2 and len(rows) == 2 and stat == "mean":
                size = _size(values, key, fmt, [value(m, key, "std") for m in order])
                part += f" ({size})" if size else ""
            parts.append(part)
        if machines is not None and key in TIME_KEYS:
            for m in order:
                if not isinstance(m, (int, float)):
                    unlike.setdefault(m, machines(m))
        holds &= ok
    if missing:
        return f"- not run: {check['text']} (missing: {', '.join(f'`{m}`' for m in missing)})"
    if len({frozenset(s) for s in unlike.values()}) > 1 or any(len(s) > 1 for s in unlike.values()):
        by_machine: dict[str, list[str]] = {}
        for m, kinds in unlike.items():
            for kind in sorted(kinds):
                by_machine.setdefault(kind, []).append(f"`{m}`")
        where = "; ".join(f"{', '.join(ms)} on {kind}" for kind, ms in by_machine.items())
        return (f"- not judged, the runs' machines differ: {check['text']} ({'; '.join(parts)}; "
                f"times compare only on one machine kind with as many runs at once: {where})")
    return f"- {'holds' if holds else 'does not hold'}: {check['text']} ({'; '.join(parts)})"


def differences(ctx: Context) -> list[str]:
    """``a − b`` of the rows' mean test success, for each ``[a, b]`` of the block's ``differences``."""
    out = []
    for a, b in ctx.spec.get("differences", []):
        ra, rb = ctx.by_id.get(a), ctx.by_id.get(b)
        if ra is None or rb is None or ra.mean("success_rate") is None or rb.mean("success_rate") is None:
            continue
        out.append(f"- `{a}` − `{b}`: {ra.mean('success_rate') - rb.mean('success_rate'):+.3f} test success "
                   f"({len(ra.runs)} and {len(rb.runs)} seeds)")
    return out


def planning_table(spec: dict) -> list[str]:
    """A block's ``planning``: the planner's figures against a parameter, one column per value, from the
    markdown table of a benchmark output whose title starts with ``table``; the paper's figures beside (its
    table ``paper`` of paper.yaml, ``{method: {figure: value}}``, the methods in ``columns`` order) and the
    paper's trends (``trends: [{text, measure, order: increasing | decreasing}]``) checked on each kind.

    ``spec``: ``{file, table, kind_column, parameter_column, columns: {value: paper method}, measures:
    {benchmark column: [label, paper figure or null, format, factor to the paper's unit (1)]}, trends}``.
    """
    path = Path(spec["file"])
    found = {t: v for t, v in load.markdown_tables(path).items() if t.startswith(spec["table"])}
    if not found:
        raise ValueError(f"{path}: no table titled {spec['table']!r}...")
    title, (header, cells) = next(iter(found.items()))
    kind_at, value_at = header.index(spec["kind_column"]), header.index(spec["parameter_column"])
    values = list(spec["columns"])
    texts: dict[str, dict[str, dict[str, str]]] = {}  # rollouts kind -> parameter value -> column -> cell
    for row in cells:
        texts.setdefault(row[kind_at], {})[row[value_at]] = dict(zip(header, row))
    figures = paper().get(spec["paper"], {})
    out = []
    for measure, (label, paper_key, fmt, *scale) in spec["measures"].items():
        factor = scale[0] if scale else 1.0
        for kind, by_value in texts.items():
            out.append([label, kind] + [format(load.number(by_value[v][measure]) * factor, fmt) if v in by_value
                                        else "—" for v in values])
        if paper_key:
            out.append([label, "the paper"] + [
                format(figures[m][paper_key][0] if isinstance(figures[m][paper_key], list) else figures[m][paper_key],
                       fmt) if paper_key in figures.get(m, {}) else "—" for m in spec["columns"].values()])
    lines = [f"Planning against {spec['parameter_column']}, from `{path}` (its table \"{title}\"):", "",
             table(["Measure", "Roadmaps", *values], out, ["l", "l", *["r"] * len(values)]), ""]
    checks = []
    for trend in spec.get("trends", []):
        for kind, by_value in texts.items():
            shown = [by_value[v][trend["measure"]] for v in values if v in by_value]
            pairs = list(zip(map(load.number, shown), map(load.number, shown[1:])))
            holds = all(b >= a for a, b in pairs) if trend["order"] == "increasing" else all(b <= a for a, b in pairs)
            sign = " ≤ " if trend["order"] == "increasing" else " ≥ "
            checks.append(f"- {'holds' if holds else 'does not hold'}: {trend['text']}, {kind} roadmaps "
                          f"({trend['measure']}: {sign.join(shown)})")
    if checks:
        lines += ["The paper's trends, on these roadmaps:", "", *checks, ""]
    benchmark = load.load_benchmark(path)
    busy = " (not alone: other work ran beside it)" if "WARNING: load average" in path.read_text() else ""
    lines += [f"Machine: {benchmark.machine}{busy}. Made by: `{benchmark.command}`. "
              f"{spec.get('about', '').strip()}".strip(), ""]
    return lines


def _paper_gap(ctx: Context, row: Row) -> float | None:
    ours, figure = row.mean("success_rate"), ctx.figures(row).get("success")
    return None if ours is None or not figure else ours - figure[0]


def paper_gaps(ctx: Context) -> list[str]:
    """``gaps: {threshold, causes: {row id: text}}``: the cause of each row further than ``threshold`` (either
    way) from the paper's test success for its method, rows of one cause together; a row without one in
    ``causes`` is listed as having none."""
    spec = ctx.spec.get("gaps")
    if not spec:
        return []
    by_cause: dict[str, list[str]] = {}
    for row in ctx.rows:
        gap = _paper_gap(ctx, row)
        if gap is not None and abs(gap) > spec["threshold"]:
            cause = spec.get("causes", {}).get(row.id, "No cause measured or stated.").strip()
            by_cause.setdefault(cause, []).append(f"`{row.id}` ({gap:+.3f})")
    return [f"- {', '.join(rows)}: {cause}" for cause, rows in by_cause.items()]


def seed_notes(ctx: Context) -> list[str]:
    expected = ctx.spec.get("seed_notes")
    if not expected:
        return []
    out = []
    for row in ctx.rows:
        if not row.runs:
            out.append(f"- `{row.id}`: not run")
        elif len(row.runs) < expected:
            out.append(f"- `{row.id}`: {len(row.runs)} of {expected} seeds ({seeds_text([r.seed for r in row.runs])})")
    return out


# ---------------------------------------------------------------------------- success against frames
def _history_end(run: Run) -> int:
    return max((p["frames"] for p in run.history if "frames" in p), default=0)


def success_by_frames(groups: dict[str, list[Run]], every: int, until: int | None = None) -> str:
    """Each group's periodic-evaluation success at every ``every`` frames and at each run's end, up to ``until``:
    per column, each run's last evaluation at or below that many frames, mean (std) over the runs that trained
    that far (``(k run(s))`` where fewer than the group's)."""
    groups = {label: runs for label, runs in groups.items() if runs}
    ends = {label: [min(_history_end(r), until or math.inf) for r in runs] for label, runs in groups.items()}
    if not groups or min(min(e) for e in ends.values()) == 0:
        return ""
    last = max(max(e) for e in ends.values())
    columns = sorted({*range(every, int(last) + 1, every), *(int(e) for es in ends.values() for e in es)})
    rows = []
    for label, runs in groups.items():
        cells = []
        for frames in columns:
            values = []
            for run, end in zip(runs, ends[label]):
                below = [p for p in run.history if p.get("frames", math.inf) <= frames and "success_rate" in p]
                if end >= frames and below:
                    values.append(max(below, key=lambda p: p["frames"])["success_rate"])
            partial = "" if len(values) in (0, len(runs)) else f" ({len(values)} run(s))"
            cells.append(mean_std(values) + partial)
        rows.append([label, *cells])
    header = ["Frames", *(f"{f // 1000}k" if f % 1000 == 0 else str(f) for f in columns)]
    return table(header, rows, ["l", *"r" * len(columns)])


def by_frames(ctx: Context) -> str:
    spec = ctx.spec.get("by_frames")
    if not spec:
        return ""
    rows = [ctx.by_id[i] for i in spec["rows"]] if "rows" in spec else ctx.rows
    until = None
    if "until" in spec:
        until = max(_history_end(r) for i in spec["until"] for r in ctx.by_id[i].runs)
    return success_by_frames({f"`{row.id}`": row.runs for row in rows}, spec["every"], until)


# ------------------------------------------------------------------------------------------ provenance
BUDGET_KEYS = ("collector.total_episodes", "collector.total_frames", "n_demos", "optim.n_updates", "budget_s",
               "eval.n_tasks")


def _grouped(rows: list[Row], key: str) -> str | None:
    """``v1 (a, b), v2 (c)`` of a config key over the rows' runs; the value alone when every row has it."""
    groups: dict[str, list[str]] = {}
    having = [row for row in rows if any(get(r.config, key) is not None for r in row.runs)]
    for row in having:
        for value in dict.fromkeys(_yaml(get(r.config, key)) for r in row.runs if get(r.config, key) is not None):
            groups.setdefault(value, []).append(row.id)
    if not groups:
        return None
    if len(groups) == 1 and len(having) == len([r for r in rows if r.runs]):
        return next(iter(groups))
    return ", ".join(f"{v} ({', '.join(ids)})" for v, ids in groups.items())


def as_typed_in_checkout(command: str) -> str:
    """A recorded sweep command as a reader types it at a checkout's root.

    A sweep may have been started from another folder (a frozen copy of the repository, so
    that edits to the checkout cannot reach runs in flight) with an absolute ``results_dir``:
    the script becomes ``recipes/sweep.py`` and ``results_dir`` its path under ``results/``.

        >>> as_typed_in_checkout("python ../work/copy/recipes/sweep.py -c x results_dir=/home/u/repo/results/robots")
        'python recipes/sweep.py -c x results_dir=results/robots'
    """
    command = re.sub(r"^python \S*recipes/sweep\.py", "python recipes/sweep.py", command)
    return re.sub(r"results_dir=\S*?/(results/\S+)", r"results_dir=\1", command)


def _machine(run: Run) -> str:
    sweep = run.sweep
    threads = get(run.config, "threads")
    if sweep is None:
        return f"not recorded (not started by recipes/sweep.py), `threads={threads}`"
    m, per_run, cluster = sweep.get("machine", {}), sweep.get("resources_per_run", {}), sweep.get("ray_cluster", {})
    gpus = f", GPU {', '.join(m['gpus'])}" if m.get("gpus") else ""
    at_once = int((cluster.get("CPU") or 1) // max(per_run.get("num_cpus") or 1, 1))
    return (f"{m.get('cpu')} ({m.get('cpu_count')} CPUs{gpus}), torch {m.get('torch')}, {m.get('torch_threads')} "
            f"thread(s) per run, up to {at_once} run(s) at once")


def provenance(ctx: Context, name: str) -> list[str]:
    """Where the block's runs are, how they were made, on which machine, and the command that regenerates it."""
    rows = [row for row in ctx.rows if row.runs]
    folders = list(dict.fromkeys(row.folder for row in ctx.rows))
    sweep = f" (sweep config `{ctx.spec['sweep_config']}`)" if ctx.spec.get("sweep_config") else ""
    lines = [f"Runs: {', '.join(f'`{f}/<method>/seed<k>/`' for f in folders)}{sweep}; regenerate with "
             f"`python recipes/report.py --block {name}`.", ""]
    budget = [f"`{key}` {text}" for key in BUDGET_KEYS if (text := _grouped(rows, key)) is not None]
    if budget:
        lines += ["Budget (the runs' `config.yaml`): " + "; ".join(budget) + ".", ""]
    tasks = [f"`{key}` {text}" for key in ("eval.seed", "eval.test_seed") if (text := _grouped(rows, key))]
    if tasks:
        lines += ["Tasks: periodic evaluations on " + " and the final one on ".join(tasks) + ".", ""]
    machines: dict[str, dict[str, list[int]]] = {}
    for row in rows:
        for run in row.runs:
            machines.setdefault(_machine(run), {}).setdefault(row.id, []).append(run.seed)
    for text, ids in machines.items():
        lines += [f"Machine: {text}: " + ", ".join(f"{i} ({seeds_text(s)})" for i, s in ids.items()) + ".", ""]
    commands = sorted({as_typed_in_checkout(r.sweep["sweep_command"]) for row in rows for r in row.runs
                       if r.sweep and r.sweep.get("sweep_command")})
    if commands:
        lines += ["Made by: " + "; ".join(f"`{c}`" for c in commands) + ".", ""]
    return lines


def relpath(target: Path, page: Path) -> str:
    return os.path.relpath(target, page.parent).replace(os.sep, "/")


# ------------------------------------------------------------------------------------------ benchmarks
class Figure:
    """A benchmark figure over one or more files: formats as ``mean (std)`` over them (``.2f``, ``hms``, ``min``,
    ``,.0f``, ...), or ``—`` when a file lacks it.

    Examples:
        >>> f"{Figure([251.4, 235.2]):min}", f"{Figure([7.17]):.2f}", f"{Figure([None]):.2f}"
        ('4.1 min (0.1 min)', '7.17', '—')
    """

    def __init__(self, values: list):
        self.values = values

    def __format__(self, spec: str) -> str:
        values = [v for v in self.values if v is not None]
        if len(values) < len(self.values) or not values:
            return "—"
        if not all(isinstance(v, (int, float)) for v in values):
            return ", ".join(dict.fromkeys(map(str, values)))
        if spec == "min":
            return _minutes(values)
        fmt = hms if spec == "hms" else (lambda x: format(x, spec))
        return mean_std(values, fmt)


def _minutes(values: list[float]) -> str:
    arr = np.asarray(values, dtype=float) / 60
    return f"{arr.mean():.1f} min" if arr.size == 1 else f"{arr.mean():.1f} min ({arr.std():.1f} min)"


def benchmark_figures(files: list[Path], run: int | None = None) -> dict[str, Figure]:
    """``{key: Figure}`` over the files' runs (each file's ``run``-th, or all of them) for the templates."""
    parsed = [load.load_benchmark(f) for f in files]
    runs = [r for b in parsed for r in (b.runs if run is None else [b.runs[run]])]
    keys = dict.fromkeys(k for r in runs for k in r)
    return {k: Figure([r.get(k) for r in runs]) for k in keys}


def speed_table(spec: dict, folder: Path, page: Path) -> str:
    """One row per measure of ``spec["rows"]``: ours and its peer (templates over the files' figures), the
    machine and command the files record, the files linked."""
    rows = []
    for item in spec["rows"]:
        files = [folder / f for f in item["files"]]
        figures = benchmark_figures(files)
        peer_files = [folder / f for f in item.get("peer_files", item["files"])]
        peer = item.get("peer", "—").format(**benchmark_figures(peer_files)) if item.get("peer") else "—"
        parsed = [load.load_benchmark(f) for f in files]
        machine = "; ".join(dict.fromkeys(b.machine for b in parsed))
        commands = "; ".join(f"`{c}`" for c in dict.fromkeys(b.command for b in parsed))
        links = ", ".join(f"[{f.name}]({relpath(f, page)})" for f in dict.fromkeys(files + peer_files))
        rows.append([item["measure"], item["method"], item["ours"].format(**figures), peer, machine, commands, links])
    return table(["Measure", "Method", "Ours", "Peer", "Machine (as the file records it)", "Command", "Output"],
                 rows, ["l", "l", "r", "l", "l", "l", "l"])
