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

import dataclasses
import functools
import time
import warnings

from omegaconf import DictConfig
from torchrl._utils import timeit

from torchrl_silp.data import EpisodeAssembler
from torchrl_silp.modules import make_averaged_actor
from torchrl_silp.recipes import schema
from torchrl_silp.recipes.builders import (
    make_actor_critic, make_buffers, make_collector, make_env, make_exploration, make_loss, make_model,
    make_optimizers, make_policy, observation_norm,
)
from torchrl_silp.recipes.checkpointing import StopRequest, checkpoint_run, restore
from torchrl_silp.recipes.metrics import (
    Progress, add_bc_filter_share, batch_metrics, count_batch, evaluate_run, final_evaluation, log_metrics,
    make_run_logger, new_counters, plot_learning_curve, summarize, truncate_logs, write_results,
)
from torchrl_silp.recipes.preflight import checkpoint_exists
from torchrl_silp.recipes.start import start_run, write_run_config
from torchrl_silp.recipes.update import compile_update, make_gradient_step, run_updates
from torchrl_silp.viz import save_rollout_png

schema.register()


@dataclasses.dataclass
class LoopState:
    """What the loop carries from batch to batch besides the checkpointed counters."""

    last_saved: float  # time.monotonic() at the last checkpoint
    last_eval_frames: int  # frames at the last periodic evaluation
    compile_left: int  # updates until the compiled update has settled (the bar says "compiling")
    tick: float  # time.perf_counter() where the current stretch of training time began


def train(cfg: DictConfig, resume_command: str | None = None) -> dict:
    """Train, evaluate on the fixed test tasks, checkpoint, report. Returns the summary dict.

    ``cfg``'s values are checked by the script's entry point (:func:`~torchrl_silp.recipes.preflight.main`)
    or the sweep before it calls this; what it asks of its ``run_dir`` and what only the built objects can
    check are checked here, before anything is written. ``resume_command``: what a stop prints to continue
    the run (the script's entry point passes its command line).
    """
    # ---- build: everything is made and checked before the run folder is written
    total_episodes, her = cfg.collector.total_episodes, cfg.replay_buffer.her
    device, run_dir = start_run(cfg, write_config=False)
    ckpt_dir = run_dir / "checkpoint"
    model = make_model(cfg, device)
    exploration = make_exploration(cfg, model, device)
    primers = [exploration.make_tensordict_primer()] if exploration is not None else []
    norm = observation_norm(cfg, model)  # network.normalize_observation: the one instance the run shares
    env = make_env(cfg, model, device, seed=cfg.seed, primers=primers)
    actor, critic = make_actor_critic(cfg, model, env, device)
    loss, updater = make_loss(cfg, actor, critic, model, env)
    optimizers = make_optimizers(cfg, loss)
    policy = make_policy(cfg, actor, exploration, env, device)
    buffers = make_buffers(cfg, model, device)
    assembler = EpisodeAssembler()
    # the evaluated policy: the actor, or an average of its parameters over updates
    decay = cfg.eval.actor_average_decay
    averaged = make_averaged_actor(actor, decay) if decay is not None else None
    policies = (actor if averaged is None else averaged.module, actor, averaged)
    write_run_config(cfg)

    # ---- start afresh or restore; the log rows after the checkpoint go (those steps are redone)
    resumed = cfg.resume and checkpoint_exists(ckpt_dir)
    counters, history, logger_state = restore(ckpt_dir, cfg, loss, optimizers, averaged, buffers, assembler,
                                              env, norm) if resumed else (new_counters(), [], None)
    dropped = truncate_logs(run_dir / "logs", counters["frames"])
    if dropped:
        print(f"dropped {dropped} log rows after frame {counters['frames']}: the run redoes those steps")
    logger = make_run_logger(cfg, run_dir, logger_state, log_hparams=not resumed)
    save = functools.partial(checkpoint_run, ckpt_dir, loss, optimizers, averaged, counters, history, assembler,
                             logger, env, buffers, norm)
    evaluate_now = functools.partial(evaluate_run, cfg, model, policies, device, counters, history, run_dir)

    # ---- the collector for the frames left, the update, the progress bar
    remaining = cfg.collector.total_frames - counters["frames"]
    if total_episodes is not None and counters["episodes"] >= total_episodes:
        remaining = 0
    collector = make_collector(cfg, env, policy, total_frames=max(remaining, cfg.collector.frames_per_batch),
                               init_random_frames=max(0, cfg.collector.init_random_frames - counters["frames"]),
                               device=device)
    updates_per_batch = max(1, int(round(cfg.collector.frames_per_batch * cfg.optim.utd_ratio)))
    gradient_step = compile_update(cfg, make_gradient_step(loss, optimizers, updater))
    progress = Progress(cfg, counters, history, len(buffers.demo_buffer))
    state = LoopState(last_saved=time.monotonic(), last_eval_frames=history[-1]["frames"] if history else 0,
                      compile_left=cfg.compile.warmup + 1 if cfg.compile.compile else 0, tick=time.perf_counter())
    progress.show()  # the checkpoint's counters from the start

    with StopRequest() as stop:
        update = functools.partial(run_updates, stop=stop, gradient_step=gradient_step, buffers=buffers,
                                   averaged=averaged, actor=actor, counters=counters, state=state, progress=progress,
                                   norm=norm)
        # ---- the updates of the batch a stop cut short, before any new frame
        if counters["updates_owed"]:
            with timeit("train"):
                update(counters["updates_owed"])
            counters["train_wall_s"] += time.perf_counter() - state.tick
            state.tick = time.perf_counter()
            if stop.requested:  # stopped again within them: what was made is saved, the rest still owed
                state.last_saved = save()
        for batch in (collector if remaining > 0 and not stop.requested else []):
            # ---- collect: count the batch, store it, plan demonstrations over the episodes it ended
            episodes_done = count_batch(counters, batch)
            if norm is not None:  # the statistics follow the interaction data, raw, before it is stored
                norm.update(batch.get("observation"))
            finished = assembler.push(batch) if cfg.silp.demos or her else None
            with timeit("rb - extend"):
                if not her:
                    buffers.extend(batch)
                elif finished is not None:  # hindsight relabelling reads episode boundaries from storage order
                    buffers.extend(finished)
            if finished is not None and cfg.silp.demos:
                with timeit("plan"):
                    buffers.demo_buffer.extend(finished)
            # ---- update
            losses = []
            if counters["frames"] >= cfg.collector.init_random_frames and len(buffers):
                with timeit("train"):
                    losses = update(updates_per_batch)
            counters["train_wall_s"] += time.perf_counter() - state.tick
            counters["planning_s"] = buffers.demo_buffer.planning_time
            metrics = batch_metrics(batch, losses, counters, len(buffers.demo_buffer))
            add_bc_filter_share(counters, losses)
            # ---- evaluate on the validation tasks
            if counters["frames"] - state.last_eval_frames >= cfg.eval.every_frames and not stop.requested:
                state.last_eval_frames = counters["frames"]
                counters["evaluations"] += 1
                with timeit("eval"):
                    metrics.update({f"eval/{k}": v for k, v in evaluate_now().items()})
                progress.show(success=f"{metrics['eval/success_rate']:.3f}", demos=len(buffers.demo_buffer))
            # ---- log
            metrics.update({f"time/{k}": v for k, v in timeit.todict(percall=False).items()})
            log_metrics(logger, metrics, counters["frames"])
            progress.bar.update(batch.numel() if total_episodes is None else episodes_done)
            # ---- checkpoint, then stop on a signal, a target success, a time or an episode budget
            if (stop.requested or counters["iterations"] % cfg.checkpoint.every_iters == 0
                    or time.monotonic() - state.last_saved >= cfg.checkpoint.every_s):
                state.last_saved = save()
            if (stop.requested
                    or cfg.stop_at_success is not None and history and history[-1]["success_rate"] >= cfg.stop_at_success
                    or cfg.max_train_wall_s and counters["train_wall_s"] >= cfg.max_train_wall_s
                    or total_episodes is not None and counters["episodes"] >= total_episodes):
                break
            state.tick = time.perf_counter()
    collector.shutdown()
    progress.bar.close()
    if stop.requested:
        stop.exit_run(counters, ckpt_dir, resume_command)

    # ---- the final figures: the last validation point, then the test tasks, read once
    final, validation, rollout = final_evaluation(cfg, counters, history, evaluate_now)
    save()
    summary = summarize(cfg, counters, final, len(buffers.demo_buffer), validation)
    if summary["warning"]:
        warnings.warn(summary["warning"])
    plot_learning_curve(history, run_dir / "learning_curve.png", label=cfg.logger.exp_name)
    save_rollout_png(model, rollout[:4], run_dir / "test_rollouts.png")
    write_results(run_dir, summary, history)
    return summary
