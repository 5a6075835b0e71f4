"""Time to success: the main job run until its validation success first reaches a bar, then tested once.

Runs ``recipes/sac_silp.py``'s ``train`` on the given config with
``stop_at_success`` (default 0.95); its periodic evaluations read the validation
tasks (``eval.seed``: the same task distribution as the test tasks, other draws)
and its final one the 1000 test tasks (``eval.test_seed``), once. Prints the frames, gradient updates and
training wall time to the first evaluation at or above the bar, and the test
success. Run it alone on the machine; the output says if it was not.

Run::

    python benchmarks/time_to_success.py                          # the default config, seed 0
    python benchmarks/time_to_success.py --seed 1 --bar 0.95 compile.compile=false
    python benchmarks/time_to_success.py method=sac_silp_plus            # the paper's SILP+ as written
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

LOAD_AT_START = os.getloadavg()[0]  # before this benchmark's own imports count in it

import torch  # noqa: E402

from torchrl_silp.recipes import sac_silp  # noqa: E402
from torchrl_silp.recipes.schema import load_config  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bar", type=float, default=0.95, help="validation success to stop at")
    parser.add_argument("--run-dir", type=Path, default=None, help="where the run writes (a temporary dir by default)")
    parser.add_argument("overrides", nargs="*", help="hydra overrides of recipes/config/sac_silp.yaml")
    args = parser.parse_args(argv)
    if not 0.0 < args.bar <= 1.0:
        parser.error(f"--bar must be in (0, 1], got {args.bar}")
    load = LOAD_AT_START
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = args.run_dir or Path(tmp) / "run"
        cfg = load_config("sac_silp", [
            *args.overrides, f"seed={args.seed}", f"stop_at_success={args.bar}", f"run_dir={run_dir}", "progress=false",
        ])
        if cfg.eval.seed == cfg.eval.test_seed:
            parser.error("eval.seed (the validation tasks it stops on) must differ from eval.test_seed")
        start = time.perf_counter()
        summary = sac_silp.train(cfg)
        wall = time.perf_counter() - start
    # the last validation evaluation is the stopping one's policy and tasks
    reached = summary["validation_success_rate"] >= args.bar
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"threads {torch.get_num_threads()}, device {cfg.device}"
          f"{'' if load < 0.5 else f' (not alone: load average {load:.1f} at the start)'}")
    print(f"config: recipes/config/sac_silp.yaml, overrides {args.overrides or 'none'}, seed {args.seed}")
    print(f"validation success {summary['validation_success_rate']:.3f} "
          f"({'reached' if reached else 'not reached'} {args.bar} within the budget) after "
          f"{summary['frames']:,} frames, {summary['updates']:,} updates, {summary['train_wall_s'] / 60:.1f} min of "
          f"training ({wall / 60:.1f} min wall with the evaluations)")
    print(f"test success of that policy ({cfg.eval.n_tasks} test tasks): {summary['success_rate']:.3f}")
    return {"summary": summary, "wall_s": wall}


if __name__ == "__main__":
    main()
