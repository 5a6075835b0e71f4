"""Builders shared by every training recipe (TorchRL recipe style: construction here, the loop in the script).

Each ``make_*`` returns stock TorchRL / torchrl_silp objects; the method itself
(task models, transforms, planner, buffers, loss, exploration, networks,
episode assembly, actor averaging) lives in the package.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
import signal
import threading
import time
import warnings
from pathlib import Path

import numpy as np
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

from torchrl_silp import CollisionHandling, GoalRelative, ReachEnv, SILPLoss
from torchrl_silp.compiling import compile_kwargs as _compile_kwargs
from torchrl_silp.data import DemoReplayBuffer, GoalRelabelingReplayBuffer, MixedReplay, cut_episodes, transition_keys
from torchrl_silp.models import make_model as _make_model
from torchrl_silp.models.learned_collision import load_collision_net, with_learned_edges
from torchrl_silp.modules import GPGuidedExploration, NextGoalOffsetQ
from torchrl_silp.objectives import DEMO_ROWS

EXPLORATION_MODES = ("gp", "random", "none")


def check_device(value) -> None:
    if value not in ("cpu", "cuda", "auto") and not str(value).startswith("cuda:"):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {value!r}")
    if str(value).startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device={value!r}, but torch finds no CUDA device here: use device=cpu or device=auto")


# fields whose change makes a checkpoint's networks or buffers the wrong shape or meaning
RESUME_FIELDS = ("algorithm", "env.name", "env.model", "env.num_envs", "env.max_steps", "network",
                 "replay_buffer.size", "replay_buffer.demo_size", "replay_buffer.her", "silp.bc",
                 "source", "source_run_dir")
# fields whose presence (set or null) must match; their value may change on resume
RESUME_PRESENCE_FIELDS = ("eval.actor_average_decay",)
# fields an older run's config.yaml may hold that no longer exist: ignored on resume, with a notice
RESUME_RETIRED_FIELDS = ("network.onednn_linear",)
RESUME_MODES = (False, True, "must")


def check_resume(cfg, run_dir: Path) -> bool:
    """Whether ``cfg.resume`` finds a checkpoint in ``run_dir``; refuses a config that differs from the run's own.

    A resume whose config differs from the checkpointed run's ``config.yaml`` in a field of
    :data:`RESUME_FIELDS` raises a ValueError naming the field, before anything is written.
    ``resume=true`` with no checkpoint says so and the run starts fresh; ``resume=must`` refuses.
    """
    resume = cfg.get("resume", False)  # prm.py has no resume
    if resume not in RESUME_MODES:
        raise ValueError(f"resume must be true, false or 'must', got {resume!r}")
    if not resume:
        return False
    if not checkpoint_exists(run_dir / "checkpoint"):
        if resume == "must":
            raise FileNotFoundError(f"resume=must, but {run_dir / 'checkpoint'} holds no checkpoint")
        print(f"resume=true, but {run_dir / 'checkpoint'} holds no checkpoint: starting a new run")
        return False
    saved_path = run_dir / "config.yaml"
    if saved_path.exists():
        saved = OmegaConf.to_container(OmegaConf.load(saved_path), resolve=True)
        now = OmegaConf.to_container(cfg, resolve=True)
        for field in RESUME_RETIRED_FIELDS:
            parent, _, leaf = field.rpartition(".")
            node = _dotted(saved, parent)
            if isinstance(node, dict) and leaf in node:
                print(f"resume: {field}={node.pop(leaf)!r} in {saved_path} no longer exists and is ignored")
        for field in (*RESUME_FIELDS, *RESUME_PRESENCE_FIELDS):
            old, new = _dotted(saved, field), _dotted(now, field)
            if field in RESUME_PRESENCE_FIELDS:
                old, new = ("set" if old is not None else None), ("set" if new is not None else None)
            if old != new:
                raise ValueError(f"resume: {field} is {new!r} here but {old!r} in the checkpointed run "
                                 f"({saved_path}); resume with the run's own config or use another run_dir")
    return True


def _dotted(tree, field: str):
    for key in field.split("."):
        if not isinstance(tree, dict) or key not in tree:
            return None
        tree = tree[key]
    return tree


def check_compile(cfg, device: torch.device) -> None:
    """Refuses a ``cfg.compile`` that cannot run on ``device``, naming the field."""
    comp = cfg.get("compile")
    if comp is None:
        return
    compile_kwargs(cfg)  # refuses an unknown compile.guards
    if not comp.get("cudagraphs", False):
        return
    if device.type != "cuda":
        raise ValueError(f"compile.cudagraphs captures the update in a CUDA graph: it needs device=cuda, "
                         f"but the run's device is {device.type}")
    if comp.get("compile_mode") == "reduce-overhead":
        raise ValueError("compile.cudagraphs and compile.compile_mode=reduce-overhead both capture CUDA graphs: "
                         "choose one")
    if cfg.silp.bc and demo_rows_of(cfg) != "mask":
        raise ValueError(f"compile.cudagraphs needs fixed shapes: set silp.demo_rows=mask or auto (got "
                         f"{cfg.silp.demo_rows!r}, whose demo rows are a shape that depends on the batch)")


DEMO_ROWS_CHOICES = (*DEMO_ROWS, "auto")


def demo_rows_of(cfg) -> str:
    """``cfg.silp.demo_rows`` for :class:`SILPLoss`, ``auto`` resolved to the faster way for the run.

    ``auto`` is ``mask`` under ``compile.cudagraphs`` (fixed shapes) and in a compiled update without
    a BC filter: there the masked term costs one actor pass over the whole batch, while ``select``'s
    ``nonzero`` breaks the compiled graph (each update runs three graphs instead of one, and compiling
    takes more than twice as long). Else ``select``: with a filter, its look-ahead (reward) or critic (Q) on every
    row makes a masked update slower, and an eager update has no graph to break.
    """
    rows = cfg.silp.demo_rows
    if rows not in DEMO_ROWS_CHOICES:
        raise ValueError(f"silp.demo_rows must be one of {DEMO_ROWS_CHOICES}, got {rows!r}")
    if rows != "auto":
        return rows
    comp = cfg.get("compile") or {}
    if comp.get("cudagraphs", False) or (comp.get("compile", False) and cfg.silp.filter == "none"):
        return "mask"
    return "select"


def resolve_device(cfg) -> torch.device:
    """``cfg.device`` checked and resolved ("auto": CUDA when there is one)."""
    check_device(cfg.device)
    return torch.device(("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device)


def start_run(cfg) -> tuple[torch.device, Path]:
    """What every recipe does first: ``(device, run_dir)``.

    Resolves ``cfg.device`` ("auto": CUDA when there is one), checks a resume against the
    checkpointed run's config (:func:`check_resume`), sets torch's threads (``cfg.threads``,
    0 leaves the default), seeds torch, numpy and ``random`` with ``cfg.seed``, creates
    ``cfg.run_dir`` and saves the resolved config there as ``config.yaml``: what rebuilds a
    run's networks from its checkpoint (``load_trained_networks``) and what a report cites.
    """
    device = resolve_device(cfg)
    check_compile(cfg, device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    run_dir = Path(cfg.run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"run_dir {str(run_dir)!r} is a file: give a directory (it is created if missing)")
    check_resume(cfg, run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    return device, run_dir


# ---------------------------------------------------------------- environment
def make_model(cfg, device):
    """The task model named by ``cfg.env.name``, with ``cfg.env.model`` as keyword arguments."""
    return _make_model(cfg.env.name, device=device, **OmegaConf.to_container(cfg.env.model, resolve=True))


def observation_keys(cfg) -> list[str]:
    """What the networks read: the flat observation, and the goal offset with ``network.goal_relative``."""
    return ["observation", "goal_offset"] if cfg.network.goal_relative else ["observation"]


def make_observation_transform(cfg, model) -> Compose:
    """The transforms that build the networks' inputs from a named state (the env's, the planner's, the loss's)."""
    transforms = [GoalRelative(model)] if cfg.network.goal_relative else []
    return Compose(*transforms, model.observation_transform())


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
        q_net = NextGoalOffsetQ(_mlp(cfg, 1, device), model, observation_keys=keys)
        critic = ValueOperator(q_net, in_keys=q_net.in_keys)
    else:
        critic = ValueOperator(_mlp(cfg, 1, device), in_keys=[*keys, "action"])
    with torch.no_grad():
        td = env.fake_tensordict().to(device)
        actor(td)
        critic(td)
    return actor, critic


def make_exploration(cfg, model, device) -> GPGuidedExploration | None:
    """The collision-recovery module of ``exploration.mode`` (its state primer goes into the env), or None."""
    if cfg.exploration.mode not in EXPLORATION_MODES:
        raise ValueError(f"exploration.mode must be one of {EXPLORATION_MODES}, got {cfg.exploration.mode!r}")
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
    return Collector(
        env, policy, frames_per_batch=cfg.collector.frames_per_batch, total_frames=total_frames,
        init_random_frames=init_random_frames, device=device,
    )


# ------------------------------------------------------------------- buffers
def make_buffers(cfg, model, device) -> MixedReplay:
    planner = {
        "d": cfg.planner.d,
        "n_pairs": cfg.planner.n_pairs,
        "step_size": cfg.planner.step_size,
        "method": cfg.planner.method,
        "goal_node": cfg.planner.goal_node,
        "own_query": cfg.planner.own_query,
        "insert_nodes": cfg.planner.insert_nodes,
    }
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
            collision_ends_episode=cfg.env.collision_type == 0,
        )
    return MixedReplay(
        demos, interaction, interaction_capacity=cfg.replay_buffer.size,
        demo_fraction=cfg.replay_buffer.demo_fraction if cfg.silp.demos else 0.0,
        batch_size=cfg.optim.batch_size, keys=transition_keys(model, keys), device=device,
    )


# ---------------------------------------------------------------------- loss
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
    return loss.rl_loss if isinstance(loss, SILPLoss) else loss


def make_optimizers(cfg, loss) -> dict[str, optim.Optimizer]:
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


class GradientStep:
    """One gradient update on a sampled batch: the losses, backward, every optimiser's step, the target
    update; calling it returns the detached loss TensorDict.

    :attr:`loss_fn` (the loss's forward) is the part :func:`compile_update` compiles; AOTAutograd
    compiles its backward with it. ``.backward()`` and the optimisers' fused steps and the target
    update run eagerly around it: dynamo cannot trace ``Tensor.backward()``, and a graph break there
    makes it trace the whole loss a second time; traced, each
    ``Optimizer.step`` breaks the graph twice, and in a loop over optimisers dynamo gives up on the
    whole function.
    """

    def __init__(self, loss, optimizers: dict, updater):
        self.loss, self.optimizers, self.updater = loss, optimizers, updater
        self.loss_fn = loss

    def forward_backward(self, sample):
        loss_td = self.loss_fn(sample)
        sum(v for k, v in loss_td.items() if k.startswith("loss_")).backward()
        return loss_td.detach()

    def zero_grad(self) -> None:
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)

    def __call__(self, sample):
        self.zero_grad()
        loss_td = self.forward_backward(sample)
        for opt in self.optimizers.values():
            opt.step()
        self.updater.step()
        return loss_td


def make_gradient_step(loss, optimizers: dict, updater) -> GradientStep:
    """The recipe's update (:class:`GradientStep`)."""
    return GradientStep(loss, optimizers, updater)


def compile_update(cfg, gradient_step):
    """``gradient_step`` compiled with ``torch.compile`` when ``cfg.compile.compile`` (TorchRL's SOTA recipes'
    switch), else itself: of a :class:`GradientStep`, its loss's forward (and so, through AOTAutograd, its
    backward); any other callable whole; with :func:`compile_kwargs` (``compile.compile_mode`` and
    ``compile.guards``). A first call whose compilation fails (e.g. no C++ compiler for inductor's CPU
    code) warns and runs eagerly from then on.

    With ``cfg.compile.cudagraphs`` the whole step (forward, backward, the optimisers' steps and the target
    update) is then captured in a CUDA graph by tensordict's ``CudaGraphModule``, as TorchRL's SOTA recipes
    do, and replayed on each call after ``cfg.compile.warmup`` warm-up calls; a capture that fails warns
    and the step runs uncaptured from then on (:func:`check_compile` has refused what cannot work)."""
    step = _compile_loss(cfg, gradient_step) if cfg.compile.compile else gradient_step
    if not cfg.compile.get("cudagraphs", False):
        return step
    return _capture_cuda_graph(step, cfg.compile.warmup)


def _capture_cuda_graph(step, warmup: int):
    from tensordict.nn import CudaGraphModule

    done = []  # the outputs of the step's own runs during the capturing call

    def counted(sample):
        out = step(sample)
        done.append(out)
        return out

    graphed = CudaGraphModule(counted, in_keys=[], out_keys=[], warmup=warmup)
    chosen = []

    def call(sample):
        if chosen:
            return chosen[0](sample)
        if graphed.counter < warmup - 1:  # a warm-up call: the step runs as itself
            return graphed(sample)
        done.clear()
        try:
            out = graphed(sample)  # one run of the step, then its capture (recorded, not run)
            chosen.append(graphed)
        except Exception as err:  # noqa: BLE001 - a failed capture ran none of what it recorded
            warnings.warn(f"compile.cudagraphs: the capture failed ({type(err).__name__}: {str(err)[:300]}); "
                          "the update runs without a CUDA graph")
            chosen.append(step)
            # the batch's update ran before the capture began: not again
            out = done[0] if done else step(sample)
        return out

    return call


def compile_kwargs(cfg) -> dict:
    """``torch.compile``'s keyword arguments for the update under ``cfg.compile``: its ``compile_mode``, and
    with ``guards=inputs`` no checks on the loss's modules or on module globals before each call
    (:func:`torchrl_silp.compiling.compile_kwargs`). The recipes build their loss once and change its
    parameters only in place, so those checks cannot fail in their runs; a script that changes a loss
    attribute mid-run needs ``compile.guards=all``."""
    return _compile_kwargs(cfg.compile.get("guards", "all"), cfg.compile.compile_mode, name="compile.guards")


def _compile_loss(cfg, gradient_step):
    if not isinstance(gradient_step, GradientStep):
        return _falling_back(torch.compile(gradient_step, **compile_kwargs(cfg)), gradient_step)
    # a new step on the same loss and optimisers; its first forward and backward (where inductor
    # compiles the backward) fall back on the eager ones together
    step = GradientStep(gradient_step.loss, gradient_step.optimizers, gradient_step.updater)
    step.loss_fn = torch.compile(gradient_step.loss_fn, **compile_kwargs(cfg))
    step.forward_backward = _falling_back(step.forward_backward, gradient_step.forward_backward,
                                          on_failure=step.zero_grad)
    return step


def _falling_back(compiled, eager, on_failure=None):
    """``compiled`` from its first call on, or ``eager`` if that call raises (warning once)."""
    chosen = []

    def call(sample):
        if chosen:
            return chosen[0](sample)
        try:
            out = compiled(sample)
            chosen.append(compiled)
        except Exception as err:  # noqa: BLE001 - any compiler failure falls back on the same function
            warnings.warn(f"compile.compile: torch.compile failed ({type(err).__name__}: {str(err)[:300]}); "
                          "the update runs eagerly")
            chosen.append(eager)
            if on_failure is not None:
                on_failure()  # whatever the failed call accumulated
            out = eager(sample)
        return out

    return call


# ------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, state: dict, buffers: MixedReplay) -> None:
    """Write everything a resumed run needs; atomically (a killed save leaves the previous one)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    torch.save(state, tmp / "state.pt")
    buffers.dumps(tmp / "buffers")
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


class StopRequest:
    """SIGTERM / SIGINT while training: the loop finishes its batch, checkpoints and stops.

    Used as a context manager around the loop (the handlers are those of the main thread only;
    elsewhere, e.g. in a thread of a Ray worker, nothing is installed and the default
    behaviour stays). A second signal gets the previous handler: it stops at once.
    :meth:`exit` then ends the process the way the signal would have: ``KeyboardInterrupt``
    for SIGINT, exit status 143 for SIGTERM.
    """

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.signum: int | None = None
        self._previous: dict = {}

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _handle(self, signum, frame) -> None:
        self.signum = signum
        self._restore()
        print(f"{signal.Signals(signum).name}: stopping after this batch with a checkpoint "
              "(send it again to stop at once)", flush=True)

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def exit(self, message: str) -> None:
        print(message, flush=True)
        if self.signum == signal.SIGINT:
            raise KeyboardInterrupt(message)
        raise SystemExit(128 + self.signum)


def truncate_logs(log_dir: Path, last_step: int) -> int:
    """Drop the rows of a run's CSV scalar logs written after step ``last_step``; returns how many.

    A resumed run redoes the steps after its checkpoint (and a run started afresh in the
    same ``run_dir`` all of them): their first rows go, so that no step appears twice.
    TorchRL's ``CSVLogger`` appends ``step,value`` rows to ``<name>.csv``.
    """
    dropped = 0
    for path in sorted(Path(log_dir).rglob("*.csv")):
        rows = path.read_text().splitlines(keepends=True)
        kept = [row for row in rows if int(float(row.split(",", 1)[0])) <= last_step]
        if len(kept) != len(rows):
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text("".join(kept))
            os.replace(tmp, path)
            dropped += len(rows) - len(kept)
    return dropped


def new_counters() -> dict:
    return {"frames": 0, "episodes": 0, "iterations": 0, "updates": 0, "collisions": 0, "swept_collisions": 0,
            "train_wall_s": 0.0, "planning_s": 0.0, "time_to_095_s": None,
            # the BC filter's kept share of demo rows, summed over the updates since the last evaluation point
            "bc_kept_sum": 0.0, "bc_kept_updates": 0}


def training_state(loss, optimizers, averaged, counters, history, assembler, logger, env) -> dict:
    """What a checkpoint holds besides the buffers."""
    return {
        "loss": loss.state_dict(), "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "averaged_actor": averaged.state_dict() if averaged is not None else None,
        "counters": dict(counters), "history": list(history), "assembler": assembler.state_dict(),
        "logger": logger.state_dict() if hasattr(logger, "state_dict") else None,
        "torch_rng": torch.get_rng_state(), "env_rng": env.base_env.rng.get_state(),
        "saved_at": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def restore(path: Path, cfg, loss, optimizers, averaged, buffers: MixedReplay, assembler, env) -> tuple:
    """Load a checkpoint into the run's objects: ``(counters, history, logger_state)``.

    The collector starts new episodes: the unfinished ones of the checkpoint are planned (and, for
    hindsight relabelling, stored as truncated episodes) now.
    """
    state = load_checkpoint(path, buffers)
    loss.load_state_dict(state["loss"])
    for name, opt in optimizers.items():
        opt.load_state_dict(state["optimizers"][name])
    if averaged is not None:
        if state.get("averaged_actor") is None:
            raise ValueError("eval.actor_average_decay is set but the checkpoint holds no averaged actor: "
                             "resume with the config the run was started with")
        averaged.load_state_dict(state["averaged_actor"])
    assembler.load_state_dict(state["assembler"])
    torch.set_rng_state(state["torch_rng"])
    env.base_env.rng.set_state(state["env_rng"])
    leftover = assembler.flush()
    if leftover is not None and cfg.replay_buffer.her:
        buffers.extend(cut_episodes(leftover))
    if leftover is not None and cfg.silp.demos:
        buffers.demo_buffer.extend(leftover)
    counters = state["counters"]
    print(f"resumed from {path} (saved {state.get('saved_at', 'at an unknown time')}): {counters['frames']} frames, "
          f"{counters['updates']} updates, {len(buffers)} transitions in the buffers")
    return state["counters"], state["history"], state["logger"]


def load_checkpoint(path: Path, buffers: MixedReplay) -> dict:
    found = _checkpoint_dir(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    state = torch.load(found / "state.pt", weights_only=False)
    buffers.loads(found / "buffers")
    return state


def checkpoint_exists(path: Path) -> bool:
    return _checkpoint_dir(path) is not None


def load_trained_networks(cfg, model, env, path: Path, device) -> tuple:
    """A run's networks, rebuilt from its config and loaded from its checkpoint: ``(actor, loss, state)``.

    ``actor`` holds the parameters the run evaluated: the average of the
    actor's parameters when the run kept one (``eval.actor_average_decay``),
    else the online actor; ``loss`` holds the online networks (critic included).
    """
    found = _checkpoint_dir(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    actor, critic = make_actor_critic(cfg, model, env, device)
    loss, _ = make_loss(cfg, actor, critic, model, env)
    state = torch.load(found / "state.pt", map_location=device, weights_only=False)
    loss.load_state_dict(state["loss"])
    if state.get("averaged_actor") is not None:
        averaged = {k[len("module."):]: v for k, v in state["averaged_actor"].items() if k.startswith("module.")}
        actor.load_state_dict(averaged)
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


def batch_metrics(batch, losses: list, counters: dict, demos_stored: int) -> dict:
    """What the loop logs after a collector batch: the counters, the episodes it ended, the mean losses."""
    metrics = {"train/collisions": counters["collisions"], "train/swept_collisions": counters["swept_collisions"],
               "train/episodes": counters["episodes"], "train/demos": demos_stored,
               "time/train_wall_s": counters["train_wall_s"]}
    ended = batch["next", "done"]
    if ended.any():
        metrics["train/episode_reward"] = batch["next", "episode_reward"][ended].mean().item()
        metrics["train/success_rate"] = batch["next", "success"][ended].float().mean().item()
    if losses:
        for key, value in torch.stack(losses).items():
            if key.startswith("loss_") or key in ("alpha", "bc_filter_fraction", "bc_mse"):
                metrics[f"train/{key}"] = value.float().mean().item()
    return metrics


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


def summarize(cfg, counters: dict, final: dict, demos_stored: int, validation: dict | None = None) -> dict:
    """The run's ``summary.json``: the method, the final test evaluation (and the validation one) and the counters."""
    return {
        "method": cfg.logger.exp_name, "env": cfg.env.name, "algorithm": cfg.algorithm, "silp_bc": cfg.silp.bc,
        "silp_demos": cfg.silp.demos, "her": cfg.replay_buffer.her, "exploration": cfg.exploration.mode,
        "seed": cfg.seed, "success_rate": final["success_rate"], "test_seed": cfg.eval.test_seed,
        "validation_success_rate": None if validation is None else validation["success_rate"],
        "validation_seed": cfg.eval.seed,
        "online_success_rate": final.get("online_success_rate", final["success_rate"]),
        "evaluated_actor": "online" if cfg.eval.actor_average_decay is None
        else f"average (decay {cfg.eval.actor_average_decay})",
        "test_collision_rate": final["collision_rate"], "collisions_during_training": counters["collisions"],
        # collisions of a motion whose reached state is free: what a check of the reached state alone let pass
        "swept_collisions_during_training": counters.get("swept_collisions", 0),
        "episodes": counters["episodes"], "frames": counters["frames"], "updates": counters["updates"],
        "train_wall_s": counters["train_wall_s"], "planning_s": counters["planning_s"],
        "planning_share": counters["planning_s"] / max(counters["train_wall_s"], 1e-9),
        "time_to_095_s": counters["time_to_095_s"], "rollout_time_per_episode_s": final["time_per_rollout_s"],
        "demos_stored": demos_stored,
        # demonstrations were on and the planner stored none: SILP+ ran as plain RL
        "warning": "silp.demos is on but no demonstration was stored" if cfg.silp.demos and not demos_stored else None,
    }


def write_json(path: Path, payload: dict) -> None:
    Path(path).write_text(json.dumps(payload, indent=2, default=float))


def write_results(run_dir: Path, summary: dict, history: list[dict]) -> None:
    """What every recipe leaves for a sweep and its report: ``summary.json`` and ``history.json``; prints the summary."""
    write_json(Path(run_dir) / "summary.json", summary)
    write_json(Path(run_dir) / "history.json", {"history": history})
    print("\n".join(f"{k:>30s}: {v}" for k, v in summary.items()))

