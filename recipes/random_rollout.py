"""Roll out a uniformly random policy in the batched UR5e reach env and draw the episodes.

A sanity check of the task, not a training recipe: it prints the mean reward,
the collision rate and the success rate of random actions, and saves one
panel per episode (arm at the final state, TCP path, obstacle, goal).

    python recipes/random_rollout.py                                   # the picture goes to runs/random_rollout.png
    python recipes/random_rollout.py --out docs/random_rollout.png     # the committed picture, regenerated
"""

from __future__ import annotations

import argparse
import os

import torch

from torchrl_silp import UR5eReachEnv
from torchrl_silp.viz import save_rollout_png


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=4, help="parallel envs (batch size)")
    parser.add_argument("--steps", type=int, default=50, help="steps per env (the env's episode length is 50)")
    parser.add_argument("--seed", type=int, default=0, help="seeds the tasks (env) and the random actions (torch)")
    parser.add_argument("--out", default="runs/random_rollout.png", help="PNG to write")
    args = parser.parse_args(argv)
    if args.num_envs < 1:
        parser.error(f"--num-envs must be >= 1, got {args.num_envs}")
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    return args


def main(argv: list[str] | None = None) -> dict[str, float]:
    args = parse_args(argv)
    # The env's generator draws the tasks; random actions come from the action
    # spec's rand(), which uses torch's global generator: seed both.
    torch.manual_seed(args.seed)
    env = UR5eReachEnv(num_envs=args.num_envs, seed=args.seed)
    # break_when_any_done=False: envs that finish early are reset and go on,
    # so every env runs exactly --steps steps.
    td = env.rollout(args.steps, break_when_any_done=False)

    nxt = td["next"]
    done = nxt["done"].squeeze(-1)
    # An episode is one that ended (done) or the unfinished tail of a row.
    episodes = int(done.sum()) + int((~done[..., -1]).sum())
    metrics = {
        "mean_reward": nxt["reward"].mean().item(),
        "collision_rate": nxt["collision"].float().mean().item(),  # per step
        "success_rate": nxt["success"].sum().item() / episodes,  # per episode
        "episodes": episodes,
    }
    print(f"random policy, {args.num_envs} envs x {args.steps} steps, seed {args.seed}")
    print(f"  mean reward     {metrics['mean_reward']:.3f}")
    print(f"  collision rate  {metrics['collision_rate']:.3f}  (colliding steps / steps)")
    print(f"  success rate    {metrics['success_rate']:.3f}  (successes / {episodes} episodes)")

    parent = os.path.dirname(os.path.abspath(args.out))
    os.makedirs(parent, exist_ok=True)
    print(f"  picture         {save_rollout_png(env, td, args.out)}")
    return metrics


if __name__ == "__main__":
    main()
