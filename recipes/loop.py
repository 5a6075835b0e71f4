"""The SILP+ training loop shared by ``sac_silp.py`` and ``ddpg_silp.py`` (the algorithm is a config field)."""

from __future__ import annotations

import time

import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torchrl._utils import timeit
from torchrl.record.loggers import get_logger

from torchrl_silp.eval import evaluate
from torchrl_silp.viz import save_rollout_png

from torchrl_silp.envs.reach import COLLISION_TYPES, TASK_BRANCHES, WORKSPACE_EXIT_MODES
from torchrl_silp.data import HER_STRATEGIES
from torchrl_silp.objectives import BC_FILTERS
from torchrl_silp.planning import SEARCH_METHODS

from utils import (
    ALGORITHMS,
    EXPLORATION_MODES,
    LOGGER_BACKENDS,
    check_choice,
    check_device,
    EpisodeAssembler,
    checkpoint_exists,
    cut_episodes,
    load_checkpoint,
    log_metrics,
    make_actor_critic,
    make_buffers,
    make_collector,
    make_env,
    make_exploration_policy,
    make_loss,
    make_optimizers,
    plot_learning_curve,
    save_checkpoint,
    start_run,
    write_results,
)


def validate(cfg: DictConfig) -> None:
    """Reject bad configurations before any work is done."""
    positive = {
        "env.num_envs": cfg.env.num_envs,
        "env.max_steps": cfg.env.max_steps,
        "collector.frames_per_batch": cfg.collector.frames_per_batch,
        "collector.total_frames": cfg.collector.total_frames,
        "optim.batch_size": cfg.optim.batch_size,
        "eval.n_tasks": cfg.eval.n_tasks,
        "eval.every_frames": cfg.eval.every_frames,
        "checkpoint.every_iters": cfg.checkpoint.every_iters,
    }
    for name, value in positive.items():
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    if cfg.collector.frames_per_batch % cfg.env.num_envs:
        raise ValueError(
            f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple of "
            f"env.num_envs ({cfg.env.num_envs})"
        )
    choices = {
        "algorithm": (cfg.algorithm, ALGORITHMS),
        "exploration.mode": (cfg.exploration.mode, EXPLORATION_MODES),
        "silp.filter": (cfg.silp.filter, BC_FILTERS),
        "planner.method": (cfg.planner.method, SEARCH_METHODS),
        "env.collision_type": (cfg.env.collision_type, COLLISION_TYPES),
        "env.workspace_exit": (cfg.env.workspace_exit, WORKSPACE_EXIT_MODES),
        "env.task_branch": (cfg.env.task_branch, TASK_BRANCHES),
        "logger.backend": (cfg.logger.backend, LOGGER_BACKENDS),
        "replay_buffer.her": (cfg.replay_buffer.get("her", False), (True, False)),
        "replay_buffer.her_strategy": (cfg.replay_buffer.get("her_strategy", "future"), HER_STRATEGIES),
    }
    for name, (value, allowed) in choices.items():
        check_choice(name, value, allowed)
    fraction = cfg.replay_buffer.demo_fraction
    if fraction != "proportional" and (isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0 <= fraction <= 1):
        raise ValueError(f"replay_buffer.demo_fraction must be a number in [0, 1] or 'proportional', got {fraction!r}")
    her_ratio = cfg.replay_buffer.get("her_ratio", 0.8)
    if isinstance(her_ratio, bool) or not isinstance(her_ratio, (int, float)) or not 0 <= her_ratio <= 1:
        raise ValueError(f"replay_buffer.her_ratio must be a number in [0, 1], got {her_ratio!r}")
    if not cfg.optim.utd_ratio > 0:
        raise ValueError(f"optim.utd_ratio must be > 0, got {cfg.optim.utd_ratio!r}")
    target_entropy = cfg.optim.get("target_entropy", "auto")
    if target_entropy != "auto" and (isinstance(target_entropy, bool) or not isinstance(target_entropy, (int, float))):
        raise ValueError(f"optim.target_entropy must be 'auto' or a number, got {target_entropy!r}")
    decay = cfg.eval.get("actor_average_decay", None)
    if decay is not None and (isinstance(decay, bool) or not isinstance(decay, (int, float)) or not 0 < decay < 1):
        raise ValueError(f"eval.actor_average_decay must be null or a number in (0, 1), got {decay!r}")
    check_device(cfg.device)


def train(cfg: DictConfig) -> dict:
    """Train, evaluate on the fixed test tasks, checkpoint, report. Returns the summary dict."""
    validate(cfg)
    device, run_dir = start_run(cfg)
    ckpt_dir = run_dir / "checkpoint"

    env = make_env(cfg, device, seed=cfg.seed)
    actor, critic = make_actor_critic(cfg, env, device)
    loss, updater = make_loss(cfg, actor, critic, env)
    optimizers = make_optimizers(cfg, loss)
    policy = make_exploration_policy(cfg, actor, env, device)
    buffers = make_buffers(cfg, env, device)
    assembler = EpisodeAssembler()
    # hindsight relabelling reads episode boundaries from storage order: it stores whole episodes
    her = bool(cfg.replay_buffer.get("her", False))
    # the evaluated policy: the actor itself, or an exponential moving average of its
    # parameters over updates (eval.actor_average_decay), which evens out the swings of
    # the online actor between evaluations
    decay = cfg.eval.get("actor_average_decay", None)
    actor_params = TensorDict.from_module(actor)
    averaged_params = actor_params.data.clone() if decay is not None else None

    counters = {"frames": 0, "episodes": 0, "iterations": 0, "updates": 0, "collisions": 0,
                "train_wall_s": 0.0, "planning_s": 0.0, "time_to_095_s": None}
    history: list[dict] = []
    logger_state = None
    resumed = cfg.resume and checkpoint_exists(ckpt_dir)
    if resumed:
        state = load_checkpoint(ckpt_dir, buffers, assembler)
        loss.load_state_dict(state["loss"])
        for name, opt in optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        counters, history, logger_state = state["counters"], state["history"], state["logger"]
        if averaged_params is not None:
            if state.get("averaged_actor") is None:
                raise ValueError("eval.actor_average_decay is set but the checkpoint holds no averaged actor: "
                                 "resume with the config the run was started with")
            averaged_params.update_(state["averaged_actor"])
        torch.set_rng_state(state["torch_rng"])
        env.base_env.rng.set_state(state["env_rng"])
        # the collector starts new episodes: plan (and store) what was left unfinished
        leftover = assembler.flush()
        if leftover is not None and her:
            buffers.extend(cut_episodes(leftover))
        if leftover is not None and cfg.silp.demos:
            buffers.demo_buffer.extend(leftover)
        print(f"resumed from {ckpt_dir}: {counters['frames']} frames, {len(buffers)} transitions in the buffers")

    logger = None
    if cfg.logger.backend:
        logger = get_logger(
            cfg.logger.backend, logger_name=str(run_dir / "logs"), experiment_name=cfg.logger.exp_name,
            state_dict=logger_state,
        )
        if not resumed:
            logger.log_hparams(OmegaConf.to_container(cfg, resolve=True))

    remaining = cfg.collector.total_frames - counters["frames"]
    if remaining <= 0:
        print("nothing left to train: total_frames reached")
    init_random = max(0, cfg.collector.init_random_frames - counters["frames"])
    cfg_collector = OmegaConf.merge(cfg, {"collector": {"init_random_frames": init_random}})
    collector = make_collector(cfg_collector, env, policy, total_frames=max(remaining, cfg.collector.frames_per_batch), device=device)
    updates_per_batch = max(1, int(round(cfg.collector.frames_per_batch * cfg.optim.utd_ratio)))

    def update(sample):
        loss_td = loss(sample)
        total = sum(v for k, v in loss_td.items() if k.startswith("loss_"))
        total.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        updater.step()
        if averaged_params is not None:
            with torch.no_grad():
                averaged_params.lerp_(actor_params.data, 1.0 - decay)
        return loss_td.detach()

    def evaluate_policy(return_rollout: bool = False):
        """``evaluate`` on the evaluated policy, plus the online actor's success rate when that is an average."""
        def run():
            return evaluate(actor, n_tasks=cfg.eval.n_tasks, seed=cfg.eval.seed, max_steps=cfg.env.max_steps,
                            workspace_exit=cfg.env.workspace_exit, task_branch=cfg.env.task_branch,
                            device=device, return_rollout=True)

        if averaged_params is None:
            metrics, rollout = run()
        else:
            online, _ = run()
            with averaged_params.to_module(actor):
                metrics, rollout = run()
            metrics["online_success_rate"] = online["success_rate"]
        return (metrics, rollout) if return_rollout else metrics

    def run_eval():
        metrics = evaluate_policy()
        point = {"frames": counters["frames"], "episodes": counters["episodes"],
                 "train_wall_s": counters["train_wall_s"], **metrics}
        history.append(point)
        if counters["time_to_095_s"] is None and metrics["success_rate"] >= 0.95:
            counters["time_to_095_s"] = counters["train_wall_s"]
        return metrics

    pbar = tqdm.tqdm(total=cfg.collector.total_frames, initial=counters["frames"], disable=not cfg.progress)
    last_eval_frames = history[-1]["frames"] if history else 0
    tick = time.perf_counter()
    for batch in (collector if remaining > 0 else []):
        counters["iterations"] += 1
        counters["frames"] += batch.numel()
        counters["episodes"] += int(batch["next", "done"].sum())
        counters["collisions"] += int(batch["next", "collision"].sum())
        if not her:
            with timeit("rb - extend"):
                buffers.extend(batch)
        if cfg.silp.demos or her:
            finished = assembler.push(batch)
            if finished is not None and her:
                with timeit("rb - extend"):
                    buffers.extend(finished)
            if finished is not None and cfg.silp.demos:
                with timeit("plan"):
                    buffers.demo_buffer.extend(finished)
        losses = []
        # (with hindsight relabelling the buffers hold finished episodes only: none may have ended yet)
        if counters["frames"] >= cfg.collector.init_random_frames and len(buffers):
            with timeit("train"):
                for _ in range(updates_per_batch):
                    losses.append(update(buffers.sample()))
                    counters["updates"] += 1
        counters["train_wall_s"] += time.perf_counter() - tick
        counters["planning_s"] = buffers.demo_buffer.planning_time

        metrics = {
            "train/collisions": counters["collisions"],
            "train/episodes": counters["episodes"],
            "train/demos": len(buffers.demo_buffer),
            "time/train_wall_s": counters["train_wall_s"],
            "time/planning_share": counters["planning_s"] / max(counters["train_wall_s"], 1e-9),
        }
        ended = batch["next", "done"]
        if ended.any():
            metrics["train/episode_reward"] = batch["next", "episode_reward"][ended].mean().item()
            metrics["train/success_rate"] = batch["next", "success"][ended].float().mean().item()
        if losses:
            stacked = torch.stack(losses)
            for key, value in stacked.items():
                if key.startswith("loss_") or key in ("alpha", "bc_filter_fraction", "bc_mse"):
                    metrics[f"train/{key}"] = value.float().mean().item()
        if counters["frames"] - last_eval_frames >= cfg.eval.every_frames:
            last_eval_frames = counters["frames"]
            with timeit("eval"):
                ev = run_eval()
            metrics.update({f"eval/{k}": v for k, v in ev.items()})
            pbar.set_postfix(success=f"{ev['success_rate']:.3f}", demos=len(buffers.demo_buffer))
        metrics.update({f"time/{k}": v for k, v in timeit.todict(percall=False).items()})
        log_metrics(logger, metrics, counters["frames"])
        pbar.update(batch.numel())
        if counters["iterations"] % cfg.checkpoint.every_iters == 0:
            save_checkpoint(ckpt_dir, _state(loss, optimizers, counters, history, logger, env, averaged_params), buffers, assembler)
        if cfg.stop_at_success is not None and history and history[-1]["success_rate"] >= cfg.stop_at_success:
            break
        if cfg.max_train_wall_s and counters["train_wall_s"] >= cfg.max_train_wall_s:
            break
        tick = time.perf_counter()
    collector.shutdown()
    pbar.close()

    final, rollout = evaluate_policy(return_rollout=True)
    if not history or history[-1]["frames"] != counters["frames"]:
        history.append({"frames": counters["frames"], "episodes": counters["episodes"],
                        "train_wall_s": counters["train_wall_s"], **final})
        if counters["time_to_095_s"] is None and final["success_rate"] >= 0.95:
            counters["time_to_095_s"] = counters["train_wall_s"]
    save_checkpoint(ckpt_dir, _state(loss, optimizers, counters, history, logger, env, averaged_params), buffers, assembler)
    summary = {
        "method": cfg.logger.exp_name,
        "algorithm": cfg.algorithm,
        "silp_bc": bool(cfg.silp.bc),
        "silp_demos": bool(cfg.silp.demos),
        "her": her,
        "exploration": cfg.exploration.mode,
        "seed": cfg.seed,
        "success_rate": final["success_rate"],
        "online_success_rate": final.get("online_success_rate", final["success_rate"]),
        "evaluated_actor": "online" if averaged_params is None else f"average (decay {decay})",
        "test_collision_rate": final["collision_rate"],
        "collisions_during_training": counters["collisions"],
        "episodes": counters["episodes"],
        "frames": counters["frames"],
        "updates": counters["updates"],
        "train_wall_s": counters["train_wall_s"],
        "planning_s": counters["planning_s"],
        "planning_share": counters["planning_s"] / max(counters["train_wall_s"], 1e-9),
        "time_to_095_s": counters["time_to_095_s"],
        "rollout_time_per_episode_s": final["time_per_rollout_s"],
        "demos_stored": len(buffers.demo_buffer),
    }
    plot_learning_curve(history, run_dir / "learning_curve.png", label=cfg.logger.exp_name)
    save_rollout_png(env.base_env, rollout[:4], run_dir / "test_rollouts.png")
    write_results(run_dir, summary, history)
    return summary


def _state(loss, optimizers, counters, history, logger, env, averaged_params) -> dict:
    return {
        "loss": loss.state_dict(),
        "averaged_actor": averaged_params.clone() if averaged_params is not None else None,
        "optimizers": {name: opt.state_dict() for name, opt in optimizers.items()},
        "counters": dict(counters),
        "history": list(history),
        "logger": logger.state_dict() if logger is not None and hasattr(logger, "state_dict") else None,
        "torch_rng": torch.get_rng_state(),
        "env_rng": env.base_env.rng.get_state(),
    }

