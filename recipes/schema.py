"""Typed (hydra structured) configs of the training recipes, and the checks of their values, key by key.

Hydra rejects a field of the wrong type or name; :func:`check_config` checks the ranges,
choices and cross-field rules of a composed config and :func:`check_run_folder` what it asks
of its ``run_dir`` (a fresh start, a resume), each raising :class:`ConfigError` whose one-line
message names the key as the user types it (``env.num_envs``, ``planner.d``). The library's
constructors check the same values again where they are used, naming their parameters.
Every field is documented in ``config/sac_silp.yaml``.

This module imports neither torch nor the package (only hydra and omegaconf), so that a
recipe script refuses a bad command line (:func:`preflight`) within a second, before its
heavy imports.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

# torchrl_silp.eval's DEFAULT_VALIDATION_SEED and DEFAULT_TEST_SEED, written out: importing the package
# would import torch (tests/test_bad_input.py checks they agree)
DEFAULT_VALIDATION_SEED = 31415926
DEFAULT_TEST_SEED = 20231101

CONFIG_DIR = Path(__file__).resolve().parent / "config"


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
class EvalConfig:
    n_tasks: int = 1000
    seed: int = DEFAULT_VALIDATION_SEED
    test_seed: int = DEFAULT_TEST_SEED
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
class TrainConfig:
    algorithm: str = "sac"
    seed: int = 0
    device: str = "cpu"
    threads: int = 0
    run_dir: str = "runs/${env.name}/${logger.exp_name}/seed${seed}"
    resume: Any = False
    progress: bool = True
    stop_at_success: Optional[float] = None
    max_train_wall_s: float = 0.0
    env: EnvConfig = field(default_factory=EnvConfig)
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
class BCEvalConfig:
    n_tasks: int = 1000
    seed: int = DEFAULT_VALIDATION_SEED
    test_seed: int = DEFAULT_TEST_SEED
    every_updates: int = 2_000


@dataclass
class BCCheckpointConfig:
    every_updates: int = 2_000


@dataclass
class BCLoggerConfig:
    exp_name: str = "bc"


@dataclass
class BCConfig:
    """The behaviour-cloning baselines (``recipes/bc.py``); every field is documented in ``config/bc.yaml``."""

    source: str = "policy"
    source_run_dir: Optional[str] = None
    prm_budget_s: float = 1.0
    n_demos: int = 10_000
    seed: int = 0
    device: str = "cpu"
    threads: int = 0
    run_dir: str = "runs/${env.name}/${logger.exp_name}/seed${seed}"
    resume: Any = False
    progress: bool = True
    env: EnvConfig = field(default_factory=EnvConfig)
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
