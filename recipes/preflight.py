"""What a training script does before it imports torch or writes a file: compose the command line,
check the config (:func:`~torchrl_silp.recipes.schema.check_config`) and what it asks of its run folder.

A refusal is a :class:`~torchrl_silp.recipes.schema.ConfigError`, whose one-line message names the key
as the user types it (``env.num_envs``, ``planner.d``). :func:`main` is the scripts' entry point: it
composes the config from the command line with hydra's compose API (so hydra writes no ``outputs/``
folder), runs the checks, prints ``error: <message>`` and exits 2 on a refusal, and only then imports
the recipe and trains; Ctrl-C and SIGTERM end it with 130 / 143 and the line that resumes the run.

This module imports hydra, omegaconf and the torch-free :mod:`~torchrl_silp.recipes.schema`, so that a
bad command line is refused within about a second.
"""

from __future__ import annotations

import importlib
import re
import shlex
import sys
from pathlib import Path
from typing import Callable, Sequence

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_silp.recipes.schema import RESUME_MODES, ConfigError, check_config, check_device

__all__ = [
    "RESUME_FIELDS", "check_run_folder", "checkpoint_exists", "compose_command_line", "find_checkpoint", "main",
    "resume_fields_differ",
]

# fields whose change makes a checkpoint's networks or buffers the wrong shape or meaning
RESUME_FIELDS = ("algorithm", "env.name", "env.model", "env.robot", "env.num_envs", "env.max_steps", "network",
                 "replay_buffer.size", "replay_buffer.demo_size", "replay_buffer.her", "silp.bc",
                 "source", "source_run_dir")
# fields whose presence (set or null) must match; their value may change on resume
RESUME_PRESENCE_FIELDS = ("eval.actor_average_decay",)
# keys added within a RESUME_FIELDS section since runs were saved: a saved config without one ran with this value
ADDED_FIELDS = {"network.normalize_observation": False, "network.next_clearance_feature": False, "env.model.boxes": None}


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
    config (``(field, here, there)``), or None."""
    saved = OmegaConf.to_container(OmegaConf.load(saved_path), resolve=True)
    now = OmegaConf.to_container(cfg, resolve=True)
    for key, value in ADDED_FIELDS.items():
        section, name = key.rsplit(".", 1)
        for config in (saved, now):  # a config without the key (older, or a recipe's that lacks it) ran with this value
            if isinstance(_dotted(config, section), dict):
                _dotted(config, section).setdefault(name, value)
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
