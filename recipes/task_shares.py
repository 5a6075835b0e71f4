"""How hard a sweep's tasks are: the share of each method's test tasks the straight joint path to the goal
solves within an episode (``torchrl_silp.eval.straight_path_free``: no detour needed), on the tasks its runs
are tested on (``ReachEnv(model, num_envs=eval.n_tasks, seed=eval.test_seed)``, as ``evaluate`` draws them).

    python recipes/task_shares.py --config-name sweep_urdf_robots --out results/urdf_robots/task_shares.json
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys

import torch

from torchrl_silp.envs import ReachEnv
from torchrl_silp.eval import straight_path_free
from torchrl_silp.recipes.builders import make_model
from torchrl_silp.recipes.schema import load_config
from torchrl_silp.recipes.sweep import load_config as load_sweep, plan


def task_shares(config_name: str, methods: list[str] | None = None) -> dict:
    """``{task: {"methods": [...], "straight_path_share": s, "n_tasks": n, "max_steps": m}}``, one entry per
    distinct task of the sweep's runs (methods sharing a task share its entry)."""
    runs = [r for r in plan(load_sweep(config_name=config_name), check_configs=False) if r.seed == 0]
    out: dict = {}
    for run in runs:
        if methods and run.method not in methods:
            continue
        cfg = load_config(run.config, [o.lstrip("+") if o.startswith("++env.") else o for o in run.overrides])
        key = json.dumps([cfg.env.name, dict(cfg.env.robot), dict(cfg.env.model)], sort_keys=True, default=str)
        if key not in out:
            model = make_model(cfg, torch.device("cpu"))
            tasks = ReachEnv(model, num_envs=cfg.eval.n_tasks, seed=cfg.eval.test_seed).reset()
            free = straight_path_free(model, tasks, cfg.env.max_steps)
            out[key] = {"methods": [], "straight_path_share": free.float().mean().item(),
                        "n_tasks": cfg.eval.n_tasks, "max_steps": cfg.env.max_steps, "task": cfg.env.run_name}
        out[key]["methods"].append(run.method)
    return {v["methods"][0]: v for v in out.values()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config-name", required=True, help="a sweep config of recipes/config")
    parser.add_argument("--methods", nargs="*", help="only these methods of its registry")
    parser.add_argument("--out", help="write the shares to this JSON file")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    shares = task_shares(args.config_name, args.methods)
    result = {"command": "python recipes/task_shares.py " + shlex.join(sys.argv[1:]), "tasks": shares}
    for method, entry in shares.items():
        print(f"{entry['task']} ({', '.join(entry['methods'])}): straight joint path solves "
              f"{entry['straight_path_share']:.3f} of {entry['n_tasks']} test tasks")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=1)
            fh.write("\n")


if __name__ == "__main__":
    main()
