"""Why does a trained policy fail? Failure analysis of a recipe checkpoint on the fixed test tasks.

    python recipes/diagnose.py RUN_DIR [hydra overrides the run was trained with]
    python recipes/diagnose.py runs/sac_silp/seed0 network.goal_relative=true
    python recipes/diagnose.py runs/ddpg_silp/seed0 algorithm=ddpg

Loads ``RUN_DIR/checkpoint`` (networks and both buffers), rolls the
deterministic policy out on the 1000 test tasks of ``evaluate`` and prints:

* outcomes: success, collision, and time-outs (neither);
* the same for the stochastic policy SAC samples from during training;
* time-outs: whether the arm came to rest (|action| and joint travel over the
  last 10 steps), its final distance to the goal, and whether one action from
  the final state could reach the goal or get closer without a collision (best
  of 2,048 random actions through the env's own model);
* the critic at those final states: Q of the policy's action, of the action
  that truly reaches furthest, of the step straight into the goal ball (through
  the model's Jacobian), and the true reward of the critic's own best action;
* success against task geometry: box in the straight TCP path or not, joint distance,
  start in the front or the shoulder-flipped IK branch (see ``UR5eReachEnv.task_branch``);
* the critic on its own training data: Q of terminal success, collision and other
  transitions of the demonstration and interaction buffers;
* what a uniformly random policy collides with (collision reasons).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).parent))
from utils import load_trained_networks, make_env, rl_loss_of  # noqa: E402

from torchrl_silp import CollisionReason, UR5eReachEnv  # noqa: E402
from torchrl_silp.eval import DEFAULT_TEST_SEED, episode_outcomes, evaluate  # noqa: E402


def min_q(rl, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The pessimistic Q (minimum over the ensemble) of SAC / TD3, or the DDPG critic's value."""
    name = "qvalue_network" if hasattr(rl, "qvalue_network") else "value_network"
    net, params = getattr(rl, name), getattr(rl, f"{name}_params")
    td = TensorDict(observation=obs, action=action, batch_size=obs.shape[:-1])
    members = [params[i] for i in range(params.batch_size[0])] if params.batch_dims else [params]
    values = []
    for p in members:
        with p.to_module(net):
            values.append(net(td.clone())["state_action_value"].squeeze(-1))
    return torch.stack(values).amin(0)


def median(x: torch.Tensor) -> float:
    return x.float().median().item() if x.numel() else float("nan")


def main(argv: list[str]) -> None:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return
    run_dir, overrides = Path(argv[0]), argv[1:]
    candidates = 2048
    ckpt = run_dir / "checkpoint"
    if not (ckpt / "state.pt").exists():
        raise FileNotFoundError(f"no checkpoint under {run_dir} (expected {ckpt / 'state.pt'})")
    with initialize_config_dir(config_dir=str(Path(__file__).parent / "config"), version_base="1.3"):
        cfg = compose(config_name="sac_silp", overrides=overrides)
    device = torch.device("cpu")
    env = make_env(cfg, device, seed=0)
    # the actor the run evaluated (the averaged one under eval.actor_average_decay): diagnose that policy
    actor, loss, state = load_trained_networks(cfg, env, ckpt, device)
    rl = rl_loss_of(loss)
    if state.get("averaged_actor") is not None:
        print("policy: the averaged actor the run evaluated (eval.actor_average_decay)")

    def test_tasks() -> UR5eReachEnv:
        # a fresh env per rollout: each first reset draws the same 1000 tasks from the seed
        return UR5eReachEnv(
            num_envs=1000, seed=DEFAULT_TEST_SEED, collision_type=0, max_steps=cfg.env.max_steps,
            workspace_exit=cfg.env.workspace_exit, task_branch=cfg.env.task_branch,
        )

    test = test_tasks()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        _, ro = evaluate(actor, env=test, return_rollout=True)
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

        last = ro["next", "observation"][timeout][:, -1]
        if last.shape[0]:
            act = ro["action"][timeout][:, -10:]
            q = ro["next", "observation"][timeout][..., :3]
            dist = (last[:, 3:6] - last[:, 12:15]).norm(dim=-1)
            print(f"time-outs: mean |action| over the last 10 steps {act.abs().mean():.4f}, median joint travel "
                  f"{median((q[:, -1] - q[:, -10]).abs().sum(-1)):.2e} rad; final distance to goal quantiles "
                  f"(10/25/50/75/90 %) {[round(v, 3) for v in torch.quantile(dist, torch.tensor([.1, .25, .5, .75, .9])).tolist()]}")
            F = last.shape[0]
            a = torch.rand(candidates, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
            S, A = last.unsqueeze(1).expand(F, candidates, 15), a.expand(F, candidates, 3)
            reward = test.reward(S, test.transition(S, A)).squeeze(-1)
            best = reward.max(-1).values
            print(f"  from the final state one action reaches the goal: {(best >= 1).float().mean():.3f}; "
                  f"gets > 1 cm closer without collision: {(best > -dist + 0.01).float().mean():.3f}")
            qa = min_q(rl, S, A)
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                pi = actor(TensorDict(observation=last, batch_size=[F]))["action"]
            rows = torch.arange(F)
            q_pi = median(min_q(rl, last, pi))
            print(f"  critic: Q(s, pi(s)) median {q_pi:.3f}; Q(s, best true action) median "
                  f"{median(qa[rows, reward.argmax(-1)]):.3f} (its reward median {median(reward[rows, reward.argmax(-1)]):.3f}); "
                  f"true reward of the critic's best action median {median(reward[rows, qa.argmax(-1)]):.3f}")
            # the step straight into the ball: the action that moves the TCP 2 cm inside it,
            # through the model's finite-difference Jacobian; its true Q is its reward when that is +1
            eps = 1e-3
            tcp0 = test.transition(last, torch.zeros(F, 3))[:, 3:6]
            jac = torch.stack([(test.transition(last, torch.eye(3)[i].expand(F, 3) * eps)[:, 3:6] - tcp0) / eps
                               for i in range(3)], -1)
            to_goal = last[:, 12:15] - last[:, 3:6]
            want = to_goal * ((dist - test.success_distance + 0.02) / dist).unsqueeze(-1)
            direct = torch.linalg.lstsq(jac, want.unsqueeze(-1)).solution.squeeze(-1).clamp(-1, 1)
            direct_reward = test.transition_reward(last, direct)[1].squeeze(-1)
            print(f"  the step 2 cm into the ball: reaches the goal {(direct_reward >= 1).float().mean():.3f}, "
                  f"max |action| median {median(direct.abs().amax(-1)):.3f}; critic Q median "
                  f"{median(min_q(rl, last, direct)):.3f} against Q(s, pi(s)) {q_pi:.3f}")

        last_q = ro["next", "observation"][:, -1, :3]
        o = ro["observation"][:, 0]
        tcp, box, goal = o[:, 3:6], o[:, 6:12], o[:, 12:15]
        t = torch.linspace(0, 1, 50).view(1, 50, 1)
        pts = tcp.unsqueeze(1) + t * (goal - tcp).unsqueeze(1)
        blocked = ((pts >= box[:, None, 0::2] - 0.05) & (pts <= box[:, None, 1::2] + 0.05)).all(-1).any(-1)
        print(f"geometry: box within 5 cm of the straight TCP path in {blocked.float().mean():.3f} of the tasks; "
              f"success there {succ[blocked].float().mean():.3f}, elsewhere {succ[~blocked].float().mean():.3f}")
        gap = (ro["goal_q"][:, 0] - o[:, :3]).abs().amax(-1)
        for lo, hi in ((0, 1), (1, 2), (2, 3), (3, 10)):
            m = (gap >= lo) & (gap < hi)
            if m.any():
                print(f"  largest joint gap start->goal {lo}-{hi} rad: {int(m.sum())} tasks, success {succ[m].float().mean():.3f}")
        flipped = UR5eReachEnv.reach_along_pan(o[:, :3], tcp) < 0
        for name, m in (("front branch", ~flipped), ("shoulder-flipped branch", flipped)):
            if m.any():
                print(f"  start in the {name}: {int(m.sum())} tasks, success {succ[m].float().mean():.3f}, "
                      f"time-outs ending with |pan| > pi {int((timeout & m & (last_q[:, 0].abs() > math.pi)).sum())}")

        for part, capacity in (("demos", cfg.replay_buffer.demo_size), ("interaction", cfg.replay_buffer.size)):
            path = ckpt / "buffers" / part
            if not (path / "storage").exists():
                continue
            buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity))
            buffer.loads(path)
            data = buffer.storage[: len(buffer)]
            r = data["next", "reward"].squeeze(-1)
            terminal = data["next", "terminated"].squeeze(-1)
            groups = {"terminal success": terminal & (r > 0), "collision": r <= -10, "other": ~terminal & (r > -10)}
            line = []
            for name, mask in groups.items():
                idx = mask.nonzero().squeeze(-1)[:5000]
                if idx.numel():
                    line.append(f"{name} ({mask.float().mean():.3f} of it) Q median "
                                f"{median(min_q(rl, data['observation'][idx], data['action'][idx])):.3f}")
            print(f"critic on the {part} buffer ({len(buffer)} transitions): " + "; ".join(line))

        rnd = UR5eReachEnv(num_envs=256, seed=0, collision_type=2, max_steps=cfg.env.max_steps)
        flags = rnd.rollout(cfg.env.max_steps, break_when_any_done=False)["next", "collision_reason"].squeeze(-1)
        hits = max(int((flags != 0).sum()), 1)
        shares = {n.lower(): int(((flags & getattr(CollisionReason, n)) != 0).sum()) / hits
                  for n in ("OBSTACLE", "TABLE", "SELF", "WORKSPACE")}
        print(f"random policy: {(flags != 0).float().mean():.3f} of steps collide; reasons "
              + ", ".join(f"{k} {v:.2f}" for k, v in shares.items()))


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(sys.argv[1:])
