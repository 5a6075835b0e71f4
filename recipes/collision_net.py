"""The learned collision model of the paper's appendix B: train, evaluate, save; the planner can then use it.

    python recipes/collision_net.py                          # labels from the task model's exact checker
    python recipes/collision_net.py --labeller mujoco        # labels from the MuJoCo twin's contacts (extra sim)
    python recipes/collision_net.py --n 20000 --epochs 2     # a quick look

Draws ``--n`` configurations (the paper: 485k) in the task's joint box with scenes of its
task distribution, labels them, trains ``CollisionNet`` (512-256-64, as the paper) on 90 %
and evaluates it on the other 10 %: accuracy, recall, precision, specificity at 0.5 and the
ROC curve, written to ``<out>/<labeller>.json``; the network to ``<out>/<labeller>.pt``
(``planner.collision_net=<out>/<labeller>.pt`` makes it the training planner's edge check).
``python recipes/report.py --block collision_net`` puts the figures in docs/results/paper_tables.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from torchrl_silp.models import UR5eReach
from torchrl_silp.models.learned_collision import collision_dataset, train_collision_net

LABELLERS = ("exact", "mujoco")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--labeller", choices=LABELLERS, default="exact")
    parser.add_argument("--n", type=int, default=485_000, help="labelled configurations (the paper: 485k)")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("results/collision_net"))
    args = parser.parse_args(argv)
    if args.n < 10:
        parser.error(f"--n must be at least 10, got {args.n}")
    torch.set_num_threads(args.threads)
    model = UR5eReach()
    labeller = None
    if args.labeller == "mujoco":
        from torchrl_silp.sim import mujoco_labels

        def labeller(config, scene):
            return mujoco_labels(model, config, scene)

    tick = time.perf_counter()
    inputs, labels, _, _ = collision_dataset(model, args.n, torch.Generator().manual_seed(args.seed), labeller)
    label_s = time.perf_counter() - tick
    print(f"{args.n:,} configurations labelled by {args.labeller} in {label_s:.1f} s: "
          f"{labels.float().mean().item():.3f} collide")
    tick = time.perf_counter()
    net, result = train_collision_net(inputs, labels, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                                      seed=args.seed, log=print)
    m = result["metrics"]
    print(f"test ({result['test_n']:,}): accuracy {m['accuracy']:.3f}, recall {m['recall']:.3f}, "
          f"precision {m['precision']:.3f}, specificity {m['specificity']:.3f}, ROC AUC {result['roc']['auc']:.4f}")
    args.out.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": net.state_dict(), "in_features": net.in_features, "hidden_sizes": net.hidden_sizes},
               args.out / f"{args.labeller}.pt")
    summary = {"labeller": args.labeller, "n": args.n, "collision_share": labels.float().mean().item(),
               "label_s": label_s, "train_s": time.perf_counter() - tick, "command": " ".join(
                   ["python recipes/collision_net.py", *(sys.argv[1:] if argv is None else argv)]),
               **result, "args": {k: str(v) for k, v in vars(args).items()}}
    (args.out / f"{args.labeller}.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"wrote {args.out / (args.labeller + '.json')} and {args.out / (args.labeller + '.pt')}")
    return summary


if __name__ == "__main__":
    main()
