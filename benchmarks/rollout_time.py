"""Time per rollout of a trained policy, one task at a time and batched, against PRM's planning time.

One task at a time runs four ways on the same tasks: through the TorchRL env
(``evaluate`` with one task), with :class:`~torchrl_silp.SingleTaskRollout` eager,
and with it compiled (the policy and the model's step as one compiled function),
with dynamo checking every guard before each step (``guards="all"``) and only the
state (``guards="inputs"``, the default);
the paper's 130 ms per rollout (its Table 1, SAC-SILP+ on its hardware) is printed beside them.

Table 1's "planning time per rollout" of a learned planner is the wall time
of its batched evaluation (1000 tasks in one batch) divided by the tasks. A
planner that serves one robot sees one task at a time: this script times
that too (``--tasks`` tasks, each the test env of its own seed: the same
distribution), beside PRM with the given budget on the first ``--tasks`` test
tasks (plan + execution, per task) — the paper's comparison at "a similar
time per rollout".

Run::

    python benchmarks/rollout_time.py results/paper_budget/sac_silp_plus/seed0
    python benchmarks/rollout_time.py RUN_DIR --tasks 50 --budget 0.1 --threads 1
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from torchrl_silp import ReachEnv, SingleTaskRollout
from torchrl_silp.eval import DEFAULT_TEST_SEED, evaluate
from torchrl_silp.recipes.builders import make_env, make_model, make_observation_transform
from torchrl_silp.recipes.checkpointing import load_trained_networks

PAPER_MS_PER_ROLLOUT = 130.0  # the paper's Table 1: SAC-SILP+'s planning time per rollout


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished training run (config.yaml + checkpoint/)")
    parser.add_argument("--tasks", type=int, default=50, help="test tasks timed one at a time (default 50)")
    parser.add_argument("--budget", type=float, default=0.1, help="PRM planning budget, s (default 0.1; 0: skip PRM)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]  # before this benchmark's own work counts in it
    if args.tasks < 1:
        parser.error(f"--tasks must be >= 1, got {args.tasks}")
    if args.budget < 0:
        parser.error(f"--budget must be >= 0, got {args.budget}")
    if not (args.run_dir / "config.yaml").exists():
        parser.error(f"{args.run_dir} holds no config.yaml (a run of recipes/sac_silp.py or recipes/sweep.py)")
    torch.set_num_threads(args.threads)
    cfg = OmegaConf.load(args.run_dir / "config.yaml")
    device = torch.device("cpu")
    model = make_model(cfg, device)  # the run's task model (env.name, env.model)
    actor, _, _ = load_trained_networks(cfg, model, make_env(cfg, model, device, seed=0), args.run_dir / "checkpoint",
                                        device)

    def run(n_tasks: int, seed: int) -> dict:
        # a fresh input transform per test env (a transform belongs to one env)
        return evaluate(actor, n_tasks=n_tasks, seed=seed, model=model, max_steps=cfg.env.max_steps,
                        observation_transform=make_observation_transform(cfg, model), device=device)

    # one task at a time: each a batch-1 test env of its own seed (same task distribution)
    run(1, DEFAULT_TEST_SEED)  # warm-up
    times, successes = [], 0
    for i in range(args.tasks):
        out = run(1, DEFAULT_TEST_SEED + 1 + i)
        times.append(out["time_per_rollout_s"])
        successes += int(out["success_rate"])
    tasks = [ReachEnv(model, num_envs=1, seed=DEFAULT_TEST_SEED + 1 + i).reset()[0] for i in range(args.tasks)]
    fused = {}
    # eager, then compiled with each of dynamo's guard sets (SingleTaskRollout's guards), the default first:
    # a compile under guards=inputs would otherwise find and run the graph that guards=all compiled before
    for label, kwargs in (("SingleTaskRollout, eager:", {"compile": False}),
                          ("SingleTaskRollout, compiled:", {"guards": "inputs"}),
                          ("SingleTaskRollout, all guards:", {"guards": "all"})):
        rollout = SingleTaskRollout(actor, model, observation_transform=make_observation_transform(cfg, model),
                                    max_steps=cfg.env.max_steps, **kwargs)
        start = time.perf_counter()
        rollout(tasks[0])  # warm-up (and the compilation)
        warm_up = time.perf_counter() - start
        per_task, wins, steps = [], 0, 0
        for task in tasks:
            start = time.perf_counter()
            out = rollout(task)
            per_task.append(time.perf_counter() - start)
            wins, steps = wins + int(out["success"]), steps + int(out["steps"])
        fused[label] = (per_task, wins, warm_up, steps)
    batched = run(1000, DEFAULT_TEST_SEED)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads {args.threads}"
          f"{'' if load < 0.5 else f' (not alone: load average {load:.1f})'}")
    print(f"policy of {args.run_dir} ({cfg.env.name})")
    print(f"  one task at a time ({args.tasks} tasks), median per rollout:")
    print(f"    TorchRL env (evaluate, 1 task):    {statistics.median(times) * 1e3:6.1f} ms, success {successes}/{args.tasks}")
    for label, (per_task, wins, warm_up, steps) in fused.items():
        print(f"    {label:<35s}{statistics.median(per_task) * 1e3:6.1f} ms, success {wins}/{args.tasks} "
              f"(first call {warm_up:.1f} s; {1e6 * sum(per_task) / steps:.0f} us per step)")
    print(f"    the paper (Table 1, SAC-SILP+):     {PAPER_MS_PER_ROLLOUT:6.1f} ms")
    print(f"  batched (1000 tasks, as in Table 1): {batched['time_per_rollout_s'] * 1e3:.3f} ms per rollout, "
          f"success {batched['success_rate']:.3f}")
    if args.budget > 0:
        from torchrl_silp.baselines.prm import evaluate_prm

        prm = evaluate_prm(model, args.budget, n_tasks=args.tasks, max_steps=cfg.env.max_steps, device=device)
        print(f"PRM-{args.budget:g} on the first {args.tasks} test tasks: {prm['time_per_rollout_s'] * 1e3:.1f} ms per rollout "
              f"(planning mean {prm['planning_time_s'] * 1e3:.1f} ms, max {prm['planning_time_max_s'] * 1e3:.1f} ms), "
              f"success {prm['success_rate']:.3f}")


if __name__ == "__main__":
    main()
