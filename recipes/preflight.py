"""What a training script checks before it imports torch or writes a file: the command line, the
config's values key by key, and what the config asks of its run folder.

A refused config raises :class:`ConfigError`, whose one-line message names the key as the user types
it (``env.num_envs``, ``planner.d``). :func:`main` is the scripts' entry point: it composes the config
from the command line with hydra's compose API (so hydra writes no ``outputs/`` folder), runs every
check, prints ``error: <message>`` and exits 2 on a refusal, and only then imports the recipe and
trains; Ctrl-C and SIGTERM end it with 130 / 143 and the line that resumes the run.

This module imports only hydra, omegaconf and the standard library, so that a bad command line is
refused within about a second. The library's constructors check the same values again where they
are used, naming their own parameters; ``tests/test_bad_input.py`` checks that the choices written
here are the library's.
"""

from __future__ import annotations

import importlib
import math
import re
import shlex
import sys
from pathlib import Path
from typing import Callable, Sequence

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

__all__ = [
    "ConfigError", "check_config", "check_device", "check_run_folder", "checkpoint_exists", "find_checkpoint",
    "compose_command_line", "main", "resume_fields_differ",
]

# the library's choices (tests/test_bad_input.py checks each against the constant it copies)
ALGORITHMS = ("sac", "ddpg", "td3")
COLLISION_TYPES = (0, 1, 2)
EXPLORATION_MODES = ("gp", "random", "none")
SEARCH_METHODS = ("exact", "greedy")
INSERT_NODES = ("equal", "halving")
BC_FILTERS = ("reward", "q", "none")
DEMO_ROWS_CHOICES = ("auto", "select", "mask")
HER_STRATEGIES = ("future", "final", "episode", "random")
GUARDS = ("inputs", "all")
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
LOGGER_BACKENDS = (None, "", "csv", "tensorboard", "wandb", "mlflow")  # None or "": no logger
RESUME_MODES = (False, True, "must")

# fields whose change makes a checkpoint's networks or buffers the wrong shape or meaning
RESUME_FIELDS = ("algorithm", "env.name", "env.model", "env.robot", "env.num_envs", "env.max_steps", "network",
                 "replay_buffer.size", "replay_buffer.demo_size", "replay_buffer.her", "silp.bc",
                 "source", "source_run_dir")
# fields whose presence (set or null) must match; their value may change on resume
RESUME_PRESENCE_FIELDS = ("eval.actor_average_decay",)
# fields an older run's config.yaml may hold that no longer exist: ignored on resume, with a notice
RESUME_RETIRED_FIELDS = ("network.onednn_linear",)


class ConfigError(ValueError):
    """A config value the recipe refuses; ``str(error)`` is one line that starts with the key."""

    def __init__(self, key: str, reason: str):
        self.key = key
        super().__init__(f"{key}: {reason}" if key else reason)


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
        >>> check_config(load_config("sac_silp", ["planner.d=-1"]))
        Traceback (most recent call last):
        ...
        torchrl_silp.recipes.preflight.ConfigError: planner.d: must be a number > 0, got -1.0
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
    _number(cfg, "planner.d", 0, low_open=True)
    _int(cfg, "planner.n_pairs")
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


# ------------------------------------------------------------------ the run folder
def find_checkpoint(path: Path) -> Path | None:
    """The folder holding the checkpoint saved at ``path``: ``path``, or ``<path>.old`` where a save was
    killed between its two renames; None if there is none."""
    path = Path(path)
    for candidate in (path, path.with_name(path.name + ".old")):
        if (candidate / "state.pt").exists():
            return candidate
    return None


def checkpoint_exists(path: Path) -> bool:
    """Whether ``path`` (or what a save killed midway left of it) holds a checkpoint."""
    return find_checkpoint(path) is not None


def _dotted(tree, field: str):
    for key in field.split("."):
        if not isinstance(tree, dict) or key not in tree:
            return None
        tree = tree[key]
    return tree


def resume_fields_differ(cfg: DictConfig, saved_path: Path) -> tuple[str, object, object] | None:
    """The first field of :data:`RESUME_FIELDS` whose value differs between ``cfg`` and the run's saved
    config (``(field, here, there)``), or None. Retired fields of the saved config are ignored, with a notice."""
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
            return field, new, old
    return None


def check_run_folder(cfg: DictConfig, quiet: bool = False) -> bool:
    """What ``cfg`` asks of its ``run_dir``, checked before anything in it is created or rewritten.

    Returns whether the run resumes from the folder's checkpoint. Refuses (:class:`ConfigError`): a
    ``run_dir`` that is a file; a fresh start (``resume=false``) into a folder that holds a run's
    checkpoint (another run's, or this one's: nothing in it is touched); ``resume=must`` with no
    checkpoint; a resume whose config differs from the checkpointed run's in a field of
    :data:`RESUME_FIELDS`. ``quiet``: say nothing of a ``resume=true`` that finds no checkpoint (a
    later check of the same config says it).
    """
    run_dir = Path(cfg.run_dir)
    resume = cfg.get("resume", False)
    if resume not in RESUME_MODES:
        raise ConfigError("resume", f"must be true, false or must, got {resume!r}")
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError("run_dir", f"{str(run_dir)!r} is a file: give a folder (it is created if missing)")
    found = checkpoint_exists(run_dir / "checkpoint")
    if not resume:
        if found:
            raise ConfigError("run_dir", f"{run_dir} holds a run's checkpoint; continue it with resume=true, or "
                                         "start a new run in another run_dir=... (nothing was written)")
        return False
    if not found:
        if resume == "must":
            raise ConfigError("resume", f"resume=must, but {run_dir / 'checkpoint'} holds no checkpoint")
        if not quiet:
            print(f"resume=true, but {run_dir / 'checkpoint'} holds no checkpoint: starting a new run")
        return False
    saved_path = run_dir / "config.yaml"
    if saved_path.exists():
        differ = resume_fields_differ(cfg, saved_path)
        if differ is not None:
            field, new, old = differ
            raise ConfigError(field, f"is {new!r} here but {old!r} in the run being resumed ({saved_path}); resume "
                                     "with the run's own config, or start a new run in another run_dir")
    return True


# ------------------------------------------------------------------ the command line
def compose_command_line(config_name: str, argv: Sequence[str]) -> DictConfig:
    """The config a script's command line composes: hydra overrides, plus hydra's ``--config-dir DIR``
    (``-cd``: a folder searched before ``recipes/config``, e.g. for a user's ``env/<name>.yaml``) and
    ``--config-name NAME`` (``-cn``). Raises :class:`ConfigError` with hydra's reason in one line."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    from torchrl_silp.recipes.schema import CONFIG_DIR, free_model_keys, register

    overrides, extra_dirs = [], []
    args = list(argv)
    while args:
        arg = args.pop(0)
        flag, eq, value = arg.partition("=")
        if flag in ("--config-dir", "-cd", "--config-name", "-cn"):
            if not eq:
                if not args:
                    raise ConfigError(flag, "needs a value")
                value = args.pop(0)
            if flag in ("--config-dir", "-cd"):
                extra_dirs.append(Path(value).expanduser().resolve())
            else:
                config_name = value
        elif arg.startswith("-"):
            raise ConfigError(arg, "is not an option of this script: give hydra overrides (key=value), "
                                   "--config-dir DIR or --config-name NAME")
        else:
            overrides.append(arg)
    overrides = free_model_keys(overrides)
    for folder in extra_dirs:
        if not folder.is_dir():
            raise ConfigError("--config-dir", f"{folder} is not a folder")
    if extra_dirs:
        overrides.append("hydra.searchpath=[" + ",".join(f"file://{d}" for d in extra_dirs) + "]")
    register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            return compose(config_name=config_name, overrides=overrides)
    except (HydraException, OmegaConfBaseException, ValueError) as error:
        raise ConfigError("", _one_line(error)) from None


def _one_line(error: BaseException) -> str:
    """Hydra's and omegaconf's multi-line errors as one line: the key they name, then the reason.

    ``Error merging override optim.lr=abc`` (caused by omegaconf's ``Value 'abc' ... could not be
    converted to Float``, ``full_key: optim.lr``) becomes ``optim.lr: Value 'abc' of type 'str' could
    not be converted to Float``.
    """
    source = error.__cause__ or error
    lines = [line.strip() for line in str(source).splitlines() if line.strip()]
    key = getattr(source, "full_key", None)
    for line in lines:
        if line.startswith("full_key:") and not key:
            key = line.split(":", 1)[1].strip()
    reason = lines[0].rstrip(".") if lines else type(source).__name__
    if "Config search path" in reason:  # hydra's list of where it looked: not the reason
        reason = reason[: reason.index("Config search path")].rstrip()
    rest = [line for line in lines[1:] if not line.startswith(("full_key:", "object_type", "reference_type",
                                                                "Config search path", "provider="))]
    if rest and source is error:  # e.g. hydra's "Available options in 'method': ..." and its hints
        reason += " (" + " ".join(rest) + ")"
    group = re.search(r"Could not find '([\w.]+)/([^']+)'", reason)
    if group and not key:  # a config group's option (method=bogus): the group is the key the user typed
        options = re.search(r"Available options in '[^']+': ([^)]*)", reason)
        listed = f"; one of: {options.group(1).strip()}" if options else ""
        return f"{group.group(1)}: no option {group.group(2)!r}{listed}"
    return f"{key}: {reason}" if key and key not in reason else reason


def _resume_command(script: str, argv: Sequence[str]) -> str:
    kept = [a for a in argv if not a.startswith(("resume=", "++resume=", "+resume="))]
    return shlex.join(["python", script, *kept, "resume=true"])


def main(config_name: str, train: str, argv: Sequence[str] | None = None, script: str | None = None) -> None:
    """A recipe script's entry point: compose and check everything, then train.

    ``train`` is ``"<module>:<function>"``, imported only once the config passed, so that a refusal
    takes about a second. A refusal prints ``error: <key>: <reason>`` on stderr and exits 2, before
    any file is written. The first Ctrl-C or a SIGTERM stops the run at its next update or collection
    boundary with a checkpoint; the script then prints the command that resumes it and exits 130 / 143.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    script = script or sys.argv[0]
    if argv and argv[0] in ("-h", "--help"):
        print(f"usage: python {script} [key=value ...] [--config-dir DIR]\n"
              f"the keys and their defaults: python {script} --cfg")
        return
    try:
        cfg = compose_command_line(config_name, [a for a in argv if a != "--cfg"])
        if "--cfg" in argv:  # hydra's --cfg job: print the composed config, run nothing
            print(OmegaConf.to_yaml(cfg))
            return
        try:
            check_config(cfg)
        except OmegaConfBaseException as error:  # e.g. an interpolation that cannot resolve
            raise ConfigError("", _one_line(error)) from None
        check_run_folder(cfg, quiet=True)  # train's start_run checks it again, and says what it found
        check_device(cfg.device)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    module, _, function = train.partition(":")
    run: Callable = getattr(importlib.import_module(module), function)
    try:
        run(cfg, resume_command=_resume_command(script, argv))
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    except ConfigError as error:  # a check that needs the built objects (a task model's, say)
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
