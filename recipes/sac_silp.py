"""SAC-SILP+: train a neural motion planner (the main job); DDPG/TD3 and the Table 1 baselines by config.

    python recipes/sac_silp.py                      # the default config (UR5e reach)
    python recipes/sac_silp.py env=panda_reach      # the Franka Panda reach task
    python recipes/sac_silp.py seed=1 resume=true   # continue a killed run
    python recipes/sac_silp.py method=sac           # plain SAC (see config/method/)
    python recipes/sac_silp.py --config-dir mine env=my_task   # a task of your own (docs/your_own_task.md)

The loop is here; the builders live in ``builders.py`` (the gradient step in ``update.py``,
checkpoints in ``checkpointing.py``, what a run logs and leaves in ``metrics.py``), the typed
config in ``schema.py`` and ``config/``, its checks in ``preflight.py``; the method in the package.
Run as a script, the command line is composed and checked (:func:`preflight.main`) before anything
heavy is imported or any file written.
"""

from __future__ import annotations

if __name__ == "__main__":  # check the command line first; the module then runs as torchrl_silp.recipes.sac_silp
    from torchrl_silp.recipes.preflight import main

    main("sac_silp", "torchrl_silp.recipes.sac_silp:train")
    raise SystemExit(0)

import time
import warnings

import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl._utils import timeit
from torchrl.record.loggers import get_logger

from torchrl_silp.data import EpisodeAssembler
from torchrl_silp.eval import evaluate
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
from torchrl_silp.recipes.preflight import check_config
from torchrl_silp.recipes.start import start_run, write_run_config
from torchrl_silp.recipes.update import compile_update, make_gradient_step
from torchrl_silp.viz import save_rollout_png

schema.register()


def train(cfg: DictConfig, resume_command: str | None = None) -> dict:
    """Train, evaluate on the fixed test tasks, checkpoint, report. Returns the summary dict.

    Every value of ``cfg`` and what it asks of its ``run_dir`` are checked before anything is written
    (:func:`~torchrl_silp.recipes.preflight.check_config`, ``start_run``). ``resume_command``: what a
    stop prints to continue the run (the script's entry point passes its command line).
    """
    check_config(cfg)
    total_episodes = cfg.collector.total_episodes
    device, run_dir = start_run(cfg, write_config=False)
    ckpt_dir = run_dir / "checkpoint"
    model = make_model(cfg, device)
    exploration = make_exploration(cfg, model, device)
    primers = [exploration.make_tensordict_primer()] if exploration is not None else []
    env = make_env(cfg, model, device, seed=cfg.seed, primers=primers)
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
    write_run_config(cfg)  # everything is built and checked: the run folder may be written

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
        plot_learning_curve(history, run_dir / "learning_curve.png", label=cfg.logger.exp_name)
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
    if history:  # a resumed run shows what its last evaluation showed
        status.update(success=f"{history[-1]['success_rate']:.3f}", demos=len(buffers.demo_buffer))
    # the update compiles in its first calls after compile.warmup eager ones: the bar says so meanwhile
    to_compile = [cfg.compile.warmup + 1 if cfg.compile.compile else 0]

    def show(**fields):
        status.update(fields, updates=f"{counters['updates']:,}")
        pbar.set_postfix(status, refresh=True)

    def update(n: int, stop: StopRequest) -> list:
        """Up to ``n`` gradient updates, stopping early on a stop request; what is left goes to ``updates_owed``."""
        losses = []
        for i in range(n):
            if stop.requested:
                counters["updates_owed"] = n - i
                break
            if to_compile[0]:
                show(phase="compiling")
            losses.append(gradient_step(buffers.sample()))
            if averaged is not None:
                averaged.update_parameters(actor)
            counters["updates"] += 1
            if to_compile[0]:
                to_compile[0] -= 1
                if not to_compile[0]:
                    show(phase="training")
            elif i % 20 == 0:
                show(phase="training")
        else:
            counters["updates_owed"] = 0
        show()
        return losses

    last_eval_frames = history[-1]["frames"] if history else 0
    show()  # the checkpoint's counters from the start
    tick = time.perf_counter()
    with StopRequest() as stop:
        if counters.get("updates_owed"):  # the updates of the batch a stop cut short, before any new frame
            with timeit("train"):
                update(counters["updates_owed"], stop)
            counters["train_wall_s"] += time.perf_counter() - tick
            tick = time.perf_counter()
            if stop.requested:  # stopped again within them: what was made is saved, the rest still owed
                checkpoint()
        for batch in (collector if remaining > 0 and not stop.requested else []):
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
                    losses = update(updates_per_batch, stop)
            counters["train_wall_s"] += time.perf_counter() - tick
            counters["planning_s"] = buffers.demo_buffer.planning_time
            metrics = batch_metrics(batch, losses, counters, len(buffers.demo_buffer))
            if losses and "bc_filter_fraction" in losses[0].keys():  # over the updates whose batch held demos
                with_demos = torch.stack([td["num_demos"] for td in losses]) > 0
                kept = torch.stack([td["bc_filter_fraction"] for td in losses])[with_demos]
                counters["bc_kept_sum"] = counters.get("bc_kept_sum", 0.0) + kept.sum().item()
                counters["bc_kept_updates"] = counters.get("bc_kept_updates", 0) + kept.numel()
            if counters["frames"] - last_eval_frames >= cfg.eval.every_frames and not stop.requested:
                last_eval_frames = counters["frames"]
                counters["evaluations"] = counters.get("evaluations", 0) + 1
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
        if not counters["frames"]:  # before the first batch: nothing to save or resume
            stop.exit("stopped before the first collector batch: nothing was collected or trained")
        how = resume_command or "resume=true and the same config"
        stop.exit(f"stopped at {counters['frames']:,} frames and {counters['updates']:,} updates with a checkpoint "
                  f"in {ckpt_dir}; continue with: {how}")

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
    save_rollout_png(model, rollout[:4], run_dir / "test_rollouts.png")
    write_results(run_dir, summary, history)
    return summary
