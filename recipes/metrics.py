"""What a training run counts, shows, logs and leaves behind.

The loop's counters (:func:`new_counters`, :func:`count_batch`, :func:`add_bc_filter_share`), its
progress bar (:class:`Progress`), its periodic evaluations (:func:`evaluate_run`), the metrics it logs
after each collector batch (``train/…``, ``eval/…``, ``time/…``: :func:`batch_metrics`,
:func:`log_metrics`), and the files a sweep and its report read: ``summary.json``
(:func:`summarize`), ``history.json`` and the learning curve.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import torch
import tqdm
from omegaconf import OmegaConf
from torchrl.envs.utils import ExplorationType
from torchrl.record.loggers import get_logger

from torchrl_silp.eval import evaluate
from torchrl_silp.recipes.builders import make_observation_transform


def new_counters() -> dict:
    """The loop's counters at the start of a run (a resumed run restores its own)."""
    return {"frames": 0, "episodes": 0, "iterations": 0, "updates": 0, "collisions": 0, "swept_collisions": 0,
            "train_wall_s": 0.0, "planning_s": 0.0, "time_to_095_s": None, "evaluations": 0,
            # gradient updates of the last batch a stop cut short: made first on resume
            "updates_owed": 0,
            # the BC filter's kept share of demo rows, summed over the updates since the last evaluation point
            "bc_kept_sum": 0.0, "bc_kept_updates": 0}


def count_batch(counters: dict, batch) -> int:
    """Add a collector batch to the counters; returns the episodes it ended."""
    episodes_done = int(batch["next", "done"].sum())
    counters["iterations"] += 1
    counters["frames"] += batch.numel()
    counters["episodes"] += episodes_done
    counters["collisions"] += int(batch["next", "collision"].sum())
    counters["swept_collisions"] += int(batch["next", "swept_collision"].sum())
    return episodes_done


def add_bc_filter_share(counters: dict, losses: list) -> None:
    """Add the BC filter's kept share of demo rows, over the updates whose batch held demos (Fig. 7)."""
    if not losses or "bc_filter_fraction" not in losses[0].keys():
        return
    with_demos = torch.stack([td["num_demos"] for td in losses]) > 0
    kept = torch.stack([td["bc_filter_fraction"] for td in losses])[with_demos]
    counters["bc_kept_sum"] += kept.sum().item()
    counters["bc_kept_updates"] += kept.numel()


class Progress:
    """The run's progress bar: frames (episodes, with an episode budget), and beside it the phase, the
    updates, the last validation success and the demonstrations stored (the ETA is tqdm's recent rate)."""

    def __init__(self, cfg, counters: dict, history: list[dict], demos_stored: int):
        total_episodes = cfg.collector.total_episodes
        self.counters = counters
        if total_episodes is None:
            self.bar = tqdm.tqdm(total=cfg.collector.total_frames, initial=counters["frames"], unit="frame",
                                 disable=not cfg.progress)
        else:
            self.bar = tqdm.tqdm(total=total_episodes, initial=min(counters["episodes"], total_episodes),
                                 unit="episode", disable=not cfg.progress)
        warming_up = counters["frames"] < cfg.collector.init_random_frames
        self.status = {"phase": "random actions" if warming_up else "training"}
        if history:  # a resumed run shows what its last evaluation showed
            self.status.update(success=f"{history[-1]['success_rate']:.3f}", demos=demos_stored)

    def show(self, **fields) -> None:
        self.status.update(fields, updates=f"{self.counters['updates']:,}")
        self.bar.set_postfix(self.status, refresh=True)


def evaluate_run(cfg, model, policies, device, counters: dict, history: list[dict], run_dir: Path,
                 seed: int | None = None, return_rollout: bool = False, closing: bool = False):
    """Evaluate the run's policy on ``cfg.eval.n_tasks`` tasks (``seed``: the validation tasks by default).

    ``policies`` is ``(evaluated, actor, averaged)``: the evaluated policy, and with an averaged actor
    the online one too (``online_success_rate``). ``closing``: the run's closing test figures also split the
    success by the straight path (``evaluate``'s ``split_by_straight_path``) and evaluate a SAC policy as it
    acts in training, its actions sampled (``sampling_success_rate``). On the validation tasks the result is a point of
    ``history`` (with the BC filter's kept share since the last point) and of the learning curve, and
    sets ``time_to_095_s`` the first time it reaches 0.95. Returns the metrics (and the rollout).

    Why inline, not TorchRL's :class:`~torchrl.collectors.Evaluator` (run aside by ``trigger_eval``/``poll``):
    the loop uses this figure in the same batch (the history point, ``stop_at_success``, ``time_to_095_s``,
    the checkpoint; ``Evaluator.state_dict`` refuses while an evaluation is pending). And ``Evaluator`` reports
    reward and episode length of the first ``num_trajectories`` episodes to finish in an env it keeps and resets,
    not success and collision rates of one deterministic episode on each fixed task of ``seed``.
    """
    evaluated, actor, averaged = policies
    seed = cfg.eval.seed if seed is None else seed
    kwargs = dict(n_tasks=cfg.eval.n_tasks, seed=seed, model=model, max_steps=cfg.env.max_steps,
                  observation_transform=make_observation_transform(cfg, model), device=device)
    metrics, rollout = evaluate(evaluated, return_rollout=True, split_by_straight_path=closing, **kwargs)
    if averaged is not None:
        metrics["online_success_rate"] = evaluate(actor, **kwargs)["success_rate"]
    if closing and cfg.algorithm == "sac":
        metrics["sampling_success_rate"] = evaluate(evaluated, exploration_type=ExplorationType.RANDOM,
                                                    **kwargs)["success_rate"]
    if seed != cfg.eval.seed:  # the test tasks' figure: not a point of the validation curve
        return (metrics, rollout) if return_rollout else metrics
    point = {"frames": counters["frames"], "episodes": counters["episodes"],
             "train_wall_s": counters["train_wall_s"], "collisions": counters["collisions"], **metrics}
    if counters["bc_kept_updates"]:  # the share of demo actions the BC filter kept since the last point (Fig. 7)
        point["bc_filter_fraction"] = counters["bc_kept_sum"] / counters["bc_kept_updates"]
    counters["bc_kept_sum"], counters["bc_kept_updates"] = 0.0, 0
    if not history or history[-1]["frames"] != counters["frames"]:
        history.append(point)
    if counters["time_to_095_s"] is None and metrics["success_rate"] >= 0.95:
        counters["time_to_095_s"] = counters["train_wall_s"]
    plot_learning_curve(history, run_dir / "learning_curve.png", label=cfg.logger.exp_name)
    return (metrics, rollout) if return_rollout else metrics


def final_evaluation(cfg, counters: dict, history: list[dict], evaluate_now):
    """The run's closing figures: ``(test, validation, rollout)``. The test tasks (``cfg.eval.test_seed``) are
    read once, here (a SAC policy also with sampled actions); the validation figure is the last point of
    ``history`` when the last batch just made it, else evaluated now. With one set of tasks for both
    (``test_seed == seed``) it is evaluated once. ``evaluate_now``: the run's :func:`evaluate_run`."""
    if cfg.eval.test_seed == cfg.eval.seed:
        final, rollout = evaluate_now(return_rollout=True, closing=True)
        return final, final, rollout
    validation = history[-1] if history and history[-1]["frames"] == counters["frames"] else evaluate_now()
    final, rollout = evaluate_now(cfg.eval.test_seed, return_rollout=True, closing=True)
    return final, validation, rollout


def make_run_logger(cfg, run_dir: Path, state_dict: dict | None, log_hparams: bool):
    """The run's TorchRL logger (``cfg.logger.backend``; None without one), writing under ``run_dir / "logs"``
    and continuing from a checkpoint's ``state_dict``; ``log_hparams``: record the config (a fresh run)."""
    if not cfg.logger.backend:
        return None
    logger = get_logger(cfg.logger.backend, logger_name=str(run_dir / "logs"),
                        experiment_name=cfg.logger.exp_name, state_dict=state_dict)
    if log_hparams:
        logger.log_hparams(OmegaConf.to_container(cfg, resolve=True))
    return logger


def log_metrics(logger, metrics: dict, step: int) -> None:
    """Log each metric as a scalar at ``step`` (no logger: nothing; None and NaN are skipped)."""
    if logger is None:
        return
    for name, value in metrics.items():
        if isinstance(value, torch.Tensor):
            value = value.item()
        if value is None or (isinstance(value, float) and math.isnan(value)):
            continue
        logger.log_scalar(name, value, step)


def batch_metrics(batch, losses: list, counters: dict, demos_stored: int) -> dict:
    """What the loop logs after a collector batch: the counters, the episodes it ended, the mean losses."""
    metrics = {"train/collisions": counters["collisions"], "train/swept_collisions": counters["swept_collisions"],
               "train/episodes": counters["episodes"], "train/demos": demos_stored,
               "time/train_wall_s": counters["train_wall_s"]}
    ended = batch["next", "done"]
    if ended.any():
        metrics["train/episode_reward"] = batch["next", "episode_reward"][ended].mean().item()
        metrics["train/success_rate"] = batch["next", "success"][ended].float().mean().item()
    if losses:
        for key, value in torch.stack(losses).items():
            if key.startswith("loss_") or key in ("alpha", "bc_filter_fraction", "bc_mse"):
                metrics[f"train/{key}"] = value.float().mean().item()
    return metrics


def plot_learning_curve(history: list[dict], path: Path, label: str) -> Path:
    """The validation success rate of each periodic evaluation against training episodes (redrawn at each one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    if history:
        ax.plot([h["episodes"] for h in history], [h["success_rate"] for h in history], marker="o", label=label)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("validation success rate")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    tmp = Path(path).with_name(Path(path).stem + ".tmp.png")
    fig.savefig(tmp, dpi=120)  # then renamed: a reader never sees half a picture
    plt.close(fig)
    os.replace(tmp, path)
    return path


def summarize(cfg, counters: dict, final: dict, demos_stored: int, validation: dict | None = None) -> dict:
    """The run's ``summary.json``: the method, the final test evaluation (and the validation one) and the counters."""
    return {
        "method": cfg.logger.exp_name, "env": cfg.env.name, "algorithm": cfg.algorithm, "silp_bc": cfg.silp.bc,
        "silp_demos": cfg.silp.demos, "her": cfg.replay_buffer.her, "exploration": cfg.exploration.mode,
        "seed": cfg.seed, "success_rate": final["success_rate"], "test_seed": cfg.eval.test_seed,
        "validation_success_rate": None if validation is None else validation["success_rate"],
        "validation_seed": cfg.eval.seed,
        "online_success_rate": final.get("online_success_rate", final["success_rate"]),
        "evaluated_actor": "online" if cfg.eval.actor_average_decay is None
        else f"average (decay {cfg.eval.actor_average_decay})",
        "test_collision_rate": final["collision_rate"],
        # the test tasks split by whether the straight joint path to the goal solves them (evaluate's split)
        "test_free_task_share": final.get("free_task_share"), "test_free_success_rate": final.get("free_success_rate"),
        "test_blocked_success_rate": final.get("blocked_success_rate"),
        "sampling_success_rate": final.get("sampling_success_rate"),  # SAC: the test tasks with sampled actions
        "collisions_during_training": counters["collisions"],
        # collisions of a motion whose reached state is free: what a check of the reached state alone let pass
        "swept_collisions_during_training": counters.get("swept_collisions", 0),
        "episodes": counters["episodes"], "frames": counters["frames"], "updates": counters["updates"],
        "train_wall_s": counters["train_wall_s"], "planning_s": counters["planning_s"],
        "planning_share": counters["planning_s"] / max(counters["train_wall_s"], 1e-9),
        "time_to_095_s": counters["time_to_095_s"], "rollout_time_per_episode_s": final["time_per_rollout_s"],
        "demos_stored": demos_stored,
        "warning": training_warning(cfg, counters, demos_stored),
    }


def training_warning(cfg, counters: dict, demos_stored: int) -> str | None:
    """What the run did not train or measure, in words, or None: no gradient update at all (the budget ended
    in the random warm-up), SILP+ with no demonstration stored (it ran as plain RL), no periodic evaluation."""
    problems = []
    if counters["updates"] == 0:
        problems.append(f"no gradient update was made: the policy is untrained (the run ended at {counters['frames']} "
                        f"frames, within collector.init_random_frames={cfg.collector.init_random_frames})")
    if cfg.silp.demos and not demos_stored:
        problems.append("silp.demos is on but no demonstration was stored: SILP+ ran as plain RL")
    if counters["updates"] and not counters.get("evaluations", 1):
        problems.append(f"no periodic evaluation ran (eval.every_frames={cfg.eval.every_frames} is past the budget): "
                        "the learning curve holds the final evaluation only")
    return "; ".join(problems) or None


def _strict(value):
    """``value`` with NaN and infinities as None, tensors and numpy scalars as floats: JSON without NaN."""
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(v) for v in value]
    if isinstance(value, torch.Tensor) or type(value).__module__ == "numpy":
        value = value.item() if hasattr(value, "item") else float(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: Path, payload: dict) -> None:
    """``payload`` as indented, strict JSON (NaN as ``null``; tensors and numpy scalars as numbers), written atomically."""
    tmp = Path(path).with_name(Path(path).name + ".tmp")
    tmp.write_text(json.dumps(_strict(payload), indent=2, allow_nan=False))
    os.replace(tmp, path)


def write_results(run_dir: Path, summary: dict, history: list[dict]) -> None:
    """What every recipe leaves for a sweep and its report: ``summary.json`` and ``history.json``; prints the summary."""
    write_json(Path(run_dir) / "summary.json", summary)
    write_json(Path(run_dir) / "history.json", {"history": history})
    print("\n".join(f"{k:>30s}: {v}" for k, v in summary.items()))


def truncate_logs(log_dir: Path, last_step: int) -> int:
    """Drop the rows of a run's CSV scalar logs written after step ``last_step``; returns how many.

    A resumed run redoes the steps after its checkpoint (and a run started afresh in the
    same ``run_dir`` all of them): their first rows go, so that no step appears twice.
    TorchRL's ``CSVLogger`` appends ``step,value`` rows to ``<name>.csv``.
    """
    dropped = 0
    for path in sorted(Path(log_dir).rglob("*.csv")):
        rows = path.read_text().splitlines(keepends=True)
        kept = [row for row in rows if int(float(row.split(",", 1)[0])) <= last_step]
        if len(kept) != len(rows):
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text("".join(kept))
            os.replace(tmp, path)
            dropped += len(rows) - len(kept)
    return dropped
