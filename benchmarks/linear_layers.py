"""The recipes' MLP through oneDNN's layers against torch's ``nn.Linear``, by batch rows.

:class:`torchrl_silp.modules.Linear` sends a float32 CPU product through
oneDNN once it has at least :data:`~torchrl_silp.modules.linear.MIN_ROWS` rows.
This script times one MLP of the recipes' shape (``--in-features`` inputs,
two hidden layers of 256, ``--out-features`` outputs) both ways, with oneDNN's
path forced at every row count, so the row count where oneDNN starts to pay
off can be read for a given thread count:

- ``forward``: no gradient, as a collector's or a planner's policy call;
- ``train``: forward and backward (input and weight gradients), as in an update.

Each figure is the best of ``--repeats`` medians of ``--reps`` calls, in microseconds.

Run::

    python benchmarks/linear_layers.py --threads 1
    python benchmarks/linear_layers.py --threads 2 --rows 32 64 128 256
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import torch
from torchrl.modules import MLP

from torchrl_silp.modules import ReLU, onednn_linear_available, with_onednn_linear
from torchrl_silp.modules import linear as onednn_linear

sys.path.insert(0, str(Path(__file__).parent))
from timing import median_ms  # noqa: E402


def best_median_us(fn, reps: int, repeats: int) -> float:
    return 1e3 * min(median_ms(fn, reps) for _ in range(repeats))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--rows", type=int, nargs="+", default=[16, 32, 64, 96, 128, 192, 256, 512])
    parser.add_argument("--in-features", type=int, default=24, help="the MLP's inputs (default 24: the actor's)")
    parser.add_argument("--out-features", type=int, default=12, help="the MLP's outputs (default 12)")
    parser.add_argument("--reps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]  # before this benchmark's own work counts in it
    for name in ("threads", "in_features", "out_features", "reps", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if min(args.rows) < 1:
        parser.error(f"--rows must all be >= 1, got {args.rows}")
    if not onednn_linear_available():
        parser.error("this torch build has no oneDNN float32 linear (torch.ops.mkldnn._linear_pointwise)")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    reference = MLP(in_features=args.in_features, num_cells=[256, 256], out_features=args.out_features,
                    activation_class=ReLU)
    through_onednn = with_onednn_linear(MLP(in_features=args.in_features, num_cells=[256, 256],
                                            out_features=args.out_features, activation_class=ReLU))
    through_onednn.load_state_dict(reference.state_dict())
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {platform.machine()}, "
          f"{os.cpu_count()} CPUs{'' if load < 0.5 else f' (not alone: load average {load:.1f})'}; "
          f"MLP {args.in_features}-256-256-{args.out_features}, float32; the library's MIN_ROWS is "
          f"{onednn_linear.MIN_ROWS}")
    print(f"{'rows':>6} {'forward torch':>14} {'oneDNN':>9} {'ratio':>6} {'train torch':>12} {'oneDNN':>9} {'ratio':>6}")
    figures = {}
    saved_min_rows = onednn_linear.MIN_ROWS
    onednn_linear.MIN_ROWS = 1  # oneDNN's path at every row count, to find where it pays off
    try:
        for rows in args.rows:
            x = torch.randn(rows, args.in_features)
            row = {}
            for name, net in (("torch", reference), ("onednn", through_onednn)):
                with torch.no_grad():
                    row[f"forward {name}"] = best_median_us(lambda: net(x), args.reps, args.repeats)
                xg = x.clone().requires_grad_()

                def train(net=net, xg=xg):
                    net(xg).sum().backward()

                row[f"train {name}"] = best_median_us(train, args.reps, args.repeats)
            figures[rows] = row
            print(f"{rows:>6} {row['forward torch']:>11.1f} us {row['forward onednn']:>6.1f} us "
                  f"{row['forward torch'] / row['forward onednn']:>6.2f} {row['train torch']:>9.1f} us "
                  f"{row['train onednn']:>6.1f} us {row['train torch'] / row['train onednn']:>6.2f}", flush=True)
    finally:
        onednn_linear.MIN_ROWS = saved_min_rows
    print("ratio: torch's time over oneDNN's (above 1: oneDNN is faster)")
    return figures


if __name__ == "__main__":
    main()
