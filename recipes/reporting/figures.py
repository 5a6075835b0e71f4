"""Curves -> PNG: the learning curves, the BC filter's share and the collision model's ROC.

Each function takes what it plots and the path to write; the text that links a figure never
depends on the drawing, so ``--check`` compares pages without drawing anything.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from .load import Run


def mean_std_curve(histories: list[list[dict]], key: str = "success_rate") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``key`` against training episodes, mean and std over the seeds at common points.

    Seeds evaluated at the same episodes are averaged there; otherwise each seed is interpolated
    (linearly, in episodes) onto the union of all the seeds' points inside the range every seed covers.

    Examples:
        >>> a = [{"episodes": 10, "success_rate": 0.2}, {"episodes": 20, "success_rate": 0.6}]
        >>> b = [{"episodes": 10, "success_rate": 0.4}, {"episodes": 20, "success_rate": 0.8}]
        >>> x, mean, std = mean_std_curve([a, b])
        >>> x.tolist(), mean.round(3).tolist(), std.round(3).tolist()
        ([10.0, 20.0], [0.3, 0.7], [0.1, 0.1])
    """
    series = []
    for history in histories:
        points = sorted((p["episodes"], p[key]) for p in history if p.get("episodes") is not None and p.get(key) is not None)
        if points:
            series.append(np.asarray(points, dtype=float).T)
    if not series:
        raise ValueError(f"no history point holds both episodes and {key}")
    if all(len(x) == len(series[0][0]) and np.array_equal(x, series[0][0]) for x, _ in series):
        grid, ys = series[0][0], np.stack([y for _, y in series])
    else:
        lo, hi = max(x[0] for x, _ in series), min(x[-1] for x, _ in series)
        grid = np.unique(np.concatenate([x for x, _ in series]))
        grid = grid[(grid >= lo) & (grid <= hi)]
        ys = np.stack([np.interp(grid, x, y) for x, y in series])
    return grid, ys.mean(0), ys.std(0)


def curves_of(groups: dict[str, list[Run]], key: str = "success_rate") -> dict[str, tuple]:
    """The groups that have a curve of ``key`` (a planner's runs have none), with it."""
    out = {}
    for label, runs in groups.items():
        with contextlib.suppress(ValueError):
            out[label] = (mean_std_curve([r.history for r in runs], key), len(runs))
    return out


def _axes():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt, *plt.subplots(figsize=(8, 5))


def _save(plt, fig, ax, path: Path, legend: str) -> None:
    ax.grid(alpha=0.3)
    ax.legend(loc=legend, fontsize="small")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_curves(groups: dict[str, list[Run]], path: Path, key: str = "success_rate",
                ylabel: str = "success rate (periodic evaluations)") -> list[str]:
    """Mean ± std over seeds of ``key`` against training episodes, one line per group; returns the groups drawn."""
    curves = curves_of(groups, key)
    if not curves:
        return []
    plt, fig, ax = _axes()
    for label, ((x, mean, std), n) in curves.items():
        (line,) = ax.plot(x, mean, marker="." if len(x) < 30 else None, label=f"{label.strip('`')} ({n} seed{'s' if n > 1 else ''})")
        ax.fill_between(x, np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1), color=line.get_color(), alpha=0.2)
    ax.set_xlabel("training episodes")
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 1.02)
    ax.secondary_xaxis("top", functions=(lambda e: e / 10, lambda p: p * 10)).set_xlabel("paper's epochs (10 episodes)")
    _save(plt, fig, ax, path, "lower right" if key == "success_rate" else "upper right")
    return list(curves)


def roc_figure(nets: list[dict], path: Path) -> None:
    """The ROC of each collision model on its test split."""
    plt, fig, ax = _axes()
    for net in nets:
        roc = net["roc"]
        ax.plot(roc["fpr"], roc["tpr"], label=f"labels: {net['labeller']} (AUC {roc['auc']:.4f})")
    ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--")
    ax.set_xlabel("false positive rate (1 - specificity)")
    ax.set_ylabel("true positive rate (recall)")
    ax.set_title("ROC of the collision model on its test split")
    _save(plt, fig, ax, path, "lower right")
