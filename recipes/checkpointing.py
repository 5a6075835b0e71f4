"""Checkpoints of a training run: save, restore, resume checks, and a run's networks rebuilt for evaluation.

A checkpoint is a directory (``<run_dir>/checkpoint``) holding ``state.pt`` (networks, optimisers,
counters, RNG states) and the buffers, written atomically. A resume is refused when the run's
config differs from the checkpointed one in a field that changes the networks' or buffers' shape
or meaning (:data:`~torchrl_silp.recipes.preflight.RESUME_FIELDS`). :class:`StopRequest` turns SIGTERM / SIGINT into a checkpoint
and a stop.

Why not ``torchrl.checkpoint.Checkpoint``: it writes ``manifest.json`` + ``components/``, not the
``state.pt`` + ``buffers/`` that :func:`~torchrl_silp.recipes.preflight.find_checkpoint` (with its ``.old``
fallback), :func:`load_trained_networks` and existing runs read. Nor is it a drop-in: no adapter is
inferred for :class:`~torchrl_silp.data.MixedReplay` (``dumps``/``loads``) or the env's ``torch.Generator``,
and ``GlobalRNGState`` omits the latter. It would replace only the atomic rename of :func:`save_checkpoint`.
"""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from pathlib import Path

import torch

from torchrl_silp.data import MixedReplay, cut_episodes
from torchrl_silp.recipes.builders import make_actor_critic, make_loss, observation_norm
from torchrl_silp.recipes.metrics import new_counters
from torchrl_silp.recipes.preflight import check_run_folder, find_checkpoint




def check_resume(cfg, run_dir: Path) -> bool:
    """Whether ``cfg`` resumes from ``run_dir``'s checkpoint (:func:`~torchrl_silp.recipes.preflight.check_run_folder`
    on ``cfg`` with that folder): refuses a fresh start over a checkpoint, ``resume=must`` without one, and a
    resume whose config differs from the checkpointed run's in a field of ``RESUME_FIELDS``."""
    if Path(cfg.run_dir) != Path(run_dir):
        cfg = cfg.copy()
        cfg.run_dir = str(run_dir)
    return check_run_folder(cfg)


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


class StopRequest:
    """SIGTERM / SIGINT while training: the loop stops at its next update or collection boundary,
    checkpoints and ends.

    Used as a context manager around the loop (the handlers are those of the main thread only;
    elsewhere, e.g. in a thread of a Ray worker, nothing is installed and the default
    behaviour stays). A second signal gets the previous handler: it stops at once.
    :meth:`exit` then ends the process the way the signal would have: ``KeyboardInterrupt``
    for SIGINT (a script's entry point turns it into exit status 130), exit status 143 for SIGTERM.
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
        print(f"\n{signal.Signals(signum).name}: stopping at the next update with a checkpoint "
              "(send it again to stop at once)", flush=True)

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def exit(self, message: str) -> None:
        print(message, flush=True)
        if self.signum == signal.SIGINT:
            raise KeyboardInterrupt(message)
        raise SystemExit(128 + self.signum)

    def exit_run(self, counters: dict, ckpt_dir: Path, resume_command: str | None = None) -> None:
        """:meth:`exit` a training loop the signal stopped, saying where its checkpoint is and how to
        continue (``resume_command``, or the generic ``resume=true``)."""
        if not counters["frames"]:  # before the first batch: nothing to save or resume
            self.exit("stopped before the first collector batch: nothing was collected or trained")
        how = resume_command or "resume=true and the same config"
        self.exit(f"stopped at {counters['frames']:,} frames and {counters['updates']:,} updates with a checkpoint "
                  f"in {ckpt_dir}; continue with: {how}")


def training_state(loss, optimizers, averaged, counters, history, assembler, logger, env, norm=None) -> dict:
    """What a checkpoint holds besides the buffers (``norm``: the run's
    :class:`~torchrl_silp.RunningObservationNorm`, whose statistics the networks' inputs depend on)."""
    return {
        "loss": loss.state_dict(), "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "averaged_actor": averaged.state_dict() if averaged is not None else None,
        "observation_norm": norm.state_dict() if norm is not None else None,
        "counters": dict(counters), "history": list(history), "assembler": assembler.state_dict(),
        "logger": logger.state_dict() if hasattr(logger, "state_dict") else None,
        "torch_rng": torch.get_rng_state(), "env_rng": env.base_env.rng.get_state(),
        "saved_at": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def checkpoint_run(path: Path, loss, optimizers, averaged, counters, history, assembler, logger, env,
                   buffers: MixedReplay, norm=None) -> float:
    """Save the run's checkpoint (:func:`training_state` and the buffers); returns when, as ``time.monotonic()``."""
    save_checkpoint(path, training_state(loss, optimizers, averaged, counters, history, assembler, logger, env, norm),
                    buffers)
    return time.monotonic()


def restore(path: Path, cfg, loss, optimizers, averaged, buffers: MixedReplay, assembler, env, norm=None) -> tuple:
    """Load a checkpoint into the run's objects: ``(counters, history, logger_state)``; ``norm``: the run's
    :class:`~torchrl_silp.RunningObservationNorm`, which gets the checkpoint's statistics.

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
    if norm is not None:
        _load_norm(norm, state)
    assembler.load_state_dict(state["assembler"])
    torch.set_rng_state(state["torch_rng"])
    env.base_env.rng.set_state(state["env_rng"])
    leftover = assembler.flush()
    if leftover is not None and cfg.replay_buffer.her:
        buffers.extend(cut_episodes(leftover))
    if leftover is not None and cfg.silp.demos:
        buffers.demo_buffer.extend(leftover)
    counters = {**new_counters(), **state["counters"]}  # a counter added since the save starts at its start value
    print(f"resumed from {path} (saved {state.get('saved_at', 'at an unknown time')}): {counters['frames']} frames, "
          f"{counters['updates']} updates, {len(buffers)} transitions in the buffers")
    return counters, state["history"], state["logger"]


def _load_norm(norm, state: dict) -> None:
    if state.get("observation_norm") is None:
        raise ValueError("network.normalize_observation is set but the checkpoint holds no observation "
                         "statistics: use the config the run was saved with")
    norm.load_state_dict(state["observation_norm"])


def load_checkpoint(path: Path, buffers: MixedReplay) -> dict:
    """The state a checkpoint holds; its buffers are loaded into ``buffers``."""
    found = find_checkpoint(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    state = torch.load(found / "state.pt", weights_only=False)
    buffers.loads(found / "buffers")
    return state


def load_trained_networks(cfg, model, env, path: Path, device) -> tuple:
    """A run's networks, rebuilt from its config and loaded from its checkpoint: ``(actor, loss, state)``.

    ``actor`` holds the parameters the run evaluated: the average of the
    actor's parameters when the run kept one (``eval.actor_average_decay``),
    else the online actor; ``loss`` holds the online networks (critic included). With
    ``network.normalize_observation`` the model's :func:`~torchrl_silp.recipes.builders.observation_norm` gets
    the run's statistics, so that ``make_observation_transform(cfg, model)`` builds the actor's inputs as it did.
    """
    found = find_checkpoint(path)
    if found is None:
        raise FileNotFoundError(f"no checkpoint under {path}")
    actor, critic = make_actor_critic(cfg, model, env, device)
    loss, _ = make_loss(cfg, actor, critic, model, env)
    state = torch.load(found / "state.pt", map_location=device, weights_only=False)
    loss.load_state_dict(state["loss"])
    norm = observation_norm(cfg, model)
    if norm is not None:  # what make_observation_transform(cfg, model) builds the actor's inputs with
        _load_norm(norm, state)
    if state.get("averaged_actor") is not None:
        averaged = {k[len("module."):]: v for k, v in state["averaged_actor"].items() if k.startswith("module.")}
        actor.load_state_dict(averaged)
    return actor, loss, state
