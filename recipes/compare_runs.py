"""Compare finished training runs: learning curves (mean ± std over seeds) in one PNG and a table.

Each group is a label and a glob of run directories (the ``run_dir`` of
``sac_silp.py`` / ``ddpg_silp.py``, each holding ``summary.json`` and
``history.json``)::

    python recipes/compare_runs.py \\
        --group "SAC-SILP+ extended=runs/sac_silp_plus_ext/seed*" --group "SAC=runs/sac/seed*" \\
        --png docs/sac_vs_sac_silp.png --markdown sac_vs_sac_silp.md

The curves are test success rate against training episodes; seeds are put on
a common episode grid by linear interpolation (each seed only up to its own
last evaluation), then averaged. The table gives mean (std) over the seeds of
the final success rate, training wall time, time to first reach 0.95,
planner share, collisions during training and rollout time per episode.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import sys
from pathlib import Path

import numpy as np


def parse_group(text: str) -> tuple[str, list[Path]]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"--group must be LABEL=GLOB, got {text!r}")
    # the last "=": labels may hold config overrides (key=value), run paths seldom do
    label, _, pattern = text.rpartition("=")
    runs = sorted(Path(p) for p in glob.glob(pattern) if (Path(p) / "summary.json").exists())
    return label, runs


def load_run(run: Path) -> tuple[dict, list[dict]]:
    summary = json.loads((run / "summary.json").read_text())
    history = json.loads((run / "history.json").read_text())["history"]
    return summary, history


def mean_std(values: list[float]) -> str:
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not values:
        return "—"
    arr = np.asarray(values, dtype=float)
    return f"{arr.mean():.3f} ({arr.std():.3f})" if len(arr) > 1 else f"{arr[0]:.3f}"


def curve(histories: list[list[dict]], points: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and std of success vs episodes over seeds, on a grid up to the shortest run's end."""
    end = min(h[-1]["episodes"] for h in histories)
    grid = np.linspace(0, end, points)
    ys = []
    for h in histories:
        x = np.asarray([0] + [p["episodes"] for p in h], dtype=float)
        y = np.asarray([0.0] + [p["success_rate"] for p in h], dtype=float)
        ys.append(np.interp(grid, x, y))
    ys = np.stack(ys)
    return grid, ys.mean(0), ys.std(0)


def table(groups: dict[str, list[tuple[dict, list[dict]]]]) -> str:
    rows = [
        "| method | seeds | success rate | train wall (min) | to 0.95 (min) | planner share | collisions in training | rollout / episode (ms) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, runs in groups.items():
        s = [r[0] for r in runs]
        to_095 = [x["time_to_095_s"] / 60 if x["time_to_095_s"] is not None else None for x in s]
        reached = sum(v is not None for v in to_095)
        rows.append(
            f"| {label} | {len(s)} | {mean_std([x['success_rate'] for x in s])} "
            f"| {mean_std([x['train_wall_s'] / 60 for x in s])} "
            f"| {mean_std(to_095)}{'' if reached == len(s) else f' ({reached}/{len(s)} reached)'} "
            f"| {mean_std([x['planning_share'] for x in s])} "
            f"| {mean_std([x['collisions_during_training'] for x in s])} "
            f"| {mean_std([x['rollout_time_per_episode_s'] * 1e3 for x in s])} |"
        )
    return "\n".join(rows)


def plot(groups: dict[str, list[tuple[dict, list[dict]]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, runs in groups.items():
        grid, mean, std = curve([r[1] for r in runs])
        ax.plot(grid, mean, label=f"{label} ({len(runs)} seed{'s' if len(runs) > 1 else ''})")
        ax.fill_between(grid, np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1), alpha=0.2)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("success rate on the 1000 test tasks")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--group", type=parse_group, action="append", required=True, help="LABEL=GLOB of run dirs")
    parser.add_argument("--png", type=Path, default=None, help="write the learning curves here")
    parser.add_argument("--markdown", type=Path, default=None, help="write the table here")
    args = parser.parse_args(argv)
    groups = {}
    for label, runs in args.group:
        if not runs:
            parser.error(f"--group {label}: no run directory with a summary.json matches")
        groups[label] = [load_run(r) for r in runs]
    text = table(groups)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.png:
        plot(groups, args.png)
        print(f"wrote {args.png}")
    return text


if __name__ == "__main__":
    sys.exit(main() and 0)
