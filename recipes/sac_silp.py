"""SAC-SILP+: train a neural motion planner (the main job); DDPG/TD3 and the Table 1 baselines by config.

    python recipes/sac_silp.py                      # the default config (UR5e reach)
    python recipes/sac_silp.py env=panda_reach      # the Franka Panda reach task
    python recipes/sac_silp.py seed=1 resume=true   # continue a killed run
    python recipes/sac_silp.py method=sac           # plain SAC (see config/method/)

The loop is here; the builders live in ``builders.py`` (the gradient step in ``update.py``,
checkpoints in ``checkpointing.py``, what a run logs and leaves in ``metrics.py``), the typed
config in ``schema.py`` and ``config/``; the method in the package.
"""

from __future__ import annotations

import time
import warnings

import hydra
import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl._utils import timeit
from torchrl.record.loggers import get_logger

from torchrl_silp.data import EpisodeAssembler
from torchrl_silp.eval import evaluate
from torchrl_silp.models import UR5eReach
from torchrl_silp.modules import make_averaged_actor
from torchrl_silp.recipes import schema
from torchrl_silp.recipes.builders import (
    make_actor_critic, make_buffers, make_collector, make_env, make_exploration, make_loss, make_model,
    make_observation_transform, make_optimizers, make_policy,
)
from torchrl_silp.recipes.checkpointing import StopRequest, checkpoint_exists, restore, save_checkpoint, training_state
from torchrl_silp.recipes.metrics import (
    batch_metrics, log_metrics, new_counters, plot_learning_curve, summarize, truncate_logs, write_results,
)
from torchrl_silp.recipes.start import start_run
from torchrl_silp.recipes.update import compile_update, make_gradient_step
from torchrl_silp.viz import save_rollout_png

schema.register()


def train(cfg: DictConfig) -> dict:
    """Train, evaluate on the fixed test tasks, checkpoint, report. Returns the summary dict."""
    total_episodes = cfg.collector.total_episodes
    if total_episodes is not None and (isinstance(total_episodes, bool) or total_episodes < 1):
        raise ValueError(f"collector.total_episodes must be a positive number of episodes or null, got {total_episodes!r}")
    device, run_dir = start_run(cfg)
    ckpt_dir = run_dir / "checkpoint"
    model = make_model(cfg, device)
    exploration = make_exploration(cfg, model, device)
    primers = [exploration.make_tensordict_primer()] if exploration is not None else []
    env = make_env(cfg, model, device, seed=cfg.seed, primers=primers)
    if cfg.collector.frames_per_batch % cfg.env.num_envs:
        raise ValueError(f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple "
                         f"of env.num_envs ({cfg.env.num_envs})")
    actor, critic = make_actor_critic(cfg, model, env, device)
    loss, updater = make_loss(cfg, actor, critic, model, env)
    optimizers = make_optimizers(cfg, loss)
    policy = make_policy(cfg, actor, exploration, env, device)
    buffers = make_buffers(cfg, model, device)
    assembler = EpisodeAssembler()
    her, decay = cfg.replay_buffer.her, cfg.eval.actor_average_decay
    # the evaluated policy: the actor, or an average of its parameters over updates
    averaged = make_averaged_actor(actor, decay) if decay is not None else None
    evaluated = actor if averaged is None else averaged.module

    resumed = cfg.resume and checkpoint_exists(ckpt_dir)
    counters, history, logger_state = restore(ckpt_dir, cfg, loss, optimizers, averaged, buffers, assembler,
                                              env) if resumed else (new_counters(), [], None)

    # the steps after the checkpoint are redone (all of them when starting afresh): no step logged twice
    dropped = truncate_logs(run_dir / "logs", counters["frames"])
    if dropped:
        print(f"dropped {dropped} log rows after frame {counters['frames']}: the run redoes those steps")
    logger = None
    if cfg.logger.backend:
        logger = get_logger(cfg.logger.backend, logger_name=str(run_dir / "logs"),
                            experiment_name=cfg.logger.exp_name, state_dict=logger_state)
        if not resumed:
            logger.log_hparams(OmegaConf.to_container(cfg, resolve=True))

    last_saved = [time.monotonic()]

    def checkpoint():
        save_checkpoint(ckpt_dir, training_state(loss, optimizers, averaged, counters, history, assembler,
                                                 logger, env), buffers)
        last_saved[0] = time.monotonic()

    def run_evaluation(seed=cfg.eval.seed, return_rollout=False):
        kwargs = dict(n_tasks=cfg.eval.n_tasks, seed=seed, model=model, max_steps=cfg.env.max_steps,
                      observation_transform=make_observation_transform(cfg, model), device=device)
        metrics, rollout = evaluate(evaluated, return_rollout=True, **kwargs)
        if averaged is not None:
            metrics["online_success_rate"] = evaluate(actor, **kwargs)["success_rate"]
        if seed != cfg.eval.seed:  # the test tasks' figure: not a point of the validation curve
            return metrics, rollout
        point = {"frames": counters["frames"], "episodes": counters["episodes"],
                 "train_wall_s": counters["train_wall_s"], "collisions": counters["collisions"], **metrics}
        kept_updates = counters.get("bc_kept_updates", 0)
        if kept_updates:  # the share of demo actions the BC filter kept over the updates since the last point (Fig. 7)
            point["bc_filter_fraction"] = counters["bc_kept_sum"] / kept_updates
        counters["bc_kept_sum"], counters["bc_kept_updates"] = 0.0, 0
        if not history or history[-1]["frames"] != counters["frames"]:
            history.append(point)
        if counters["time_to_095_s"] is None and metrics["success_rate"] >= 0.95:
            counters["time_to_095_s"] = counters["train_wall_s"]
        return (metrics, rollout) if return_rollout else metrics

    remaining = cfg.collector.total_frames - counters["frames"]
    if total_episodes is not None and counters["episodes"] >= total_episodes:
        remaining = 0
    collector = make_collector(cfg, env, policy, total_frames=max(remaining, cfg.collector.frames_per_batch),
                               init_random_frames=max(0, cfg.collector.init_random_frames - counters["frames"]),
                               device=device)
    updates_per_batch = max(1, int(round(cfg.collector.frames_per_batch * cfg.optim.utd_ratio)))

    gradient_step = compile_update(cfg, make_gradient_step(loss, optimizers, updater))

    # frames (episodes, with an episode budget) on the bar; the updates and the phase beside it (the ETA is
    # tqdm's smoothed recent rate)
    if total_episodes is None:
        pbar = tqdm.tqdm(total=cfg.collector.total_frames, initial=counters["frames"], unit="frame",
                         disable=not cfg.progress)
    else:
        pbar = tqdm.tqdm(total=total_episodes, initial=min(counters["episodes"], total_episodes), unit="episode",
                         disable=not cfg.progress)
    status = {"phase": "random actions" if counters["frames"] < cfg.collector.init_random_frames else "training"}

    def show(**fields):
        status.update(fields, updates=f"{counters['updates']:,}")
        pbar.set_postfix(status, refresh=True)

    last_eval_frames = history[-1]["frames"] if history else 0
    tick = time.perf_counter()
    with StopRequest() as stop:
        for batch in (collector if remaining > 0 else []):
            counters["iterations"] += 1
            counters["frames"] += batch.numel()
            episodes_done = int(batch["next", "done"].sum())
            counters["episodes"] += episodes_done
            counters["collisions"] += int(batch["next", "collision"].sum())
            counters["swept_collisions"] += int(batch["next", "swept_collision"].sum())
            finished = assembler.push(batch) if cfg.silp.demos or her else None
            with timeit("rb - extend"):
                if not her:
                    buffers.extend(batch)
                elif finished is not None:  # hindsight relabelling reads episode boundaries from storage order
                    buffers.extend(finished)
            if finished is not None and cfg.silp.demos:
                with timeit("plan"):
                    buffers.demo_buffer.extend(finished)
            losses = []
            if counters["frames"] >= cfg.collector.init_random_frames and len(buffers):
                with timeit("train"):
                    for i in range(updates_per_batch):
                        losses.append(gradient_step(buffers.sample()))
                        if averaged is not None:
                            averaged.update_parameters(actor)
                        counters["updates"] += 1
                        if i % 20 == 0:
                            show(phase="training")
            counters["train_wall_s"] += time.perf_counter() - tick
            counters["planning_s"] = buffers.demo_buffer.planning_time
            metrics = batch_metrics(batch, losses, counters, len(buffers.demo_buffer))
            if losses and "bc_filter_fraction" in losses[0].keys():  # over the updates whose batch held demos
                with_demos = torch.stack([td["num_demos"] for td in losses]) > 0
                kept = torch.stack([td["bc_filter_fraction"] for td in losses])[with_demos]
                counters["bc_kept_sum"] = counters.get("bc_kept_sum", 0.0) + kept.sum().item()
                counters["bc_kept_updates"] = counters.get("bc_kept_updates", 0) + kept.numel()
            if counters["frames"] - last_eval_frames >= cfg.eval.every_frames:
                last_eval_frames = counters["frames"]
                with timeit("eval"):
                    metrics.update({f"eval/{k}": v for k, v in run_evaluation().items()})
                show(success=f"{metrics['eval/success_rate']:.3f}", demos=len(buffers.demo_buffer))
            metrics.update({f"time/{k}": v for k, v in timeit.todict(percall=False).items()})
            log_metrics(logger, metrics, counters["frames"])
            pbar.update(batch.numel() if total_episodes is None else episodes_done)
            if (stop.requested or counters["iterations"] % cfg.checkpoint.every_iters == 0
                    or time.monotonic() - last_saved[0] >= cfg.checkpoint.every_s):
                checkpoint()
            if stop.requested:
                break
            if cfg.stop_at_success is not None and history and history[-1]["success_rate"] >= cfg.stop_at_success:
                break
            if cfg.max_train_wall_s and counters["train_wall_s"] >= cfg.max_train_wall_s:
                break
            if total_episodes is not None and counters["episodes"] >= total_episodes:
                break
            tick = time.perf_counter()
    collector.shutdown()
    pbar.close()
    if stop.requested:
        stop.exit(f"stopped at {counters['frames']} frames, checkpoint in {ckpt_dir}: continue with resume=true")

    if cfg.eval.test_seed == cfg.eval.seed:  # one set of tasks for the curve and the figure: evaluated once
        final, rollout = run_evaluation(return_rollout=True)
        validation = final
    else:  # the last validation point (evaluated now unless the last batch just did), then the test tasks, once
        validation = history[-1] if history and history[-1]["frames"] == counters["frames"] else run_evaluation()
        final, rollout = run_evaluation(cfg.eval.test_seed, return_rollout=True)
    checkpoint()
    summary = summarize(cfg, counters, final, len(buffers.demo_buffer), validation)
    if summary["warning"]:
        warnings.warn(summary["warning"])
    plot_learning_curve(history, run_dir / "learning_curve.png", label=cfg.logger.exp_name)
    if isinstance(model, UR5eReach):  # the pictures draw a UR5e
        save_rollout_png(model, rollout[:4], run_dir / "test_rollouts.png")
    write_results(run_dir, summary, history)
    return summary


@hydra.main(version_base="1.3", config_path="config", config_name="sac_silp")
def main(cfg):
    return train(cfg)


if __name__ == "__main__":
    main()
