"""Whole episodes out of collector batches: :class:`EpisodeAssembler` and :func:`cut_episodes`.

A TorchRL collector cuts its rollouts into batches of ``frames_per_batch``
frames regardless of episode boundaries; the planner of the demonstration
buffer and hindsight relabelling need whole episodes. The collector marks each
step with its trajectory, ``("collector", "traj_ids")``; the pieces of one
trajectory are joined by that id.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

__all__ = ["EpisodeAssembler", "cut_episodes", "TRAJ_KEY", "DONE_KEY"]

TRAJ_KEY = ("collector", "traj_ids")
DONE_KEY = ("next", "done")


def _episode_order(ids: torch.Tensor) -> torch.Tensor:
    # stable: each trajectory's steps keep the order they came in (time order)
    return torch.sort(ids, stable=True).indices


class EpisodeAssembler:
    """Joins the pieces of episodes that span collector batches, by ``("collector", "traj_ids")``.

    :meth:`push` takes a collector batch (any batch shape whose flattening puts
    each trajectory's steps in time order, as the collector's
    ``(*env_batch, time)`` layout does) and returns the transitions of every
    episode that finished in it (``("next", "done")`` set on its last step),
    whole and in time order, grouped by trajectory id in increasing order, as
    one flat TensorDict; ``None`` when none finished. The unfinished pieces are
    kept (:attr:`pending`) and joined to the next batch. :meth:`flush` hands
    them out (e.g. at the end of training, or on resume, where the collector
    starts new episodes; :func:`cut_episodes` makes them whole truncated ones).

    The pending pieces are the assembler's state: :meth:`state_dict` and
    :meth:`load_state_dict` carry them through a checkpoint (plain tensors,
    loadable with ``torch.load(..., weights_only=True)``).

    Why not the collector's ``trajs_per_batch``: with it, ``Collector`` yields only finished
    episodes, ``trajs_per_batch`` at a time, never the ``frames_per_batch`` batch the loop counts,
    normalizes, stores (without hindsight relabelling) and runs its updates per batch on. Its
    unfinished pieces (``_traj_assembly``) are not in ``Collector.state_dict()``, so a resumed run
    would lose them. Finished episodes short of ``trajs_per_batch`` at the end are never yielded.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_silp.data.episodes import EpisodeAssembler
        >>> def batch(ids, t, done):  # a collector-like batch [envs, time]
        ...     n = torch.tensor(ids).shape
        ...     return TensorDict({
        ...         ("collector", "traj_ids"): torch.tensor(ids),
        ...         "t": torch.tensor(t),
        ...         ("next", "done"): torch.tensor(done).unsqueeze(-1),
        ...     }, batch_size=n)
        >>> asm = EpisodeAssembler()
        >>> # env 0 runs episode 0 (3 steps) then episode 2; env 1 runs episode 1 (4 steps)
        >>> asm.push(batch([[0, 0], [1, 1]], [[0, 1], [0, 1]], [[False, False], [False, False]])) is None
        True
        >>> out = asm.push(batch([[0, 2], [1, 1]], [[2, 0], [2, 3]], [[True, False], [False, True]]))
        >>> out["collector", "traj_ids"].tolist(), out["t"].tolist()
        ([0, 0, 0, 1, 1, 1, 1], [0, 1, 2, 0, 1, 2, 3])
        >>> asm.pending["collector", "traj_ids"].tolist()
        [2]
        >>> restored = EpisodeAssembler()
        >>> restored.load_state_dict(asm.state_dict())
        >>> restored.flush()["t"].tolist(), restored.flush()
        ([0], None)
    """

    def __init__(self, traj_key=TRAJ_KEY, done_key=DONE_KEY):
        self.traj_key = traj_key
        self.done_key = done_key
        #: the unfinished pieces, flat and in arrival order; ``None`` when there are none
        self.pending: TensorDictBase | None = None

    @property
    def num_pending(self) -> int:
        """How many transitions wait for their episode to finish."""
        return 0 if self.pending is None else self.pending.batch_size.numel()

    def push(self, batch: TensorDictBase) -> TensorDictBase | None:
        """Add a batch; return the whole episodes that finished (flat, by trajectory, in time order) or ``None``."""
        flat = batch.reshape(-1)
        if self.num_pending:
            flat = torch.cat([self.pending, flat])
        ids = flat.get(self.traj_key).reshape(-1)
        done = flat.get(self.done_key).reshape(-1)
        finished = torch.isin(ids, ids[done])
        self.pending = flat[~finished]
        if not finished.any():
            return None
        out = flat[finished]
        return out[_episode_order(out.get(self.traj_key).reshape(-1))]

    def flush(self) -> TensorDictBase | None:
        """Hand out (and forget) the unfinished pieces, in arrival order; ``None`` when there are none."""
        out, self.pending = self.pending, None
        return out if out is not None and out.batch_size.numel() else None

    def state_dict(self) -> dict:
        """The pending pieces as a nested dict of tensors (``None`` when there are none)."""
        return {"pending": self.pending.to_dict() if self.num_pending else None}

    def load_state_dict(self, state_dict: dict) -> None:
        """Restore the pending pieces of :meth:`state_dict` (replacing the current ones)."""
        if "pending" not in state_dict:
            raise KeyError("state_dict lacks 'pending' (not an EpisodeAssembler state)")
        pending = state_dict["pending"]
        if pending is None:
            self.pending = None
        elif isinstance(pending, TensorDictBase):
            self.pending = pending.reshape(-1).clone()
        else:
            self.pending = TensorDict.from_dict(pending, batch_dims=1)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_pending={self.num_pending})"


def cut_episodes(pieces: TensorDictBase, traj_key=TRAJ_KEY) -> TensorDictBase:
    """Unfinished episodes (what :meth:`EpisodeAssembler.flush` returns) as whole truncated ones.

    Each trajectory's steps are made contiguous and in time order (a stable
    sort by trajectory id) and its last step is flagged ``("next", "truncated")``
    and ``("next", "done")``: what a buffer that reads episode boundaries from
    ``("next", "done")`` (hindsight relabelling) needs. The input is not modified.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_silp.data.episodes import cut_episodes
        >>> pieces = TensorDict({
        ...     ("collector", "traj_ids"): torch.tensor([4, 5, 4, 5, 4]),
        ...     "t": torch.tensor([0, 0, 1, 1, 2]),
        ...     ("next", "done"): torch.zeros(5, 1, dtype=torch.bool),
        ...     ("next", "truncated"): torch.zeros(5, 1, dtype=torch.bool),
        ... }, batch_size=[5])
        >>> out = cut_episodes(pieces)
        >>> out["collector", "traj_ids"].tolist(), out["t"].tolist()
        ([4, 4, 4, 5, 5], [0, 1, 2, 0, 1])
        >>> out["next", "done"].squeeze(-1).tolist()
        [False, False, True, False, True]
    """
    ids = pieces.get(traj_key).reshape(-1)
    order = _episode_order(ids)
    out = pieces.reshape(-1)[order].clone()
    ids = ids[order]
    last = torch.ones_like(ids, dtype=torch.bool)
    last[:-1] = ids[1:] != ids[:-1]
    last = last.view(-1, 1)
    out["next", "truncated"] = out["next", "truncated"] | last
    out["next", "done"] = out["next", "done"] | last
    return out
