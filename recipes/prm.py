"""PRM-0.1 / PRM-1 of the paper's Table 1: OMPL's PRM plans every test task online, its path is executed.

    python recipes/prm.py                    # PRM-0.1: 0.1 s of planning per task
    python recipes/prm.py budget_s=1.0       # PRM-1
    python recipes/prm.py budget_s=1.0 eval.n_tasks=200 progress=false

Each test task of ``evaluate`` gets a fresh roadmap (the obstacle changes) and
at most ``budget_s`` of planning in the task model's configuration space; the path
runs through the same test env as the learned policies, in action-bounded steps
(``torchrl_silp.baselines.evaluate_prm``). The task model is
``UR5eReach(workspace_exit=env.workspace_exit, task_branch=env.task_branch)``.
Writes ``run_dir/summary.json``, ``history.json`` (empty: nothing is trained)
and ``config.yaml``. ``run(cfg)`` returns the summary, for sweeps that call it
in-process. Configuration: ``recipes/config/prm.yaml``. Needs OMPL
(``pip install "torchrl_silp[planning]"``).
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from torchrl_silp.baselines import evaluate_prm
from torchrl_silp.models import TASK_BRANCHES, WORKSPACE_EXIT_MODES, UR5eReach
from torchrl_silp.recipes.metrics import write_results
from torchrl_silp.recipes.start import check_device, start_run


def _check_choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")


def validate(cfg: DictConfig) -> None:
    """Reject bad configurations before any planning (errors name the field)."""
    for name, value in (("budget_s", cfg.budget_s), ("edge_step", cfg.edge_step)):
        if name == "edge_step" and value is None:  # the model's motion_resolution
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    for name, value, low in (("seed", cfg.seed, 0), ("eval.test_seed", cfg.eval.test_seed, 0), ("threads", cfg.threads, 0),
                             ("eval.n_tasks", cfg.eval.n_tasks, 1), ("env.max_steps", cfg.env.max_steps, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    for name in ("simplify", "progress"):
        if not isinstance(cfg[name], bool):
            raise ValueError(f"{name} must be true or false, got {cfg[name]!r}")
    _check_choice("env.workspace_exit", cfg.env.workspace_exit, WORKSPACE_EXIT_MODES)
    _check_choice("env.task_branch", cfg.env.task_branch, TASK_BRANCHES)
    check_device(cfg.device)


def make_model(cfg: DictConfig, device) -> UR5eReach:
    """The task model the planner plans in and the test env runs: the paper's UR5e reach task."""
    return UR5eReach(workspace_exit=cfg.env.workspace_exit, task_branch=cfg.env.task_branch, device=device)


def run(cfg: DictConfig) -> dict:
    """Plan and execute every test task, report. Returns the summary dict."""
    validate(cfg)
    device, run_dir = start_run(cfg)  # (OMPL has its own generator, seeded from cfg.seed per plan)
    model = make_model(cfg, device)
    metrics = evaluate_prm(
        model,
        cfg.budget_s,
        n_tasks=cfg.eval.n_tasks,
        seed=cfg.eval.test_seed,
        ompl_seed=cfg.seed,
        max_steps=cfg.env.max_steps,
        device=device,
        progress=cfg.progress,
        edge_step=cfg.edge_step,
        simplify=cfg.simplify,
    )
    summary = {
        "method": cfg.logger.exp_name,
        "seed": cfg.seed,
        "budget_s": float(cfg.budget_s),
        "success_rate": metrics["success_rate"],
        "test_collision_rate": metrics["collision_rate"],
        "train_wall_s": None,  # an online planner: no training
        "rollout_time_per_episode_s": metrics["time_per_rollout_s"],  # planning + execution, per task
        "planning_time_s": metrics["planning_time_s"],
        "planning_time_max_s": metrics["planning_time_max_s"],
        "execution_time_per_episode_s": metrics["execution_time_per_rollout_s"],
        "solved_rate": metrics["solved_rate"],
        "path_steps_mean": metrics["path_steps_mean"],
        "mean_steps": metrics["mean_steps"],
        "n_tasks": metrics["n_tasks"],
        "episodes": 0,
        "frames": 0,
    }
    write_results(run_dir, summary, history=[])  # an online planner has no learning curve
    return summary


@hydra.main(version_base="1.3", config_path="config", config_name="prm")
def main(cfg: DictConfig):
    return run(cfg)


if __name__ == "__main__":
    main()
