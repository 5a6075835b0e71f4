"""Checkpoints of a training run: save, restore, resume checks, and a run's networks rebuilt for evaluation.

A checkpoint is a directory (``<run_dir>/checkpoint``) holding ``state.pt`` (networks, optimisers,
counters, RNG states) and the buffers, written atomically. A resume is refused when the run's
config differs from the checkpointed one in a field that changes the networks' or buffers' shape
or meaning (:data:`RESUME_FIELDS`). :class:`StopRequest` turns SIGTERM / SIGINT into a checkpoint
and a stop.
"""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from torchrl_silp.data import MixedReplay, cut_episodes
from torchrl_silp.recipes.builders import make_actor_critic, make_loss


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
    """The state a checkpoint holds; its buffers are loaded into ``buffers``."""
    found = _checkpoint_dir(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    state = torch.load(found / "state.pt", weights_only=False)
    buffers.loads(found / "buffers")
    return state


def checkpoint_exists(path: Path) -> bool:
    """Whether ``path`` (or what a save killed midway left of it) holds a checkpoint."""
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
