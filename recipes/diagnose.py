"""Why does a trained policy fail? Failure analysis of a recipe checkpoint on the fixed test tasks.

    python recipes/diagnose.py RUN_DIR [hydra overrides the run was trained with]
    python recipes/diagnose.py runs/sac_silp_plus_ext/seed0 network.goal_relative=false
    python recipes/diagnose.py runs/ddpg_silp/seed0 algorithm=ddpg
    python recipes/diagnose.py runs/panda/seed0 env=panda_reach

Composes ``config/sac_silp.yaml`` with the overrides, rebuilds the run's task
model (``env.name``, ``env.model``) and networks, loads ``RUN_DIR/checkpoint``
(networks and both buffers), rolls the deterministic policy out on the 1000
test tasks of ``evaluate`` and prints:

* outcomes: success, collision, and time-outs (neither);
* the same for the stochastic policy SAC samples from during training;
* time-outs: whether the arm came to rest (|action| and joint travel over the
  last 10 steps), its final distance to the goal, and whether one action from
  the final state could reach the goal or get closer without a collision (best
  of 1,024 random actions through the task model's own step, swept collision
  check included; on the first 200 time-outs);
* the critic at those final states: Q of the policy's action, of the action
  that truly reaches furthest, of the step straight into the goal ball (through
  the model's Jacobian), and the true reward of the critic's own best action;
* success against task geometry: a box of the scene in the straight achieved-goal
  path or not (box scenes: ``"obstacle"`` holding AABBs), joint distance, and for
  the UR5e task the start in the front or the shoulder-flipped IK branch (see
  ``UR5eReach.task_branch``);
* the critic on its own training data: Q of terminal success, collision and other
  transitions of the demonstration and interaction buffers;
* what a uniformly random policy collides with (the model's collision reasons).

Everything is read from the model's named state keys (``"joint_position"``,
``"achieved_goal"``, the scene, ``"desired_goal"``, ``"goal_joint_position"``);
the networks' inputs are built from them by the run's observation transforms.
"""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp import CollisionHandling, ReachEnv
from torchrl_silp.data import FilledStorageCheckpointer
from torchrl_silp.eval import DEFAULT_TEST_SEED, episode_outcomes, evaluate
from torchrl_silp.models import UR5eReach
from torchrl_silp.recipes.builders import make_env, make_model, make_observation_transform, rl_loss_of
from torchrl_silp.recipes.checkpointing import load_trained_networks
from torchrl_silp.recipes.schema import load_config

CHUNK = 16384  # (state, candidate action) pairs per model step / critic call
MAX_ACTION_SEARCH = 200  # time-outs whose final state gets the one-action search


def min_q(rl, inputs: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
    """The pessimistic Q (minimum over the ensemble) of SAC / TD3, or the DDPG critic's value.

    ``inputs`` holds what the critic reads besides the action (the networks' inputs and the
    named state); it is broadcast over the leading dimensions of ``action``.
    """
    name = "qvalue_network" if hasattr(rl, "qvalue_network") else "value_network"
    net, params = getattr(rl, name), getattr(rl, f"{name}_params")
    batch = action.shape[:-1]
    td = inputs.select(*(k for k in net.in_keys if k != "action"), strict=False)
    while td.batch_dims < len(batch):
        td = td.unsqueeze(-1)
    td = td.expand(*batch).clone(False)
    td.set("action", action)
    members = [params[i] for i in range(params.batch_size[0])] if params.batch_dims else [params]
    values = []
    for p in members:
        with p.to_module(net):
            values.append(net(td.clone(False))["state_action_value"].squeeze(-1))
    return torch.stack(values).amin(0)


def median(x: torch.Tensor) -> float:
    return x.float().median().item() if x.numel() else float("nan")


def by_rows(fn, n: int, rows: int) -> torch.Tensor:
    """``fn(slice)`` over ``n`` rows, ``rows`` at a time, concatenated: bounds the memory of a big candidate batch."""
    return torch.cat([fn(slice(i, min(i + rows, n))) for i in range(0, n, rows)])


def boxes(scene: torch.Tensor) -> torch.Tensor | None:
    """``(..., K, 6)`` AABBs ``(xmin, xmax, ymin, ymax, zmin, zmax)`` of a box scene, or None."""
    if scene.shape[-1] % 6:
        return None
    return scene.reshape(*scene.shape[:-1], -1, 6)


def load_run(run_dir: Path, overrides: list[str]):
    """A run's checkpoint on the CPU for a diagnosis: ``(cfg, model, actor, rl, state, ckpt)``.

    ``cfg`` is ``config/sac_silp.yaml`` with the overrides the run was trained with; ``actor`` the policy
    the run evaluated (the averaged one under ``eval.actor_average_decay``), ``rl`` the actor-critic loss
    holding the critic, ``state`` the checkpoint's training state. TorchRL's INFO lines, which it writes
    to stdout, are silenced: a diagnosis prints its report there.
    """
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    ckpt = run_dir / "checkpoint"
    if not (ckpt / "state.pt").exists():
        raise FileNotFoundError(f"no checkpoint under {run_dir} (expected {ckpt / 'state.pt'})")
    cfg = load_config("sac_silp", overrides)
    device = torch.device("cpu")
    model = make_model(cfg, device)
    env = make_env(cfg, model, device, seed=0)  # specs only
    actor, loss, state = load_trained_networks(cfg, model, env, ckpt, device)
    return cfg, model, actor, rl_loss_of(loss), state, ckpt


def main(argv: list[str]) -> None:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return
    candidates = 1024
    cfg, model, actor, rl, state, ckpt = load_run(Path(argv[0]), argv[1:])
    device = torch.device("cpu")
    if state.get("averaged_actor") is not None:
        print("policy: the averaged actor the run evaluated (eval.actor_average_decay)")
    cfg_key, ag_key, dg_key = model.config_key, model.achieved_goal_key, model.desired_goal_key

    def inputs(states: TensorDictBase) -> TensorDictBase:
        """The networks' inputs at named states (the run's observation transforms)."""
        return make_observation_transform(cfg, model)(states.select(*model.state_keys).clone(False))

    def test_tasks() -> TransformedEnv:
        # a fresh env per rollout: each first reset draws the same 1000 tasks from the seed
        return TransformedEnv(
            ReachEnv(model, num_envs=1000, seed=DEFAULT_TEST_SEED, max_steps=cfg.env.max_steps, device=device),
            Compose(CollisionHandling(0), make_observation_transform(cfg, model)),
        )

    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        _, ro = evaluate(actor, env=test_tasks(), return_rollout=True)
        _, succ, coll = episode_outcomes(ro)
        timeout = ~succ & ~coll
        print(f"outcomes: success {succ.float().mean():.3f}  collision {coll.float().mean():.3f}  "
              f"time-out {timeout.float().mean():.3f}")

        # the same tasks under the sampling policy SAC trains with: a gap to the deterministic
        # policy means the noise, not the mean action, finishes the reaches the critic was trained on
        noisy = test_tasks()
        torch.manual_seed(0)
        with set_exploration_type(ExplorationType.RANDOM):
            noisy_ro = noisy.rollout(noisy.max_steps, actor, break_when_all_done=True, break_when_any_done=False)
        _, n_succ, n_coll = episode_outcomes(noisy_ro)
        print(f"the sampling (stochastic) policy on the same tasks: success {n_succ.float().mean():.3f}  "
              f"collision {n_coll.float().mean():.3f}")

        ended = ro["next"][timeout]  # [F, T]
        if ended.shape[0]:
            last = ended[:, -1].select(*model.state_keys)  # the time-outs' final states
            act = ro["action"][timeout][:, -10:]
            q = ended[cfg_key]
            dist = (last[ag_key] - last[dg_key]).norm(dim=-1)
            quantiles = torch.quantile(dist, torch.tensor([.1, .25, .5, .75, .9], dtype=dist.dtype))
            print(f"time-outs: mean |action| over the last 10 steps {act.abs().mean():.4f}, median joint travel "
                  f"{median((q[:, -1] - q[:, -10]).abs().sum(-1)):.2e} rad; final distance to goal quantiles "
                  f"(10/25/50/75/90 %) {[round(v, 3) for v in quantiles.tolist()]}")
            # what one action could do from there: on the first MAX_ACTION_SEARCH time-outs (a swept
            # motion check per candidate action)
            last = last[:MAX_ACTION_SEARCH]
            dist = dist[:MAX_ACTION_SEARCH]
            F, A = last.shape[0], model.action_dim
            print(f"  one action from the final state ({F} of the time-outs, {candidates} random actions each):")
            a = torch.rand(candidates, A, generator=torch.Generator().manual_seed(0)) * 2 - 1
            S = last.unsqueeze(1).expand(F, candidates)
            Acts = a.expand(F, candidates, A)
            per_call = max(1, CHUNK // candidates)  # a step checks ~15 configurations along its motion
            reward = by_rows(lambda r: model.step(S[r], Acts[r])[1].squeeze(-1), F, per_call)
            best = reward.max(-1).values
            print(f"    reaches the goal: {(best >= model.success_reward).float().mean():.3f}; "
                  f"gets > 1 cm closer without collision: {(best > -dist + 0.01).float().mean():.3f}")
            last_in = inputs(last)
            qa = by_rows(lambda r: min_q(rl, last_in[r], Acts[r]), F, per_call)
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                pi = actor(last_in.clone(False))["action"]
            rows = torch.arange(F)
            q_pi = median(min_q(rl, last_in, pi))
            print(f"  critic: Q(s, pi(s)) median {q_pi:.3f}; Q(s, best true action) median "
                  f"{median(qa[rows, reward.argmax(-1)]):.3f} (its reward median {median(reward[rows, reward.argmax(-1)]):.3f}); "
                  f"true reward of the critic's best action median {median(reward[rows, qa.argmax(-1)]):.3f}")
            # the step straight into the ball: the action that moves the achieved goal 2 cm inside it,
            # through the model's finite-difference Jacobian; its true Q is its reward when that is +1
            eps = 1e-3
            goal0 = model.transition(last, torch.zeros(F, A))[ag_key]
            jac = torch.stack([(model.transition(last, torch.eye(A)[i].expand(F, A) * eps)[ag_key] - goal0) / eps
                               for i in range(A)], -1)  # (F, goal_dim, A)
            to_goal = last[dg_key] - last[ag_key]
            want = to_goal * ((dist - model.success_distance + 0.02) / dist).unsqueeze(-1)
            direct = torch.linalg.lstsq(jac, want.unsqueeze(-1)).solution.squeeze(-1).clamp(-1, 1)
            direct_reward = model.step(last, direct)[1].squeeze(-1)
            print(f"  the step 2 cm into the ball: reaches the goal {(direct_reward >= model.success_reward).float().mean():.3f}, "
                  f"max |action| median {median(direct.abs().amax(-1)):.3f}; critic Q median "
                  f"{median(min_q(rl, last_in, direct)):.3f} against Q(s, pi(s)) {q_pi:.3f}")

        first = ro[:, 0]
        q0, start, goal = first[cfg_key], first[ag_key], first[dg_key]
        scene = first[model.scene_keys[0]] if model.scene_keys else None
        box = boxes(scene) if scene is not None else None
        if box is not None:
            t = torch.linspace(0, 1, 50).view(1, 50, 1)
            pts = (start.unsqueeze(1) + t * (goal - start).unsqueeze(1)).unsqueeze(2)  # (n, 50, 1, 3)
            near = (pts >= box[:, None, :, 0::2] - 0.05) & (pts <= box[:, None, :, 1::2] + 0.05)
            blocked = near.all(-1).any(-1).any(-1)
            print(f"geometry: box within 5 cm of the straight achieved-goal path in {blocked.float().mean():.3f} of the "
                  f"tasks; success there {succ[blocked].float().mean():.3f}, elsewhere {succ[~blocked].float().mean():.3f}")
        gap = (first[model.goal_config_key] - q0).abs().amax(-1)
        for lo, hi in ((0, 1), (1, 2), (2, 3), (3, 10)):
            m = (gap >= lo) & (gap < hi)
            if m.any():
                print(f"  largest joint gap start->goal {lo}-{hi} rad: {int(m.sum())} tasks, success {succ[m].float().mean():.3f}")
        if isinstance(model, UR5eReach):  # the UR5e's two inverse-kinematics branches
            last_q = ro["next", cfg_key][:, -1]
            flipped = model.reach_along_pan(q0, start) < 0
            for name, m in (("front branch", ~flipped), ("shoulder-flipped branch", flipped)):
                if m.any():
                    print(f"  start in the {name}: {int(m.sum())} tasks, success {succ[m].float().mean():.3f}, "
                          f"time-outs ending with |pan| > pi {int((timeout & m & (last_q[:, 0].abs() > math.pi)).sum())}")

        for part, capacity in (("demos", cfg.replay_buffer.demo_size), ("interaction", cfg.replay_buffer.size)):
            path = ckpt / "buffers" / part
            if not (path / "storage").exists():
                continue
            buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity), checkpointer=FilledStorageCheckpointer())
            buffer.loads(path)
            data = buffer.storage[: len(buffer)]
            r = data["next", "reward"].squeeze(-1)
            terminal = data["next", "terminated"].squeeze(-1)
            collided = r <= model.collision_reward
            groups = {"terminal success": terminal & (r > 0), "collision": collided, "other": ~terminal & ~collided}
            line = []
            for name, mask in groups.items():
                idx = mask.nonzero().squeeze(-1)[:5000]
                if idx.numel():
                    line.append(f"{name} ({mask.float().mean():.3f} of it) Q median "
                                f"{median(min_q(rl, data[idx], data['action'][idx])):.3f}")
            print(f"critic on the {part} buffer ({len(buffer)} transitions): " + "; ".join(line))

        rnd = TransformedEnv(ReachEnv(model, num_envs=256, seed=0, max_steps=cfg.env.max_steps, device=device),
                             CollisionHandling(2))
        flags = rnd.rollout(cfg.env.max_steps, break_when_any_done=False)["next", "collision_reason"].squeeze(-1)
        hits = max(int((flags != 0).sum()), 1)
        shares = {name: int(((flags & (1 << bit)) != 0).sum()) / hits for bit, name in enumerate(model.collision_reasons)}
        print(f"random policy: {(flags != 0).float().mean():.3f} of steps collide; reasons "
              + ", ".join(f"{k} {v:.2f}" for k, v in shares.items()))


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(sys.argv[1:])
