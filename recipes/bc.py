"""Behaviour-cloning baselines of the paper's Table 1: BC-SAC-SILP+ and BC-PRM.

    python recipes/bc.py source_run_dir=results/table1/sac_silp_plus/seed0 logger.exp_name=bc_sac_silp_plus
    python recipes/bc.py source=prm logger.exp_name=bc_prm
    python recipes/bc.py source=prm resume=true   # continue a killed run; demonstrations are not collected again

``n_demos`` demonstration episodes are collected on training tasks (seeded by
``seed``, never the test seed), from a trained run's evaluated actor rolled out
deterministically (``source=policy``) or from OMPL's PRM (``source=prm``); the
transitions of the successful episodes are kept and cached in
``run_dir/demos.pt``. The recipes' deterministic tanh actor is then fitted to
their actions with TorchRL's ``BCLoss`` and evaluated on the fixed test tasks
of ``evaluate``. The training wall time counted is collection plus fitting.

``BCLoss`` is used on the deterministic actor with ``loss_function="l2"``
(mean squared error to the demonstrated actions). On the SAC TanhNormal actor
it would fit the negative log-likelihood of those actions instead, which is
unbounded for actions on the edge of the box (clipped planner steps, saturated
policy actions at +-1); and the policy is deterministic at test time anyway.

Writes ``run_dir/summary.json``, ``history.json`` (the periodic evaluations),
``config.yaml`` and ``checkpoint/state.pt``. ``run(cfg)`` returns the summary,
for sweeps that call it in-process. Configuration: ``recipes/config/bc.yaml``.
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torch import optim
from torchrl.objectives import BCLoss

sys.path.insert(0, str(Path(__file__).parent))
from utils import (  # noqa: E402
    check_choice,
    check_device,
    checkpoint_exists,
    load_trained_networks,
    make_actor_critic,
    make_env,
    start_run,
    write_results,
)

from torchrl_silp import UR5eReachEnv  # noqa: E402
from torchrl_silp.envs.reach import TASK_BRANCHES, WORKSPACE_EXIT_MODES  # noqa: E402
from torchrl_silp.eval import episode_outcomes, evaluate  # noqa: E402

SOURCES = ("policy", "prm")
# what a demonstration transition holds, whichever its source (the PRM collector's keys)
DEMO_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
             ("next", "terminated"), "episode")
COLLECT_BATCH = 1000  # source=policy: training tasks rolled out at once


# ---------------------------------------------------------------- validation
def _positive_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def validate(cfg: DictConfig) -> None:
    """Reject bad configurations before any work is done (errors name the field)."""
    check_choice("source", cfg.source, SOURCES)
    positive = {
        "n_demos": cfg.n_demos,
        "env.max_steps": cfg.env.max_steps,
        "optim.batch_size": cfg.optim.batch_size,
        "optim.n_updates": cfg.optim.n_updates,
        "eval.n_tasks": cfg.eval.n_tasks,
        "eval.every_updates": cfg.eval.every_updates,
        "checkpoint.every_updates": cfg.checkpoint.every_updates,
    }
    for name, value in positive.items():
        if not _positive_int(value):
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    for name, value in (("seed", cfg.seed), ("eval.seed", cfg.eval.seed), ("threads", cfg.threads)):
        if not isinstance(value, int) or isinstance(value, bool) or (name == "threads" and value < 0):
            raise ValueError(f"{name} must be {'a non-negative' if name == 'threads' else 'an'} int, got {value!r}")
    for name, value in (("optim.lr", cfg.optim.lr), ("prm_budget_s", cfg.prm_budget_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    sizes = cfg.network.hidden_sizes
    if not OmegaConf.is_list(sizes) or not len(sizes) or not all(_positive_int(s) for s in sizes):
        raise ValueError(f"network.hidden_sizes must be a non-empty list of positive ints, got {sizes!r}")
    check_choice("env.workspace_exit", cfg.env.workspace_exit, WORKSPACE_EXIT_MODES)
    check_choice("env.task_branch", cfg.env.task_branch, TASK_BRANCHES)
    check_device(cfg.device)
    if cfg.source == "policy":
        src = cfg.source_run_dir
        if not src:
            raise ValueError("source_run_dir must name a finished training run dir when source=policy, got null")
        src = Path(src)
        if not src.is_dir():
            raise ValueError(f"source_run_dir {str(src)!r} is not a directory")
        if not (src / "config.yaml").is_file():
            raise ValueError(f"source_run_dir {str(src)!r} holds no config.yaml (the run's resolved config)")
        if not checkpoint_exists(src / "checkpoint"):
            raise ValueError(f"source_run_dir {str(src)!r} holds no checkpoint (expected checkpoint/state.pt)")


# -------------------------------------------------------------- demonstrations
def load_source_policy(run_dir: Path, device) -> torch.nn.Module:
    """A finished training run's evaluated actor (the averaged one if the run kept it), from its config and checkpoint."""
    run_dir = Path(run_dir)
    source_cfg = OmegaConf.load(run_dir / "config.yaml")
    env = make_env(source_cfg, device, seed=0)  # only its specs and model: no task is drawn from it
    actor, _, _ = load_trained_networks(source_cfg, env, run_dir / "checkpoint", device)
    return actor


@torch.no_grad()
def collect_policy_demonstrations(
    policy,
    n_episodes: int,
    *,
    seed: int = 0,
    max_steps: int = 50,
    workspace_exit: str = "collision",
    task_branch: str = "front",
    device=None,
    progress: bool = False,
) -> tuple[TensorDictBase, dict]:
    """Roll ``policy`` out deterministically on ``n_episodes`` training tasks; keep its successful episodes.

    The tasks are those a batched ``UR5eReachEnv(seed=seed, collision_type=0)``
    draws, ``COLLECT_BATCH`` at a time, as ``evaluate`` rolls a policy out on
    the test tasks. Returns a flat TensorDict of the transitions of the
    successful episodes (``DEMO_KEYS``, in time order per episode; ``"episode"``
    is the episode's index among the ``n_episodes`` attempted) and the stats
    ``n_attempted``, ``n_kept``, ``n_transitions``, ``success_rate``.
    """
    batch = min(n_episodes, COLLECT_BATCH)
    env = UR5eReachEnv(num_envs=batch, seed=seed, collision_type=0, max_steps=max_steps,
                       workspace_exit=workspace_exit, task_branch=task_branch, device=device)
    kept, attempted, n_kept = [], 0, 0
    with tqdm.tqdm(total=n_episodes, disable=not progress, desc="demonstrations") as pbar:
        while attempted < n_episodes:
            _, rollout = evaluate(policy, env=env, return_rollout=True)
            alive, success, _ = episode_outcomes(rollout)
            take = min(batch, n_episodes - attempted)
            success[take:] = False  # the last batch may hold more tasks than are still wanted
            episode = torch.arange(attempted, attempted + batch, device=rollout.device)
            rollout.set("episode", episode.unsqueeze(-1).expand(rollout.batch_size))
            kept.append(rollout[alive & success.unsqueeze(-1)].select(*DEMO_KEYS))
            attempted += take
            n_kept += int(success.sum())
            pbar.update(take)
    demos = torch.cat(kept)
    stats = {"n_attempted": attempted, "n_kept": n_kept, "n_transitions": demos.shape[0],
             "success_rate": n_kept / attempted}
    return demos, stats


def collect_demonstrations(cfg: DictConfig, device) -> tuple[TensorDictBase, dict]:
    """The demonstrations of ``cfg.source``: a flat TensorDict of successful transitions, and stats."""
    common = dict(seed=cfg.seed, max_steps=cfg.env.max_steps, workspace_exit=cfg.env.workspace_exit,
                  task_branch=cfg.env.task_branch, device=device, progress=cfg.progress)
    if cfg.source == "policy":
        policy = load_source_policy(Path(cfg.source_run_dir), device)
        return collect_policy_demonstrations(policy, cfg.n_demos, **common)
    from torchrl_silp.baselines.prm import collect_prm_demonstrations  # OMPL: only for this source

    demos, stats = collect_prm_demonstrations(cfg.n_demos, budget_s=cfg.prm_budget_s, **common)
    demos = demos.select(*DEMO_KEYS).to(device)
    n_kept = int(demos["episode"].unique().numel())
    return demos, {**stats, "n_attempted": cfg.n_demos, "n_kept": n_kept, "n_transitions": demos.shape[0],
                   "success_rate": n_kept / cfg.n_demos}


def _collection_settings(cfg: DictConfig) -> dict:
    """What the cached demonstrations depend on: a resumed run must ask for the same."""
    out = {"source": cfg.source, "n_demos": cfg.n_demos, "seed": cfg.seed,
           "env": OmegaConf.to_container(cfg.env, resolve=True)}
    if cfg.source == "policy":
        out["source_run_dir"] = str(Path(cfg.source_run_dir).resolve())
    else:
        out["prm_budget_s"] = float(cfg.prm_budget_s)
    return out


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def demonstrations(cfg: DictConfig, run_dir: Path, device) -> dict:
    """Cached demonstrations of a resumed run, else collected now and cached in ``run_dir/demos.pt``."""
    path = run_dir / "demos.pt"
    settings = _collection_settings(cfg)
    if cfg.resume and path.exists():
        cache = torch.load(path, map_location=device, weights_only=False)
        if cache["settings"] != settings:
            differ = sorted(k for k in settings if cache["settings"].get(k) != settings[k])
            raise ValueError(f"the demonstrations cached in {path} were collected with other {differ}: "
                             f"{ {k: cache['settings'].get(k) for k in differ} }; resume with those or resume=false")
        print(f"demonstrations: {cache['stats']['n_kept']} episodes from the cache {path}")
        return cache
    start = time.perf_counter()
    demos, stats = collect_demonstrations(cfg, device)
    cache = {"settings": settings, "demos": demos, "stats": stats,
             "collection_wall_s": time.perf_counter() - start}
    _save_atomic(cache, path)
    return cache


# ----------------------------------------------------------------- BC policy
def make_bc_actor(cfg: DictConfig, device) -> torch.nn.Module:
    """The BC policy: the recipes' deterministic tanh actor (that of DDPG/TD3) on ``cfg.network``."""
    net_cfg = OmegaConf.create({
        "algorithm": "ddpg",
        "network": {"hidden_sizes": list(cfg.network.hidden_sizes), "goal_relative": bool(cfg.network.goal_relative),
                    "next_tcp_feature": False},
    })
    env = UR5eReachEnv(num_envs=1, device=device)  # specs only
    actor, _ = make_actor_critic(net_cfg, env, device)  # the Q-network is left unused
    return actor


def make_bc_loss(actor) -> BCLoss:
    with warnings.catch_warnings():
        # BCLoss sets an unannotated target-parameter attribute it never uses
        warnings.filterwarnings("ignore", message=".*target_actor_network_params.*")
        return BCLoss(actor, loss_function="l2")


# ----------------------------------------------------------------------- run
def run(cfg: DictConfig) -> dict:
    """Collect (or load) the demonstrations, fit the BC policy, evaluate, checkpoint, report. Returns the summary."""
    validate(cfg)
    device, run_dir = start_run(cfg)
    ckpt = run_dir / "checkpoint" / "state.pt"

    cache = demonstrations(cfg, run_dir, device)
    demos, stats, collection_wall_s = cache["demos"], cache["stats"], cache["collection_wall_s"]
    if not demos.shape[0]:  # (a TensorDict's numel() is never below 1)
        raise RuntimeError(f"none of the {stats['n_attempted']} demonstration episodes succeeded: nothing to clone")
    data = demos.select("observation", "action").to(device)

    actor = make_bc_actor(cfg, device)
    loss = make_bc_loss(actor)
    optimizer = optim.Adam(loss.parameters(), lr=cfg.optim.lr)
    sampler = torch.Generator().manual_seed(cfg.seed)  # minibatch indices, on the CPU on every device
    counters = {"updates": 0, "bc_wall_s": 0.0}
    history: list[dict] = []
    if cfg.resume and ckpt.exists():
        state = torch.load(ckpt, map_location=device, weights_only=False)
        loss.load_state_dict(state["loss"])
        optimizer.load_state_dict(state["optimizer"])
        counters, history = state["counters"], state["history"]
        sampler.set_state(state["sampler_rng"])
        torch.set_rng_state(state["torch_rng"])
        print(f"resumed from {ckpt}: {counters['updates']} updates")

    def save():
        ckpt.parent.mkdir(exist_ok=True)
        _save_atomic({"loss": loss.state_dict(), "optimizer": optimizer.state_dict(), "counters": dict(counters),
                      "history": list(history), "sampler_rng": sampler.get_state(),
                      "torch_rng": torch.get_rng_state()}, ckpt)

    def record(bc_loss: float | None) -> dict:
        metrics = evaluate(actor, n_tasks=cfg.eval.n_tasks, seed=cfg.eval.seed, max_steps=cfg.env.max_steps,
                           workspace_exit=cfg.env.workspace_exit, task_branch=cfg.env.task_branch, device=device)
        point = {"updates": counters["updates"], "train_wall_s": collection_wall_s + counters["bc_wall_s"],
                 "bc_wall_s": counters["bc_wall_s"], "bc_loss": bc_loss, **metrics}
        history.append(point)
        return point

    n = data.shape[0]
    pbar = tqdm.tqdm(total=cfg.optim.n_updates, initial=counters["updates"], disable=not cfg.progress, desc="BC")
    loss_sum, loss_count = torch.zeros((), device=device), 0
    tick = time.perf_counter()
    while counters["updates"] < cfg.optim.n_updates:
        idx = torch.randint(n, (cfg.optim.batch_size,), generator=sampler).to(device)
        value = loss(data[idx])["loss_bc"]
        value.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        loss_sum += value.detach()
        loss_count += 1
        counters["updates"] += 1
        pbar.update(1)
        at_eval = counters["updates"] % cfg.eval.every_updates == 0 or counters["updates"] == cfg.optim.n_updates
        at_save = counters["updates"] % cfg.checkpoint.every_updates == 0
        if at_eval or at_save:
            counters["bc_wall_s"] += time.perf_counter() - tick  # evaluations and saving are not training
            if at_eval:
                point = record((loss_sum / loss_count).item())
                loss_sum, loss_count = torch.zeros((), device=device), 0
                pbar.set_postfix(success=f"{point['success_rate']:.3f}", bc_loss=f"{point['bc_loss']:.4f}")
            save()
            tick = time.perf_counter()
    pbar.close()
    if not history or history[-1]["updates"] != counters["updates"]:
        record(None)
        save()
    final = history[-1]

    summary = {
        "method": cfg.logger.exp_name,
        "seed": cfg.seed,
        "source": cfg.source,
        "source_run_dir": str(cfg.source_run_dir) if cfg.source == "policy" else None,
        "prm_budget_s": float(cfg.prm_budget_s) if cfg.source == "prm" else None,
        "success_rate": final["success_rate"],
        "test_collision_rate": final["collision_rate"],
        "mean_steps": final["mean_steps"],
        "train_wall_s": collection_wall_s + counters["bc_wall_s"],
        "collection_wall_s": collection_wall_s,
        "bc_wall_s": counters["bc_wall_s"],
        "rollout_time_per_episode_s": final["time_per_rollout_s"],
        "n_demos_attempted": stats["n_attempted"],
        "n_demos_kept": stats["n_kept"],
        "n_transitions": stats["n_transitions"],
        "updates": counters["updates"],
        "bc_loss": final["bc_loss"],
        "episodes": 0,  # BC never interacts with the training env
        "frames": 0,
    }
    write_results(run_dir, summary, history)
    return summary


@hydra.main(version_base="1.3", config_path="config", config_name="bc")
def main(cfg: DictConfig):
    return run(cfg)


if __name__ == "__main__":
    main()
