"""Time to success: the main job run until its validation success first reaches a bar, then tested once.

Runs ``recipes/sac_silp.py``'s ``train`` on the given config with
``stop_at_success`` (default 0.95) and its periodic evaluations on the
validation tasks (``eval.seed`` = ``DEFAULT_VALIDATION_SEED``: the same task
distribution as the test tasks, other draws), then evaluates the policy it
stopped with on the 1000 test tasks once. Prints the frames, gradient updates and
training wall time to the first evaluation at or above the bar, and the test
success. Run it alone on the machine; the output says if it was not.

Run::

    python benchmarks/time_to_success.py                          # the default config, seed 0
    python benchmarks/time_to_success.py --seed 1 --bar 0.95 compile.compile=false
    python benchmarks/time_to_success.py method=sac_silp_plus env=panda_reach
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))
import sac_silp  # noqa: E402  (registers the structured schema)
import utils  # noqa: E402

from torchrl_silp.eval import DEFAULT_TEST_SEED, DEFAULT_VALIDATION_SEED, evaluate  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bar", type=float, default=0.95, help="validation success to stop at")
    parser.add_argument("--run-dir", type=Path, default=None, help="where the run writes (a temporary dir by default)")
    parser.add_argument("overrides", nargs="*", help="hydra overrides of recipes/config/sac_silp.yaml")
    args = parser.parse_args(argv)
    if not 0.0 < args.bar <= 1.0:
        parser.error(f"--bar must be in (0, 1], got {args.bar}")
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = args.run_dir or Path(tmp) / "run"
        with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
            cfg = compose(config_name="sac_silp", overrides=[
                *args.overrides, f"seed={args.seed}", f"stop_at_success={args.bar}",
                f"eval.seed={DEFAULT_VALIDATION_SEED}", f"run_dir={run_dir}", "progress=false",
            ])
        start = time.perf_counter()
        summary = sac_silp.train(cfg)
        wall = time.perf_counter() - start
        device = torch.device("cpu")
        model = utils.make_model(cfg, device)
        actor, _, _ = utils.load_trained_networks(cfg, model, utils.make_env(cfg, model, device, seed=0),
                                                  run_dir / "checkpoint", device)
        test = evaluate(actor, n_tasks=1000, seed=DEFAULT_TEST_SEED, model=model, max_steps=cfg.env.max_steps,
                        observation_transform=utils.make_observation_transform(cfg, model))
    reached = summary["success_rate"] >= args.bar  # the final evaluation is the stopping one's policy and tasks
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"threads {torch.get_num_threads()}, device {cfg.device}"
          f"{'' if load < 0.5 else f' (not alone: load average {load:.1f} at the start)'}")
    print(f"config: recipes/config/sac_silp.yaml, overrides {args.overrides or 'none'}, seed {args.seed}")
    print(f"validation success {summary['success_rate']:.3f} "
          f"({'reached' if reached else 'not reached'} {args.bar} within the budget) after "
          f"{summary['frames']:,} frames, {summary['updates']:,} updates, {summary['train_wall_s'] / 60:.1f} min of "
          f"training ({wall / 60:.1f} min wall with the evaluations)")
    print(f"test success of that policy (1000 test tasks): {test['success_rate']:.3f}")
    return {"summary": summary, "test_success_rate": test["success_rate"], "wall_s": wall}


if __name__ == "__main__":
    main()
