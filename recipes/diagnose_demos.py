"""What limits SILP+ on a task: its demonstrations and its critic, measured on a run's checkpoint.

    python recipes/diagnose_demos.py RUN_DIR [hydra overrides the run was trained with]
    python recipes/diagnose_demos.py results/hard_tasks/ur5e3_sac_silp_plus_ext/seed0 'env.model.boxes=[...]'

Composes ``config/sac_silp.yaml`` with the overrides, loads ``RUN_DIR/checkpoint`` (networks and the
demonstration buffer) and reads the validation tasks only (``eval.seed``), never the test tasks. It prints:

* the policy on the validation tasks: success, collision and time-out shares;
* the demonstrations the planner gets from the policy's own episodes: the policy, sampling as in
  training, runs one episode on each validation task under the run's collision handling; each
  episode's roadmap (the run's planner settings) is searched from its start to its goal configuration.
  The share of episodes with such a path, among those the policy failed, is what SILP+ can imitate
  there; the same with ``planner.sampled_nodes`` free configurations around the visited states
  (ours) shows what nodes beyond the visited ones add. A path's length in the achieved-goal space
  against the straight distance says how far round it goes. What the run's whole planner (its random
  pairs too) makes of the same episodes: demonstration transitions per episode, their mean length in
  steps, and its time per episode on this machine;
* the batch: the demonstrations' share of a batch, the BC weights, the buffers' fill;
* the critic on stored demonstrations: Q of the demonstration's action against Q of the policy's, and
  which of the two truly gets the higher one-step reward (through the task model's own step).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp import CollisionHandling, ReachEnv
from torchrl_silp.data import FilledStorageCheckpointer
from torchrl_silp.eval import episode_outcomes, evaluate
from torchrl_silp.planning import ExperienceRoadmap, plan_demonstrations, roadmap_paths
from torchrl_silp.planning.roadmap import split_episodes
from torchrl_silp.recipes.builders import make_observation_transform, planner_kwargs
from torchrl_silp.recipes.diagnose import load_run, median, min_q

SAMPLED_NODES = (0, 32, 128)  # the roadmap's extra free nodes per episode compared
CRITIC_ROWS = 4096  # demonstration transitions the critic is read on


def demonstration_yield(model, cfg, episodes: TensorDictBase, sampled_nodes: int, generator: torch.Generator) -> dict:
    """The start-to-goal search on the roadmap of each env's first episode (its validation task): found, whether
    the episode reached its goal, and the path's length over the straight one."""
    roadmap = ExperienceRoadmap(model, episodes, d=cfg.planner.d, step_size=cfg.planner.step_size, lazy=True,
                                goal_node=True, sampled_nodes=sampled_nodes, sample_spread=cfg.planner.sample_spread,
                                generator=generator)
    with_goal = roadmap.is_goal_node.any(-1).nonzero().squeeze(-1)
    paths = roadmap_paths(roadmap, with_goal, torch.zeros_like(with_goal), roadmap.num_nodes[with_goal] - 1,
                          method=cfg.planner.method)
    found = torch.zeros(roadmap.num_episodes, dtype=torch.bool)
    found[with_goal] = paths.found
    straight = (roadmap.goal - roadmap.achieved_goal[:, 0]).norm(dim=-1)
    stretch = torch.full((roadmap.num_episodes,), float("nan"))
    stretch[with_goal] = paths.cost / straight[with_goal].clamp(min=1e-6)
    first = split_episodes(episodes)[1][:, 0]  # each env's first episode: the validation task itself
    return {"found": found[first], "reached": roadmap.reached[first], "stretch": stretch[first],
            "nodes": roadmap.num_nodes[first].float().mean().item()}


def demonstration_cost(model, cfg, episodes: TensorDictBase, sampled_nodes: int, generator: torch.Generator) -> dict:
    """The run's planner with ``sampled_nodes`` on ``episodes``: demonstration transitions per episode, mean
    demonstration length (steps) and planning seconds per episode."""
    kwargs = {**planner_kwargs(cfg), "sampled_nodes": sampled_nodes}
    start = time.perf_counter()
    demos = plan_demonstrations(model, episodes, generator=generator, **kwargs)
    seconds = time.perf_counter() - start
    n_episodes = int(split_episodes(episodes)[1].max()) + 1
    n_demos = int(demos["next", "done"].sum())
    return {"transitions": demos.shape[0] / n_episodes, "length": demos.shape[0] / max(n_demos, 1),
            "seconds": seconds / n_episodes}


def main(argv: list[str]) -> None:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return
    run_dir = Path(argv[0])
    cfg, model, actor, rl, _, ckpt = load_run(run_dir, argv[1:])
    device = torch.device("cpu")
    n = cfg.eval.n_tasks

    def validation_tasks(collision_type: int) -> TransformedEnv:
        # a fresh env per rollout: its first reset draws the same validation tasks from the seed
        return TransformedEnv(
            ReachEnv(model, num_envs=n, seed=cfg.eval.seed, max_steps=cfg.env.max_steps, device=device),
            Compose(CollisionHandling(collision_type), make_observation_transform(cfg, model)),
        )

    print(f"run {run_dir}: {cfg.env.name}, method {cfg.logger.exp_name}; {n} validation tasks (eval.seed "
          f"{cfg.eval.seed}); the test tasks are not read")
    with torch.no_grad():
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            _, ro = evaluate(actor, env=validation_tasks(0), return_rollout=True)
        _, succ, coll = episode_outcomes(ro)
        print(f"policy (deterministic, as evaluated): success {succ.float().mean():.3f}  collision "
              f"{coll.float().mean():.3f}  time-out {(~succ & ~coll).float().mean():.3f}")

        # the policy's own episodes, sampled as in training, under the run's collision handling
        torch.manual_seed(0)
        rollout_env = validation_tasks(cfg.env.collision_type)
        with set_exploration_type(ExplorationType.RANDOM):
            episodes = rollout_env.rollout(cfg.env.max_steps, actor, break_when_any_done=False)
        print("start-to-goal paths on the roadmap of the sampling policy's episode on each validation task "
              f"(planner.d {cfg.planner.d}, {cfg.planner.method} search, goal node):")
        for k in SAMPLED_NODES:
            out = demonstration_yield(model, cfg, episodes, k, torch.Generator().manual_seed(0))
            failed = ~out["reached"]
            stretch = out["stretch"][out["found"]]
            print(f"  {k:4d} sampled nodes per episode (mean {out['nodes']:.0f} nodes): the episode reached its goal "
                  f"in {out['reached'].float().mean():.3f}; a path in {out['found'].float().mean():.3f} of the episodes, "
                  f"{out['found'][failed].float().mean():.3f} of the {int(failed.sum())} that failed; path length over "
                  f"the straight distance median "
                  f"{median(stretch):.2f} (90 %: {torch.quantile(stretch, 0.9).item() if stretch.numel() else float('nan'):.2f})")
        print(f"the run's planner (n_pairs {cfg.planner.n_pairs}, goal node {cfg.planner.goal_node}) on the same episodes:")
        for k in SAMPLED_NODES:
            cost = demonstration_cost(model, cfg, episodes, k, torch.Generator().manual_seed(0))
            print(f"  {k:4d} sampled nodes per episode: {cost['transitions']:.1f} demonstration transitions per episode, "
                  f"{cost['length']:.1f} steps a demonstration, {1000 * cost['seconds']:.1f} ms of planning per episode")

        print(f"batch: demo_fraction {cfg.replay_buffer.demo_fraction}, BC weights lambda1 {cfg.silp.lambda1} "
              f"lambda2 {cfg.silp.lambda2}, BC filter {cfg.silp.filter}; update ratio {cfg.optim.utd_ratio}, "
              f"batch {cfg.optim.batch_size}, networks {list(cfg.network.hidden_sizes)}")
        path = ckpt / "buffers" / "demos"
        if not (path / "storage").exists():
            print("no demonstration buffer in the checkpoint")
            return
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.replay_buffer.demo_size),
                                        checkpointer=FilledStorageCheckpointer())
        buffer.loads(path)
        size = len(buffer)
        ends = buffer.storage[:size]["next", "done"].sum().item()
        print(f"demonstration buffer: {size} transitions of {cfg.replay_buffer.demo_size} "
              f"({size / cfg.replay_buffer.demo_size:.2f} full), {int(ends)} demonstrations ending in it, mean "
              f"length {size / max(ends, 1):.1f} steps")
        rows = torch.randperm(size, generator=torch.Generator().manual_seed(0))[:CRITIC_ROWS]
        demos = buffer.storage[rows]
        states = demos.select(*model.state_keys)
        inputs = make_observation_transform(cfg, model)(states.clone(False))
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            pi = actor(inputs.clone(False))["action"]
        q_demo, q_pi = min_q(rl, inputs, demos["action"]), min_q(rl, inputs, pi)
        r_demo = model.step(states, demos["action"])[1].squeeze(-1)
        r_pi = model.step(states, pi)[1].squeeze(-1)
        better = r_demo > r_pi + 1e-6
        print(f"critic on {rows.numel()} stored demonstration transitions: Q(s, a_demo) - Q(s, pi(s)) median "
              f"{median(q_demo - q_pi):.3f}; Q prefers the demo's action in {(q_demo > q_pi).float().mean():.3f}, the "
              f"true one-step reward in {better.float().mean():.3f}; where the demo's action is truly better, Q "
              f"agrees in {(q_demo > q_pi)[better].float().mean():.3f}")


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(sys.argv[1:])
