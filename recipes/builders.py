"""The builders of a training run (TorchRL recipe style: construction here, the loop in the script).

Each ``make_*`` takes the run's config (``recipes/config/sac_silp.yaml``) and returns stock TorchRL /
torchrl_silp objects: the task model and its env, the networks, the exploration and the collector's
policy, the replay buffers, the loss and its optimisers. The method itself (task models, transforms,
planner, buffers, loss, exploration, networks) lives in the package.

Examples:
    >>> import torch
    >>> from torchrl_silp.recipes.schema import load_config
    >>> cfg = load_config("sac_silp", ["env.num_envs=2"])
    >>> model = make_model(cfg, torch.device("cpu"))
    >>> env = make_env(cfg, model, torch.device("cpu"), seed=0)
    >>> actor, critic = make_actor_critic(cfg, model, env, torch.device("cpu"))
    >>> actor(env.reset())["action"].shape
    torch.Size([2, 3])
"""

from __future__ import annotations

import torch
from omegaconf import OmegaConf
from tensordict.nn import InteractionType, TensorDictModule, TensorDictSequential
from tensordict.nn.distributions import NormalParamExtractor
from torch import nn, optim
from torchrl.collectors import Collector
from torchrl.envs import Compose, InitTracker, RewardSum, TransformedEnv
from torchrl.modules import MLP, AdditiveGaussianModule, ProbabilisticActor, TanhModule, ValueOperator
from torchrl.modules.distributions import TanhNormal
from torchrl.objectives import DDPGLoss, SACLoss, SoftUpdate, TD3Loss

from torchrl_silp import CollisionHandling, GoalRelative, ReachEnv, RunningObservationNorm, SILPLoss
from torchrl_silp.data import DemoReplayBuffer, GoalRelabelingReplayBuffer, MixedReplay, transition_keys
from torchrl_silp.models import TaskModel, make_model as _make_model
from torchrl_silp.models.check import TaskModelError, ensure_checked
from torchrl_silp.models.learned_collision import load_collision_net, with_learned_edges
from torchrl_silp.modules import GPGuidedExploration, NextGoalOffsetQ
from torchrl_silp.recipes.schema import ConfigError


# ---------------------------------------------------------------- environment
def make_model(cfg, device):
    """The run's task model, checked (:func:`~torchrl_silp.models.check_task_model`), on ``device``.

    ``cfg.env.model`` holds either a ``_target_`` (any :class:`~torchrl_silp.models.TaskModel` class,
    built by hydra's ``instantiate`` with the node's other keys: a user's own task, with no file of the
    repository changed), or the keyword arguments of the package's model named ``cfg.env.name``.
    A model that breaks a rule of the interface is refused with a ``ConfigError`` naming
    ``env.model`` and the member and rule it broke.
    """
    kwargs = OmegaConf.to_container(cfg.env.model, resolve=True)
    if "_target_" in kwargs:
        from hydra.errors import InstantiationException
        from hydra.utils import instantiate

        try:
            model = instantiate(cfg.env.model)
        except InstantiationException as error:
            raise ConfigError("env.model._target_", " ".join(str(error).split())) from error
        if not isinstance(model, TaskModel):
            raise ConfigError("env.model._target_", f"{kwargs['_target_']} built a {type(model).__name__}, "
                                                    "not a torchrl_silp.models.TaskModel")
        if model.device != torch.device(device):
            model.to(device)
    else:
        robot = OmegaConf.to_container(cfg.env.robot, resolve=True) if cfg.env.get("robot") else {}
        if robot:
            kwargs["robot"] = robot
        try:
            model = _make_model(cfg.env.name, device=device, **kwargs)
        except (ValueError, TypeError) as error:
            raise ConfigError(_config_key(str(error), robot), " ".join(str(error).split())) from error
    try:
        ensure_checked(model)
    except TaskModelError as error:
        raise ConfigError("env.model", str(error)) from error
    return model


def _config_key(message: str, robot: dict) -> str:
    """The config key a model's or robot's refusal names: its message starts with the parameter
    (``joints: ...``, ``boxes[1].size: ...``, ``__init__() got an unexpected keyword argument 'x'``)."""
    import inspect
    import re

    from torchrl_silp.robots import URDFArm

    unexpected = re.search(r"unexpected keyword argument '(\w+)'", message)
    name = unexpected.group(1) if unexpected else re.split(r"[:\s\[.]", message, maxsplit=1)[0]
    robot_params = set(inspect.signature(URDFArm).parameters) - {"device", "dtype"}
    if robot and (name in robot_params or (unexpected and name in robot)):
        return f"env.robot.{name}"
    return f"env.model.{name}" if name else "env.model"


def observation_keys(cfg) -> list[str]:
    """What the networks read: the flat observation (``"observation_normalized"`` with
    ``network.normalize_observation``), and the goal offset with ``network.goal_relative``."""
    observation = "observation_normalized" if normalizes_observation(cfg) else "observation"
    return [observation, "goal_offset"] if cfg.network.goal_relative else [observation]


def normalizes_observation(cfg) -> bool:
    """``network.normalize_observation`` (false in a config saved before the key, or without it, as BC's)."""
    return bool(cfg.network.get("normalize_observation", False))


_NORM_ATTR = "_observation_norm"  # private: the model's check ignores it (models.check.ensure_checked)


def observation_norm(cfg, model) -> RunningObservationNorm | None:
    """The run's :class:`~torchrl_silp.RunningObservationNorm` with ``network.normalize_observation``, else None.

    One per model object, kept on the model (and so on a shallow copy of it, as ``with_learned_edges``
    makes): the env's transform, :func:`make_observation_transform` (the planner, SILPLoss's look-ahead,
    hindsight relabelling, evaluation), the update's batch normalisation and the checkpoint all hold
    the same statistics. The recipe updates them from each collected batch's raw ``"observation"``.
    """
    if not normalizes_observation(cfg):
        return None
    norm = model.__dict__.get(_NORM_ATTR)
    if norm is None:
        norm = RunningObservationNorm().to(model.device)
        setattr(model, _NORM_ATTR, norm)
    return norm


def make_observation_transform(cfg, model) -> Compose:
    """The transforms that build the networks' inputs from a named state (the env's, the planner's, the loss's);
    with ``network.normalize_observation``, the run's :func:`observation_norm` last."""
    transforms = [GoalRelative(model)] if cfg.network.goal_relative else []
    norm = observation_norm(cfg, model)
    return Compose(*transforms, model.observation_transform(), *([norm] if norm is not None else []))


def make_env(cfg, model, device, seed: int, primers=()) -> TransformedEnv:
    """The batched training env: the model's ReachEnv, collision handling, the networks' inputs,
    ``is_init`` and ``episode_reward`` (read by the loop and the exploration module), and ``primers``."""
    base = ReachEnv(model, num_envs=cfg.env.num_envs, seed=seed, max_steps=cfg.env.max_steps, device=device)
    transforms = [CollisionHandling(cfg.env.collision_type), make_observation_transform(cfg, model), InitTracker(), RewardSum()]
    return TransformedEnv(base, Compose(*transforms, *primers))


# --------------------------------------------------------------------- models
def _mlp(cfg, out_features: int, device) -> nn.Module:
    return MLP(num_cells=list(cfg.network.hidden_sizes), out_features=out_features, activation_class=nn.ReLU, device=device)


def make_actor_critic(cfg, model, env, device):
    """Actor (stochastic TanhNormal for SAC, deterministic tanh for DDPG/TD3) and Q-network."""
    spec = env.action_spec_unbatched.to(device)
    keys = observation_keys(cfg)
    if cfg.algorithm == "sac":
        net = TensorDictSequential(
            TensorDictModule(_mlp(cfg, 2 * spec.shape[-1], device), in_keys=keys, out_keys=["param"]),
            TensorDictModule(
                NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
                in_keys=["param"], out_keys=["loc", "scale"],
            ),
        )
        actor = ProbabilisticActor(
            net,
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
            default_interaction_type=InteractionType.RANDOM,
            return_log_prob=False,
        )
    elif cfg.algorithm in ("ddpg", "td3"):
        actor = TensorDictSequential(
            TensorDictModule(_mlp(cfg, spec.shape[-1], device), in_keys=keys, out_keys=["param"]),
            TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
        )
    else:
        raise ValueError(f"algorithm must be one of ('sac', 'ddpg', 'td3'), got {cfg.algorithm!r}")
    if cfg.network.next_tcp_feature:
        if cfg.algorithm == "td3":
            raise ValueError("network.next_tcp_feature needs algorithm sac or ddpg: TorchRL's TD3Loss gives the "
                             "critic only the actor's inputs, not the named state the model steps from")
        q_net = NextGoalOffsetQ(_mlp(cfg, 1, device), model, observation_keys=keys,
                                clearance=bool(cfg.network.get("next_clearance_feature", False)))
        critic = ValueOperator(q_net, in_keys=q_net.in_keys)
    elif cfg.network.get("next_clearance_feature", False):
        raise ValueError("network.next_clearance_feature needs network.next_tcp_feature: the Q-network that steps "
                         "the model (NextGoalOffsetQ) is the one that reads the next clearance")
    else:
        critic = ValueOperator(_mlp(cfg, 1, device), in_keys=[*keys, "action"])
    with torch.no_grad():
        td = env.fake_tensordict().to(device)
        actor(td)
        critic(td)
    return actor, critic


def make_exploration(cfg, model, device) -> GPGuidedExploration | None:
    """The collision-recovery module of ``exploration.mode`` (its state primer goes into the env), or None."""
    if cfg.exploration.mode == "none":
        return None
    return GPGuidedExploration(
        model,
        mode=cfg.exploration.mode,
        num_candidates=cfg.exploration.n_candidates,
        history_size=cfg.env.max_steps + 1,
        mask_colliding_candidates=cfg.exploration.mask_colliding_candidates,
    ).to(device)


def make_policy(cfg, actor, exploration, env, device):
    """The collector's policy: the actor, DDPG/TD3 Gaussian noise, then collision-recovery exploration."""
    modules = [actor]
    if cfg.algorithm != "sac":
        modules.append(
            AdditiveGaussianModule(
                spec=env.action_spec_unbatched.to(device), sigma_init=cfg.exploration.sigma,
                sigma_end=cfg.exploration.sigma, annealing_num_steps=1, device=device,
            )
        )
    if exploration is not None:
        modules.append(exploration)
    return TensorDictSequential(*modules) if len(modules) > 1 else actor


def make_collector(cfg, env, policy, total_frames: int, init_random_frames: int, device) -> Collector:
    """TorchRL's collector of ``cfg.collector.frames_per_batch`` transitions per batch, random actions first."""
    return Collector(
        env, policy, frames_per_batch=cfg.collector.frames_per_batch, total_frames=total_frames,
        init_random_frames=init_random_frames, device=device,
    )


# ------------------------------------------------------------------- buffers
def planner_kwargs(cfg) -> dict:
    """``planner.*`` as the keyword arguments of :func:`~torchrl_silp.planning.plan_demonstrations`."""
    names = ("d", "n_pairs", "step_size", "method", "goal_node", "own_query", "insert_nodes", "sampled_nodes",
             "sample_spread")
    return {name: cfg.planner[name] for name in names}


def make_buffers(cfg, model, device) -> MixedReplay:
    """The interaction buffer D_pi (hindsight-relabelled with ``replay_buffer.her``) and the demonstration
    buffer D_demo with its planner, mixed ``replay_buffer.demo_fraction`` demos per batch (none without
    ``silp.demos``)."""
    planner = planner_kwargs(cfg)
    keys = observation_keys(cfg)
    if cfg.planner.collision_net is not None:  # the paper's planner: edges checked by the learned model
        net = load_collision_net(cfg.planner.collision_net).to(device)
        model = with_learned_edges(model, net, cfg.planner.collision_threshold)
    demos = DemoReplayBuffer(
        model, capacity=cfg.replay_buffer.demo_size, device=device, planner_kwargs=planner,
        observation_transform=make_observation_transform(cfg, model), observation_keys=keys,
    )
    interaction = None
    if cfg.replay_buffer.her:
        # the *-HER baselines: TorchRL's hindsight relabelling on the interaction data
        interaction = GoalRelabelingReplayBuffer(
            model, her_ratio=cfg.replay_buffer.her_ratio, strategy=cfg.replay_buffer.her_strategy,
            capacity=cfg.replay_buffer.size, device=device,
            observation_transform=make_observation_transform(cfg, model),
            collision_ends_episode=cfg.env.collision_type == 0 or cfg.replay_buffer.collision_terminal,
        )
    return MixedReplay(
        demos, interaction, interaction_capacity=cfg.replay_buffer.size,
        demo_fraction=cfg.replay_buffer.demo_fraction if cfg.silp.demos else 0.0,
        batch_size=cfg.optim.batch_size, keys=transition_keys(model, keys), device=device,
        collision_terminal=cfg.replay_buffer.collision_terminal,
    )


# ---------------------------------------------------------------------- loss

def demo_rows_of(cfg) -> str:
    """``cfg.silp.demo_rows`` for :class:`SILPLoss`, ``auto`` resolved to the faster way for the run.

    ``auto`` is ``mask`` under ``compile.cudagraphs`` (fixed shapes) and in a compiled update without
    a BC filter: there the masked term costs one actor pass over the whole batch, while ``select``'s
    ``nonzero`` breaks the compiled graph (each update runs three graphs instead of one, and compiling
    takes more than twice as long). Else ``select``: with a filter, its look-ahead (reward) or critic (Q) on every
    row makes a masked update slower, and an eager update has no graph to break.
    """
    rows = cfg.silp.demo_rows
    if rows != "auto":
        return rows
    comp = cfg.get("compile") or {}
    if comp.get("cudagraphs", False) or (comp.get("compile", False) and cfg.silp.filter == "none"):
        return "mask"
    return "select"


def make_loss(cfg, actor, critic, model, env):
    """The RL loss (SAC / DDPG / TD3), wrapped by SILPLoss when the BC term is on, and its target updater."""
    if cfg.algorithm == "sac":
        rl = SACLoss(
            actor_network=actor, qvalue_network=critic, num_qvalue_nets=2, loss_function="l2",
            delay_actor=False, delay_qvalue=True, alpha_init=cfg.optim.alpha_init, min_alpha=cfg.optim.min_alpha,
            target_entropy=cfg.optim.target_entropy,
        )
        # SACLoss registers its target-entropy buffer on first use: create it now, so a
        # fresh loss and a checkpointed one have the same state_dict keys on resume
        _ = rl.target_entropy
    elif cfg.algorithm == "ddpg":
        rl = DDPGLoss(actor_network=actor, value_network=critic, delay_actor=True, delay_value=True, loss_function="l2")
    else:
        rl = TD3Loss(actor_network=actor, qvalue_network=critic, action_spec=env.action_spec_unbatched, loss_function="l2")
    rl.make_value_estimator(gamma=cfg.optim.gamma)
    updater = SoftUpdate(rl, tau=cfg.optim.tau)
    if not cfg.silp.bc:
        return rl, updater
    loss = SILPLoss(
        rl, model, filter=cfg.silp.filter, lambda1=cfg.silp.lambda1, lambda2=cfg.silp.lambda2, k=cfg.silp.k,
        gamma=cfg.optim.gamma, observation_transform=make_observation_transform(cfg, model),
        demo_rows=demo_rows_of(cfg),
    )
    return loss, updater


def rl_loss_of(loss):
    """The actor-critic loss itself: that of a :class:`SILPLoss`, or ``loss``."""
    return loss.rl_loss if isinstance(loss, SILPLoss) else loss


def make_optimizers(cfg, loss) -> dict[str, optim.Optimizer]:
    """Adam for the actor, the critic and (SAC) the entropy temperature, at ``optim.lr``."""
    rl = rl_loss_of(loss)
    actor_params = list(rl.actor_network_params.flatten_keys().values())
    critic_params = rl.qvalue_network_params if hasattr(rl, "qvalue_network_params") else rl.value_network_params
    # fused: one ATen kernel per optimiser step, outside the compiled forward and backward;
    # capturable (step counts on the device) when a CUDA graph replays the steps
    adam = dict(lr=cfg.optim.lr, fused=True, capturable=bool(cfg.compile.get("cudagraphs", False)))
    opts = {
        "actor": optim.Adam(actor_params, **adam),
        "critic": optim.Adam(list(critic_params.flatten_keys().values()), **adam),
    }
    if cfg.algorithm == "sac":
        opts["alpha"] = optim.Adam([rl.log_alpha], **adam)
    return opts
