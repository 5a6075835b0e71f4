"""Builders shared by every training recipe (TorchRL recipe style: construction here, the loop in one place)."""

from __future__ import annotations

import json
import math
import os
import random
import shutil
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModule, TensorDictSequential
from tensordict.nn.distributions import NormalParamExtractor
from torch import nn, optim
from torchrl.collectors import Collector
from torchrl.envs import Compose, InitTracker, RewardSum, TransformedEnv
from torchrl.modules import MLP, AdditiveGaussianModule, ProbabilisticActor, TanhModule, ValueOperator
from torchrl.modules.distributions import TanhNormal
from torchrl.objectives import DDPGLoss, SACLoss, SoftUpdate, TD3Loss

from torchrl_silp import UR5eReachEnv
from torchrl_silp.data import DemoReplayBuffer, GoalRelabelingReplayBuffer, MixedReplay
from torchrl_silp.objectives import SILPLoss

ALGORITHMS = ("sac", "ddpg", "td3")
EXPLORATION_MODES = ("gp", "random", "none")
LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "", None)  # "" or null: no logger


def check_choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")


def check_device(value) -> None:
    if value not in ("cpu", "cuda", "auto") and not str(value).startswith("cuda:"):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {value!r}")


def start_run(cfg) -> tuple[torch.device, Path]:
    """What every recipe does first: ``(device, run_dir)``.

    Resolves ``cfg.device`` ("auto": CUDA when there is one), sets torch's
    threads (``cfg.threads``, 0 leaves the default), seeds torch, numpy and
    ``random`` with ``cfg.seed``, creates ``cfg.run_dir`` and saves the resolved
    config there as ``config.yaml``: what rebuilds a run's networks from its
    checkpoint (``load_trained_networks``) and what a report cites.
    """
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    return device, run_dir


# ---------------------------------------------------------------- environment
def make_env(cfg, device, seed: int) -> TransformedEnv:
    """The batched training env with the transforms the loop reads (is_init, episode_reward)."""
    base = UR5eReachEnv(
        num_envs=cfg.env.num_envs,
        seed=seed,
        max_steps=cfg.env.max_steps,
        collision_type=cfg.env.collision_type,
        workspace_exit=cfg.env.workspace_exit,
        task_branch=cfg.env.task_branch,
        device=device,
    )
    return TransformedEnv(base, Compose(InitTracker(), RewardSum()))


# --------------------------------------------------------------------- models
class GoalRelativeMLP(nn.Module):
    """An MLP that also sees the TCP-to-goal vector of the observation.

    The 15-D observation holds the TCP (3:6) and the goal (12:15) separately;
    success is decided at the 5 cm scale of their difference, which an MLP
    must otherwise learn to subtract. The difference is appended to the
    inputs (observation first, then any further input such as the action).
    """

    def __init__(self, mlp: nn.Module):
        super().__init__()
        self.mlp = mlp

    def forward(self, observation: torch.Tensor, *others: torch.Tensor) -> torch.Tensor:
        to_goal = observation[..., 12:15] - observation[..., 3:6]
        return self.mlp(observation, to_goal, *others)


class NextTCPFeatureQ(nn.Module):
    """A Q-network that also sees where the action takes the TCP, through the env's kinematic model.

    Success is a step in the *next* TCP's distance to the goal (5 cm), so a
    Q-network on ``(s, a)`` must learn the arm's kinematics to place that step;
    near the goal it blurs it, and the policy comes to rest just outside the
    5 cm ball. The env's transition ``f_s`` (the model SILP+ already uses for
    its reward filter) gives the next TCP exactly: its vector to the goal is
    appended to the inputs. The model is differentiable in the action, so the
    actor's gradient flows through it.
    """

    def __init__(self, inner: nn.Module, env: UR5eReachEnv):
        super().__init__()
        self.inner = inner
        # a plain attribute, not a submodule: the env's tensors are no parameters of the critic
        self.__dict__["model"] = env

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        next_tcp = self.model.transition(observation, action)[..., 3:6]
        return self.inner(observation, action, observation[..., 12:15] - next_tcp)


def _mlp(cfg, out_features: int, device) -> nn.Module:
    mlp = MLP(num_cells=list(cfg.network.hidden_sizes), out_features=out_features, activation_class=nn.ReLU, device=device)
    return GoalRelativeMLP(mlp) if cfg.network.goal_relative else mlp


def make_actor_critic(cfg, env, device):
    """Actor (stochastic TanhNormal for SAC, deterministic tanh for DDPG/TD3) and Q-network."""
    check_choice("algorithm", cfg.algorithm, ALGORITHMS)
    spec = env.action_spec_unbatched.to(device)
    if cfg.algorithm == "sac":
        net = nn.Sequential(
            _mlp(cfg, 2 * spec.shape[-1], device),
            NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
        )
        actor = ProbabilisticActor(
            TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
            default_interaction_type=InteractionType.RANDOM,
            return_log_prob=False,
        )
    else:
        actor = TensorDictSequential(
            TensorDictModule(_mlp(cfg, spec.shape[-1], device), in_keys=["observation"], out_keys=["param"]),
            TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
        )
    q_net = _mlp(cfg, 1, device)
    if cfg.network.get("next_tcp_feature", False):
        q_net = NextTCPFeatureQ(q_net, env.base_env)
    critic = ValueOperator(q_net, in_keys=["observation", "action"])
    with torch.no_grad():
        td = env.fake_tensordict().to(device)
        actor(td)
        critic(td)
    return actor, critic


def make_exploration_policy(cfg, actor, env, device):
    """The collector's policy: the actor, DDPG/TD3 Gaussian noise, then collision-recovery exploration."""
    check_choice("exploration.mode", cfg.exploration.mode, EXPLORATION_MODES)
    modules = [actor]
    if cfg.algorithm != "sac":
        modules.append(
            AdditiveGaussianModule(
                spec=env.action_spec_unbatched.to(device),
                sigma_init=cfg.exploration.sigma,
                sigma_end=cfg.exploration.sigma,
                annealing_num_steps=1,
                device=device,
            )
        )
    if cfg.exploration.mode != "none":
        from torchrl_silp.modules import GPGuidedExploration

        modules.append(
            GPGuidedExploration(
                env.base_env,
                mode=cfg.exploration.mode,
                num_candidates=cfg.exploration.n_candidates,
                history_size=cfg.env.max_steps + 1,
            ).to(device)
        )
    return TensorDictSequential(*modules) if len(modules) > 1 else actor


def make_collector(cfg, env, policy, total_frames: int, device) -> Collector:
    return Collector(
        env,
        policy,
        frames_per_batch=cfg.collector.frames_per_batch,
        total_frames=total_frames,
        init_random_frames=cfg.collector.init_random_frames,
        device=device,
    )


# ------------------------------------------------------------------- buffers
def make_buffers(cfg, env, device) -> MixedReplay:
    planner = {
        "d": cfg.planner.d,
        "n_pairs": cfg.planner.n_pairs,
        "step_size": cfg.planner.step_size,
        "method": cfg.planner.method,
        "goal_node": bool(cfg.planner.goal_node),
    }
    demos = DemoReplayBuffer(env.base_env, capacity=cfg.replay_buffer.demo_size, device=device, planner_kwargs=planner)
    interaction = None
    if cfg.replay_buffer.get("her", False):
        # the *-HER baselines: TorchRL's hindsight relabelling on the interaction data
        interaction = GoalRelabelingReplayBuffer(
            env.base_env,
            her_ratio=cfg.replay_buffer.her_ratio,
            strategy=cfg.replay_buffer.her_strategy,
            capacity=cfg.replay_buffer.size,
            device=device,
        )
    return MixedReplay(
        demos,
        interaction,
        interaction_capacity=cfg.replay_buffer.size,
        demo_fraction=cfg.replay_buffer.demo_fraction if cfg.silp.demos else 0.0,
        batch_size=cfg.optim.batch_size,
        device=device,
    )


class EpisodeAssembler:
    """Joins the pieces of episodes that span collector batches, by ``("collector", "traj_ids")``.

    ``push(batch)`` returns the transitions of every episode that finished in
    this batch (whole episodes, in time order) and keeps the unfinished tails
    for the next call, so the planner only ever sees complete episodes.
    """

    def __init__(self):
        self.pending: TensorDictBase | None = None

    def push(self, batch: TensorDictBase) -> TensorDictBase | None:
        flat = batch.reshape(-1)
        if self.pending is not None and self.pending.batch_size.numel():
            flat = torch.cat([self.pending, flat])
        ids = flat["collector", "traj_ids"].reshape(-1)
        done = flat["next", "done"].reshape(-1)
        finished = torch.isin(ids, ids[done])
        self.pending = flat[~finished]
        if not finished.any():
            return None
        out = flat[finished]
        # stable sort by trajectory keeps each episode's steps in time order
        order = torch.sort(out["collector", "traj_ids"].reshape(-1), stable=True).indices
        return out[order]

    def flush(self) -> TensorDictBase | None:
        out, self.pending = self.pending, None
        return out if out is not None and out.batch_size.numel() else None


def cut_episodes(pieces: TensorDictBase) -> TensorDictBase:
    """Unfinished episodes (what ``EpisodeAssembler.flush`` returns) as truncated whole ones.

    Each trajectory's steps are made contiguous and in time order and its last
    step is flagged truncated and done: what a buffer that reads episode
    boundaries from ``("next", "done")`` (hindsight relabelling) needs.
    """
    ids = pieces["collector", "traj_ids"].reshape(-1)
    order = torch.sort(ids, stable=True).indices
    out = pieces[order].clone()
    ids = ids[order]
    last = torch.ones_like(ids, dtype=torch.bool)
    last[:-1] = ids[1:] != ids[:-1]
    last = last.view(-1, 1)
    out["next", "truncated"] = out["next", "truncated"] | last
    out["next", "done"] = out["next", "done"] | last
    return out


# ---------------------------------------------------------------------- loss
def make_loss(cfg, actor, critic, env):
    """The RL loss (SAC / DDPG / TD3), wrapped by SILPLoss when the BC term is on, and its target updater."""
    if cfg.algorithm == "sac":
        rl = SACLoss(
            actor_network=actor,
            qvalue_network=critic,
            num_qvalue_nets=2,
            loss_function="l2",
            delay_actor=False,
            delay_qvalue=True,
            alpha_init=cfg.optim.alpha_init,
            min_alpha=cfg.optim.get("min_alpha", None),
            target_entropy=cfg.optim.get("target_entropy", "auto"),
        )
    elif cfg.algorithm == "ddpg":
        rl = DDPGLoss(actor_network=actor, value_network=critic, delay_actor=True, delay_value=True, loss_function="l2")
    else:
        rl = TD3Loss(actor_network=actor, qvalue_network=critic, action_spec=env.action_spec_unbatched, loss_function="l2")
    rl.make_value_estimator(gamma=cfg.optim.gamma)
    if cfg.algorithm == "sac":
        # SACLoss registers its target-entropy buffer on first use: create it now, so a
        # fresh loss and a checkpointed one have the same state_dict keys on resume
        _ = rl.target_entropy
    updater = SoftUpdate(rl, tau=cfg.optim.tau)
    if not cfg.silp.bc:
        return rl, updater
    loss = SILPLoss(
        rl,
        env.base_env,
        filter=cfg.silp.filter,
        lambda1=cfg.silp.lambda1,
        lambda2=cfg.silp.lambda2,
        k=cfg.silp.k,
        gamma=cfg.optim.gamma,
    )
    return loss, updater


def rl_loss_of(loss):
    return loss.rl_loss if isinstance(loss, SILPLoss) else loss


def make_optimizers(cfg, loss) -> dict[str, optim.Optimizer]:
    rl = rl_loss_of(loss)
    actor_params = list(rl.actor_network_params.flatten_keys().values())
    critic_params = (
        rl.qvalue_network_params if hasattr(rl, "qvalue_network_params") else rl.value_network_params
    )
    opts = {
        "actor": optim.Adam(actor_params, lr=cfg.optim.lr),
        "critic": optim.Adam(list(critic_params.flatten_keys().values()), lr=cfg.optim.lr),
    }
    if hasattr(rl, "log_alpha") and cfg.algorithm == "sac":
        opts["alpha"] = optim.Adam([rl.log_alpha], lr=cfg.optim.lr)
    return opts


# ------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, state: dict, buffers: MixedReplay, assembler: EpisodeAssembler) -> None:
    """Write everything a resumed run needs; atomically (a killed save leaves the previous one)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    torch.save(state, tmp / "state.pt")
    buffers.dumps(tmp / "buffers")
    if assembler.pending is not None and assembler.pending.batch_size.numel():
        torch.save(assembler.pending, tmp / "pending_episodes.pt")
    old = path.with_name(path.name + ".old")
    if path.exists():
        os.replace(path, old)
    os.replace(tmp, path)
    if old.exists():
        shutil.rmtree(old)


def _checkpoint_dir(path: Path) -> Path | None:
    # a run killed between the two renames of save_checkpoint left only ".old"
    path = Path(path)
    for candidate in (path, path.with_name(path.name + ".old")):
        if (candidate / "state.pt").exists():
            return candidate
    return None


def load_checkpoint(path: Path, buffers: MixedReplay, assembler: EpisodeAssembler) -> dict:
    found = _checkpoint_dir(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    path = found
    state = torch.load(path / "state.pt", weights_only=False)
    buffers.loads(path / "buffers")
    pending = path / "pending_episodes.pt"
    if pending.exists():
        assembler.pending = torch.load(pending, weights_only=False)
    return state


def checkpoint_exists(path: Path) -> bool:
    return _checkpoint_dir(path) is not None


def load_trained_networks(cfg, env, path: Path, device) -> tuple:
    """A run's networks, rebuilt from its config and loaded from its checkpoint: ``(actor, loss, state)``.

    ``actor`` holds the parameters the run evaluated: the average of the
    actor's parameters when the run kept one (``eval.actor_average_decay``),
    else the online actor; ``loss`` holds the online networks (critic included).
    """
    found = _checkpoint_dir(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    actor, critic = make_actor_critic(cfg, env, device)
    loss, _ = make_loss(cfg, actor, critic, env)
    state = torch.load(found / "state.pt", map_location=device, weights_only=False)
    loss.load_state_dict(state["loss"])
    if state.get("averaged_actor") is not None:
        state["averaged_actor"].to(device).to_module(actor)
    return actor, loss, state


# ------------------------------------------------------------------ reports
def log_metrics(logger, metrics: dict, step: int) -> None:
    if logger is None:
        return
    for name, value in metrics.items():
        if isinstance(value, torch.Tensor):
            value = value.item()
        if value is None or (isinstance(value, float) and math.isnan(value)):
            continue
        logger.log_scalar(name, value, step)


def plot_learning_curve(history: list[dict], path: Path, label: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    if history:
        ax.plot([h["episodes"] for h in history], [h["success_rate"] for h in history], marker="o", label=label)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("test success rate")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_json(path: Path, payload: dict) -> None:
    Path(path).write_text(json.dumps(payload, indent=2, default=float))


def write_results(run_dir: Path, summary: dict, history: list[dict]) -> None:
    """What every recipe leaves for a sweep and its report: ``summary.json`` and ``history.json``; prints the summary."""
    write_json(Path(run_dir) / "summary.json", summary)
    write_json(Path(run_dir) / "history.json", {"history": history})
    print("\n".join(f"{k:>30s}: {v}" for k, v in summary.items()))

