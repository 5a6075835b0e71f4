"""Typed (hydra structured) configs of the training recipes, and the one check of their values.

Hydra rejects a field of the wrong type or name; :func:`check_config` checks the ranges,
choices and cross-field rules of a composed config, raising :class:`ConfigError` whose one-line
message names the key as the user types it (``env.num_envs``, ``planner.d``). The choices are
the library's own (:mod:`torchrl_silp.choices`). ``recipes/preflight.py`` composes a script's
command line, calls this check and what a config asks of its run folder, and exits 2 on a
refusal. Every field is documented in ``config/sac_silp.yaml``.

This module imports hydra, omegaconf and :mod:`torchrl_silp.choices`, not torch, so that a
recipe script refuses a bad command line within a second, before its heavy imports.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence
from typing import Any, Optional

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_silp.choices import (
    BC_FILTERS, COLLISION_TYPES, DEFAULT_TEST_SEED, DEFAULT_VALIDATION_SEED, DEMO_ROWS, GP_EXPLORATION_MODES, GUARDS,
    HER_STRATEGIES, INSERT_NODES, SEARCH_METHODS,
)

CONFIG_DIR = Path(__file__).resolve().parent / "config"

# the recipes' own choices; the library's come from torchrl_silp.choices
ALGORITHMS = ("sac", "ddpg", "td3")
EXPLORATION_MODES = (*GP_EXPLORATION_MODES, "none")  # none: the actor's own noise, no exploration module
DEMO_ROWS_CHOICES = (*DEMO_ROWS, "auto")  # auto: the faster of the two for the run (builders.demo_rows_of)
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
LOGGER_BACKENDS = (None, "", "csv", "tensorboard", "wandb", "mlflow")  # None or "": no logger
RESUME_MODES = (False, True, "must")


class ConfigError(ValueError):
    """A config value the recipe refuses; ``str(error)`` is one line that starts with the key."""

    def __init__(self, key: str, reason: str):
        self.key = key
        super().__init__(f"{key}: {reason}" if key else reason)


@dataclass
class EnvConfig:
    name: str = "ur5e_reach"
    run_name: str = "${env.name}"  # the run folder's task part (env=urdf_reach: the URDF file's name)
    num_envs: int = 32
    max_steps: int = 50
    collision_type: int = 2
    model: dict[str, Any] = field(default_factory=dict)
    robot: dict[str, Any] = field(default_factory=dict)  # env=urdf_reach: URDFArm's keyword arguments


@dataclass
class CollectorConfig:
    frames_per_batch: int = 800
    total_frames: int = 160_000
    total_episodes: Optional[int] = None
    init_random_frames: int = 8_000


@dataclass
class ReplayBufferConfig:
    size: int = 500_000
    demo_size: int = 200_000
    demo_fraction: Any = 0.25
    her: bool = False
    her_ratio: float = 0.8
    her_strategy: str = "future"
    collision_terminal: bool = False


@dataclass
class PlannerConfig:
    d: float = 0.15
    n_pairs: int = 4
    step_size: Optional[float] = None
    method: str = "exact"
    goal_node: bool = True
    own_query: bool = True
    insert_nodes: str = "equal"
    collision_net: Optional[str] = None
    collision_threshold: float = 0.5
    sampled_nodes: int = 0
    sample_spread: Optional[float] = None


@dataclass
class SILPConfig:
    demos: bool = True
    bc: bool = True
    filter: str = "none"
    lambda1: float = 1.0
    lambda2: float = 20.0
    k: int = 1
    demo_rows: str = "auto"


@dataclass
class ExplorationConfig:
    mode: str = "gp"
    n_candidates: int = 64
    mask_colliding_candidates: bool = True
    sigma: float = 0.2


@dataclass
class NetworkConfig:
    hidden_sizes: list[int] = field(default_factory=lambda: [256, 256])
    goal_relative: bool = True
    next_tcp_feature: bool = True
    # ours, off by default: the networks read the observation standardised by running statistics of the
    # collected data, clipped to +-5 (torchrl_silp.RunningObservationNorm, key "observation_normalized")
    normalize_observation: bool = False
    # ours, off by default: the Q-network (next_tcp_feature) also reads the task model's per-reason clearance of
    # the next configuration, clipped to +-0.2 m (NextGoalOffsetQ(clearance=True))
    next_clearance_feature: bool = False


@dataclass
class OptimConfig:
    batch_size: int = 256
    utd_ratio: float = 0.25
    lr: float = 3.0e-4
    gamma: float = 0.98
    tau: float = 0.005
    alpha_init: float = 1.0
    min_alpha: Optional[float] = None
    target_entropy: Any = -6


@dataclass
class EvalTasksConfig:
    """The tasks every recipe evaluates on: validation ones periodically, the test ones once at the end."""

    n_tasks: int = 1000
    seed: int = DEFAULT_VALIDATION_SEED
    test_seed: int = DEFAULT_TEST_SEED


@dataclass
class EvalConfig(EvalTasksConfig):
    every_frames: int = 8_000
    actor_average_decay: Optional[float] = 0.999


@dataclass
class CheckpointConfig:
    every_iters: int = 25
    every_s: float = 300.0


@dataclass
class CompileConfig:
    compile: bool = True
    compile_mode: Optional[str] = None
    guards: str = "inputs"
    cudagraphs: bool = False
    warmup: int = 5


@dataclass
class LoggerConfig:
    backend: Optional[str] = "csv"
    exp_name: str = "sac_silp_plus_ext"


@dataclass
class RunConfig:
    """What every training recipe's run has: its seed, machine, folder, resume mode and task."""

    seed: int = 0
    device: str = "cpu"
    threads: int = 0
    run_dir: str = "runs/${env.name}/${logger.exp_name}/seed${seed}"
    resume: Any = False
    progress: bool = True
    env: EnvConfig = field(default_factory=EnvConfig)


@dataclass
class TrainConfig(RunConfig):
    algorithm: str = "sac"
    stop_at_success: Optional[float] = None
    max_train_wall_s: float = 0.0
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    replay_buffer: ReplayBufferConfig = field(default_factory=ReplayBufferConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    silp: SILPConfig = field(default_factory=SILPConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    compile: CompileConfig = field(default_factory=CompileConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)


def register() -> None:
    """Register the recipes' schemas: ``train_schema`` (sac_silp, ddpg_silp), ``bc_schema`` (bc) and
    ``transfer_schema`` (transfer), and the ``class_name`` and ``file_stem`` resolvers."""
    # ${class_name:a.b.Arm3Reach} -> "Arm3Reach": config/env/custom.yaml names a user's task by its class
    OmegaConf.register_new_resolver("class_name", lambda target: str(target).rsplit(".", 1)[-1], replace=True)
    # ${file_stem:/a/ur10_robot.urdf} -> "ur10_robot": config/env/urdf_reach.yaml names the run's folder by its URDF
    OmegaConf.register_new_resolver("file_stem", lambda path: Path(str(path)).stem, replace=True)
    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
    ConfigStore.instance().store(name="bc_schema", node=BCConfig)
    ConfigStore.instance().store(name="transfer_schema", node=TransferConfig)


@contextlib.contextmanager
def config_context():
    """Hydra's compose API over ``recipes/config`` with the schemas registered, inside ``@hydra.main``
    (already set up: its primary config dir is ``recipes/config``) or not."""
    register()
    if GlobalHydra.instance().is_initialized():
        yield
    else:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            yield


def free_model_keys(overrides: list[str] | tuple[str, ...]) -> list[str]:
    """``env.model.<key>=value`` as ``++env.model.<key>=value`` (and ``env.robot.`` the same): ``env.model``
    holds a task model's keyword arguments and ``env.robot`` a robot's, whichever they take, so a key the
    env yaml does not list is added, not refused.

    Examples:
        >>> free_model_keys(["env.model.n_discs=2", "+env.model.a=1", "env.robot.held={a: 1}", "seed=3"])
        ['++env.model.n_discs=2', '+env.model.a=1', '++env.robot.held={a: 1}', 'seed=3']
    """
    return [f"++{o}" if o.startswith(("env.model.", "env.robot.")) and "=" in o else o for o in overrides]


def load_config(config_name: str, overrides: list[str] | tuple[str, ...] = ()) -> DictConfig:
    """A recipe's config (``recipes/config/<config_name>.yaml``) with hydra overrides, as its script composes it.

    Examples:
        >>> cfg = load_config("sac_silp", ["env=panda_reach", "seed=3"])
        >>> cfg.env.name, cfg.seed, cfg.algorithm
        ('panda_reach', 3, 'sac')
    """
    with config_context():
        return compose(config_name=config_name, overrides=free_model_keys(overrides))


# ------------------------------------------------------------------ recipes/bc.py
@dataclass
class BCNetworkConfig:
    hidden_sizes: list[int] = field(default_factory=lambda: [256, 256])
    goal_relative: bool = True


@dataclass
class BCOptimConfig:
    lr: float = 1.0e-3
    batch_size: int = 256
    n_updates: int = 20_000


@dataclass
class BCEvalConfig(EvalTasksConfig):
    every_updates: int = 2_000


@dataclass
class BCCheckpointConfig:
    every_updates: int = 2_000


@dataclass
class BCLoggerConfig:
    exp_name: str = "bc"


@dataclass
class BCConfig(RunConfig):
    """The behaviour-cloning baselines (``recipes/bc.py``); every field is documented in ``config/bc.yaml``."""

    source: str = "policy"
    source_run_dir: Optional[str] = None
    prm_budget_s: float = 1.0
    n_demos: int = 10_000
    network: BCNetworkConfig = field(default_factory=BCNetworkConfig)
    optim: BCOptimConfig = field(default_factory=BCOptimConfig)
    eval: BCEvalConfig = field(default_factory=BCEvalConfig)
    checkpoint: BCCheckpointConfig = field(default_factory=BCCheckpointConfig)
    logger: BCLoggerConfig = field(default_factory=BCLoggerConfig)


# ------------------------------------------------------------ recipes/transfer.py
@dataclass
class TransferConfig:
    """A trained policy on the MuJoCo twin (``recipes/transfer.py``); every field is documented in ``config/transfer.yaml``."""

    checkpoint: Optional[str] = None
    prm_budget_s: Optional[float] = None
    scenario: str = "all"
    noise: str = "all"
    n_tasks: int = 100
    trials: int = 10
    task_seed: int = 0
    seed: int = 0
    control_dt: float = 0.1
    max_steps: Optional[int] = None
    out: Optional[str] = None
    run_dir: Optional[str] = None
    resume: bool = False
    pictures: Optional[str] = None
    device: str = "cpu"
    threads: int = 1


# ------------------------------------------------------------------ value rules
def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _int(cfg, key: str, low: int = 1, optional: bool = False) -> None:
    value = OmegaConf.select(cfg, key)
    if value is None and optional:
        return
    if not _is_int(value) or value < low:
        raise ConfigError(key, f"must be an integer >= {low}{' or null' if optional else ''}, got {value!r}")


def _number(cfg, key: str, low: float | None = None, high: float | None = None, *, low_open: bool = False,
            high_open: bool = False, optional: bool = False) -> None:
    value = OmegaConf.select(cfg, key)
    if value is None and optional:
        return
    ok = _is_number(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        if low is not None and high is not None:
            allowed = f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        elif low is not None:
            allowed = f"{'>' if low_open else '>='} {low}"
        else:
            allowed = "finite"
        raise ConfigError(key, f"must be a number {allowed}{' or null' if optional else ''}, got {value!r}")


def _choice(cfg, key: str, choices: Sequence) -> None:
    value = OmegaConf.select(cfg, key)
    if isinstance(value, bool) and not any(isinstance(c, bool) for c in choices) or value not in choices:
        raise ConfigError(key, f"must be one of {', '.join(map(repr, choices))}, got {value!r}")


def _check_device_name(value) -> None:
    if not isinstance(value, str) or not (value in ("cpu", "cuda", "auto") or
                                          (value.startswith("cuda:") and value[5:].isdigit())):
        raise ConfigError("device", f"must be cpu, cuda, cuda:N or auto, got {value!r}")


def check_device(value) -> None:
    """Refuses (:class:`ConfigError`) a ``device`` that is not cpu, cuda, cuda:N or auto, or CUDA on a machine
    without one. Imports torch only to look for a CUDA device, when one is asked for."""
    _check_device_name(value)
    if value.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError("device", f"{value} asked, but torch finds no CUDA device here: use device=cpu or "
                                        "device=auto")


# ------------------------------------------------------------------ the config
def _missing_keys(tree, prefix: str = "") -> list[str]:
    """The dotted keys of a config (as an unresolved container) whose value is hydra's mandatory ``???``."""
    if isinstance(tree, dict):
        return [k for key, value in tree.items() for k in _missing_keys(value, f"{prefix}{key}.")]
    return [prefix[:-1]] if tree == "???" else []


def check_config(cfg: DictConfig) -> None:
    """Every value of a training config (``sac_silp``, ``ddpg_silp``): types, ranges, choices and the
    rules between keys. Raises :class:`ConfigError` on the first refused value; writes nothing.

    A frame budget the random warm-up would use up (no gradient update) is refused here.

    Examples:
        >>> from torchrl_silp.recipes.schema import load_config
        >>> try:
        ...     check_config(load_config("sac_silp", ["planner.d=-1"]))
        ... except ConfigError as err:
        ...     print(err)
        planner.d: must be a number > 0, got -1.0
    """
    missing = _missing_keys(OmegaConf.to_container(cfg, resolve=False, throw_on_missing=False))
    if missing:
        example = " (the task model's class, e.g. mypkg.tasks.MyReach)" if missing[0] == "env.model._target_" else ""
        raise ConfigError(missing[0], f"must be given{example}: {missing[0]}=...")
    _int(cfg, "seed", 0)
    _check_device_name(cfg.device)  # its CUDA device: check_device, which needs torch
    _int(cfg, "threads", 0)
    _choice(cfg, "resume", RESUME_MODES)
    if not isinstance(cfg.run_dir, str) or not cfg.run_dir.strip():
        raise ConfigError("run_dir", f"must be a folder's path, got {cfg.run_dir!r}")
    _number(cfg, "stop_at_success", 0, 1, low_open=True, optional=True)
    _number(cfg, "max_train_wall_s", 0)
    _choice(cfg, "algorithm", ALGORITHMS)
    if not isinstance(cfg.env.name, str) or not cfg.env.name:
        raise ConfigError("env.name", f"must name the task, got {cfg.env.name!r}")
    _int(cfg, "env.num_envs")
    _int(cfg, "env.max_steps")
    _choice(cfg, "env.collision_type", COLLISION_TYPES)
    col = cfg.collector
    _int(cfg, "collector.frames_per_batch")
    if col.frames_per_batch % cfg.env.num_envs:
        raise ConfigError("collector.frames_per_batch", f"must be a multiple of env.num_envs ({cfg.env.num_envs}), "
                                                        f"got {col.frames_per_batch}")
    _int(cfg, "collector.total_frames")
    _int(cfg, "collector.total_episodes", optional=True)
    _int(cfg, "collector.init_random_frames", 0)
    budget_key, budget = "collector.total_frames", col.total_frames
    if col.total_episodes is not None:  # an episode budget: its frames, at most max_steps an episode
        budget_key, budget = "collector.total_episodes", col.total_episodes * cfg.env.max_steps
    collected = -(-budget // col.frames_per_batch) * col.frames_per_batch  # whole batches
    if collected < col.init_random_frames:  # updates start after the batch that reaches the warm-up
        raise ConfigError(budget_key, f"a budget of {budget} frames is used up by the {col.init_random_frames} "
                                      "frames of random actions (collector.init_random_frames): nothing would "
                                      "be trained; raise the budget or lower the warm-up")
    rb = cfg.replay_buffer
    _int(cfg, "replay_buffer.size")
    _int(cfg, "replay_buffer.demo_size")
    if rb.demo_fraction != "proportional":
        _number(cfg, "replay_buffer.demo_fraction", 0, 1)
    if cfg.silp.bc and not cfg.silp.demos:
        raise ConfigError("silp.bc", "the BC term learns from demonstrations, but silp.demos=false plans none")
    if not isinstance(rb.her, bool):
        raise ConfigError("replay_buffer.her", f"must be true or false, got {rb.her!r}")
    _number(cfg, "replay_buffer.her_ratio", 0, 1)
    _choice(cfg, "replay_buffer.her_strategy", HER_STRATEGIES)
    if not isinstance(rb.collision_terminal, bool):
        raise ConfigError("replay_buffer.collision_terminal", f"must be true or false, got {rb.collision_terminal!r}")
    _number(cfg, "planner.d", 0, low_open=True)
    _int(cfg, "planner.n_pairs")
    _int(cfg, "planner.sampled_nodes", 0)
    _number(cfg, "planner.sample_spread", 0, low_open=True, optional=True)
    _number(cfg, "planner.step_size", 0, low_open=True, optional=True)
    _choice(cfg, "planner.method", SEARCH_METHODS)
    _choice(cfg, "planner.insert_nodes", INSERT_NODES)
    _number(cfg, "planner.collision_threshold", 0, 1, low_open=True, high_open=True)
    _choice(cfg, "silp.filter", BC_FILTERS)
    _number(cfg, "silp.lambda1", 0)
    _number(cfg, "silp.lambda2", 0)
    _int(cfg, "silp.k")
    _choice(cfg, "silp.demo_rows", DEMO_ROWS_CHOICES)
    _choice(cfg, "exploration.mode", EXPLORATION_MODES)
    _int(cfg, "exploration.n_candidates")
    _number(cfg, "exploration.sigma", 0, low_open=True)
    sizes = cfg.network.hidden_sizes
    if not isinstance(sizes, (list, ListConfig)) or not sizes or not all(_is_int(s) and s >= 1 for s in sizes):
        raise ConfigError("network.hidden_sizes", f"must be a non-empty list of positive integers, got {sizes!r}")
    if not isinstance(cfg.network.normalize_observation, bool):
        raise ConfigError("network.normalize_observation",
                          f"must be true or false, got {cfg.network.normalize_observation!r}")
    if not isinstance(cfg.network.next_clearance_feature, bool):
        raise ConfigError("network.next_clearance_feature",
                          f"must be true or false, got {cfg.network.next_clearance_feature!r}")
    if cfg.network.next_clearance_feature and not cfg.network.next_tcp_feature:
        raise ConfigError("network.next_clearance_feature",
                          "needs network.next_tcp_feature=true (the Q-network that steps the task model reads it)")
    _int(cfg, "optim.batch_size")
    _number(cfg, "optim.utd_ratio", 0, low_open=True)
    _number(cfg, "optim.lr", 0, low_open=True)
    _number(cfg, "optim.gamma", 0, 1, low_open=True)
    _number(cfg, "optim.tau", 0, 1, low_open=True)
    _number(cfg, "optim.alpha_init", 0, low_open=True)
    _number(cfg, "optim.min_alpha", 0, low_open=True, optional=True)
    if cfg.optim.target_entropy != "auto":
        _number(cfg, "optim.target_entropy")
    _int(cfg, "eval.n_tasks")
    _int(cfg, "eval.seed", 0)
    _int(cfg, "eval.test_seed", 0)
    _int(cfg, "eval.every_frames")
    _number(cfg, "eval.actor_average_decay", 0, 1, low_open=True, high_open=True, optional=True)
    _int(cfg, "checkpoint.every_iters")
    _number(cfg, "checkpoint.every_s", 0, low_open=True)
    _choice(cfg, "compile.guards", GUARDS)
    _choice(cfg, "compile.compile_mode", COMPILE_MODES)
    _int(cfg, "compile.warmup", 0)
    _choice(cfg, "logger.backend", LOGGER_BACKENDS)
    name = cfg.logger.exp_name
    if not isinstance(name, str) or not name or "/" in name:
        raise ConfigError("logger.exp_name", f"must be a non-empty name without '/', got {name!r}")
