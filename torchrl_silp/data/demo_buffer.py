"""The planner-backed demonstration buffer and the mixed demo / interaction sampler."""

from __future__ import annotations

import inspect
import json
import time
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorDictReplayBuffer

from torchrl_silp.data.storage import FilledStorageCheckpointer
from torchrl_silp.models.base import as_model
from torchrl_silp.models.check import ensure_checked
from torchrl_silp.planning import plan_demonstrations
from torchrl_silp.planning.demos import check_planner_kwargs
from torchrl_silp.validation import check_bool, check_choice, check_positive_int, check_probability

__all__ = ["DemoReplayBuffer", "MixedReplay", "TRANSITION_KEYS", "transition_keys"]

# What a transition needs for off-policy learning: the keys both buffers
# store, so that one sampled batch concatenates demos and interaction.
TRANSITION_KEYS: tuple[NestedKey, ...] = (
    "observation",
    "action",
    "is_demo",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)


def transition_keys(model, observation_keys: Sequence[NestedKey] = ("observation",)) -> tuple[NestedKey, ...]:
    """The keys a SILP+ transition keeps: :data:`TRANSITION_KEYS`, the networks' further inputs
    ``observation_keys``, and the model's named state at the root and under ``"next"`` (which the
    reward filter's model look-ahead and hindsight relabelling read).

    Examples:
        >>> from torchrl_silp.models import UR5eReach
        >>> keys = transition_keys(UR5eReach(), ("observation", "goal_offset"))
        >>> ("next", "achieved_goal") in keys, "goal_offset" in keys
        (True, True)
    """
    model = as_model(model)
    keys = list(TRANSITION_KEYS)
    for key in (*observation_keys, *model.state_keys):
        for k in (key, ("next", key) if isinstance(key, str) else ("next", *key)):
            if k not in keys:
                keys.append(k)
    return tuple(keys)


def _storage_device(device):
    # LazyTensorStorage wants "auto" (store where the data comes from), not None
    return "auto" if device is None else torch.device(device)


def _flat(data: TensorDictBase) -> TensorDictBase:
    return data.reshape(-1) if data.batch_dims != 1 else data


def own_signature(cls: type) -> type:
    """Class decorator giving a replay-buffer subclass its ``__init__``'s signature.

    ``inspect.signature`` (and so ``help()`` and IDEs) would otherwise show TorchRL's
    ``ReplayBuffer.__new__`` (``*args, use_ray_service=...``). A class's ``__signature__`` is the hook
    ``inspect.signature`` documents for this (PEP 362), so no private state is touched.
    """
    init = inspect.signature(cls.__init__)
    cls.__signature__ = init.replace(parameters=list(init.parameters.values())[1:])
    return cls


@own_signature
class DemoReplayBuffer(TensorDictReplayBuffer):
    """A replay buffer whose ``extend(episodes)`` plans demonstrations from them.

    Every call runs the experience-based planner
    (:func:`~torchrl_silp.planning.plan_demonstrations`) on the episodes of a
    collector batch (``[B, T]`` or flat) and stores the resulting MDP
    transitions, flagged ``"is_demo"``. Everything else is a TorchRL
    :class:`~torchrl.data.TensorDictReplayBuffer`: sampling, samplers, and
    :meth:`dumps` / :meth:`loads` through the storage checkpointers.

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` the planner uses (or an env holding one).
        capacity: number of demo transitions kept (FIFO); ignored when ``storage`` is given.
        storage: a TorchRL storage; ``LazyTensorStorage(capacity, device=device)`` by default.
        device: device of the default storage.
        keys: keys stored for each demo transition; :func:`transition_keys` of the model and
            the observation keys by default, ``None`` keeps all the planner returns.
        observation_transform: builds the networks' inputs (``"observation"``, ...) from a named
            state, as the env's transforms do; the model's :class:`~torchrl.envs.CatTensors`
            by default. Give the env's observation transforms here (e.g. with an
            :class:`~torchrl.envs.ObservationNorm`) so demos and interaction data match.
        observation_keys: what ``observation_transform`` writes (stored with the named keys).
        planner_kwargs: forwarded to :func:`plan_demonstrations` (``d``, ``n_pairs``,
            ``step_size``, ``method``, ``goal_node``, ...).
        **kwargs: forwarded to :class:`~torchrl.data.TensorDictReplayBuffer`
            (``batch_size``, ``sampler``, ``transform``, ...).

    Attributes:
        planning_time: total seconds spent planning in :meth:`extend`.
        episodes_planned: number of episodes given to the planner.
        demos_added: number of demo transitions stored (including overwritten ones).

    Examples:
        >>> from torchrl_silp import ReachEnv, UR5eReach
        >>> from torchrl_silp.data import DemoReplayBuffer
        >>> env = ReachEnv(UR5eReach(), num_envs=4, seed=0)
        >>> episodes = env.rollout(50, break_when_any_done=False)
        >>> demos = DemoReplayBuffer(env.model, capacity=10_000, batch_size=32)
        >>> _ = demos.extend(episodes)
        >>> len(demos) > 0
        True
        >>> bool(demos.sample()["is_demo"].all())
        True
    """

    def __init__(
        self,
        model,
        *,
        capacity: int = 100_000,
        storage=None,
        device: torch.device | str | None = None,
        keys: Sequence[NestedKey] | None | str = "default",
        observation_transform=None,
        observation_keys: Sequence[NestedKey] = ("observation",),
        planner_kwargs: dict | None = None,
        **kwargs,
    ):
        model = as_model(model)
        ensure_checked(model)  # e.g. bool collision flags, which the planner's bit tests would read as "free"
        if storage is None:
            check_positive_int(capacity, name="capacity")
            storage = LazyTensorStorage(capacity, device=_storage_device(device))
            kwargs.setdefault("checkpointer", FilledStorageCheckpointer())
        planner_kwargs = dict(planner_kwargs or {})
        if "observation_transform" in planner_kwargs:
            raise ValueError("pass observation_transform to DemoReplayBuffer, not in planner_kwargs")
        check_planner_kwargs(planner_kwargs)
        super().__init__(storage=storage, **kwargs)
        self.model = model
        self.observation_transform = observation_transform
        if isinstance(keys, str):
            if keys != "default":
                raise ValueError(f"keys must be a sequence of keys, None or 'default', got {keys!r}")
            keys = transition_keys(model, observation_keys)
        self.keys = None if keys is None else tuple(keys)
        self.planner_kwargs = planner_kwargs
        self.planning_time = 0.0
        self.episodes_planned = 0
        self.demos_added = 0

    def extend(self, episodes: TensorDictBase, *args, **kwargs) -> torch.Tensor:
        """Plan demonstrations from ``episodes`` and store them; returns their indices.

        Episodes that yield no demonstration (no path found) add nothing.
        """
        ensure_checked(self.model)  # a model changed since the buffer was built is checked again
        start = time.perf_counter()
        demos = plan_demonstrations(
            self.model, episodes, observation_transform=self.observation_transform, **self.planner_kwargs
        )
        self.planning_time += time.perf_counter() - start
        self.episodes_planned += _count_episodes(episodes)
        return self.add_demonstrations(demos, *args, **kwargs)

    def add_demonstrations(self, demos: TensorDictBase, *args, **kwargs) -> torch.Tensor:
        """Store ready-made demo transitions (flagged ``"is_demo"``) without planning."""
        demos = _flat(demos)
        if demos.batch_size.numel() == 0:
            return torch.empty(0, dtype=torch.long)
        demos.set("is_demo", torch.ones(*demos.batch_size, 1, dtype=torch.bool, device=demos.device))
        if self.keys is not None:
            demos = demos.select(*self.keys)
        self.demos_added += demos.numel()
        return super().extend(demos, *args, **kwargs)

    def dumps(self, path):
        super().dumps(path)
        stats = {"planning_time": self.planning_time, "episodes_planned": self.episodes_planned,
                 "demos_added": self.demos_added}
        (Path(path) / "demo_stats.json").write_text(json.dumps(stats))

    def loads(self, path):
        super().loads(path)
        stats_file = Path(path) / "demo_stats.json"
        if stats_file.exists():
            stats = json.loads(stats_file.read_text())
            self.planning_time = stats["planning_time"]
            self.episodes_planned = stats["episodes_planned"]
            self.demos_added = stats["demos_added"]


def _count_episodes(episodes: TensorDictBase) -> int:
    """Trajectory segments in a ``[..., T]`` batch: finished episodes plus each row's unfinished tail."""
    done = episodes.get(("next", "done"), None)
    if done is None or episodes.batch_dims == 0:
        return 0
    d = done.reshape(-1, episodes.batch_size[-1])
    return int(d.sum()) + int((~d[:, -1]).sum())


def _dump(buffer: ReplayBuffer, path: Path) -> None:
    # TorchRL's checkpointers refuse a storage that was never written to
    path.mkdir(parents=True, exist_ok=True)
    if len(buffer) == 0:
        (path / "EMPTY").touch()
    else:
        buffer.dumps(path)


def _load(buffer: ReplayBuffer, path: Path) -> None:
    if not (path / "EMPTY").exists():
        buffer.loads(path)


class MixedReplay:
    """Samples ``N_D`` demonstrations and ``N_pi`` interaction transitions per batch, exactly.

    The paper's SILP+ batch: ``round(demo_fraction * batch_size)`` transitions
    from the demonstration buffer and the rest from the interaction buffer,
    concatenated into one ``[batch_size]`` TensorDict with ``"is_demo"`` set on
    each part. Before the demo buffer holds anything every sample comes from the
    interaction buffer (and the other way round).

    This mirrors :class:`torchrl.data.OfflineToOnlineReplayBuffer` (exact split
    per batch) but does not wrap it: that class treats its offline part as an
    immutable, non-empty dataset, has no ``"is_demo"`` flag and no
    ``dumps``/``loads``; here both parts grow during training, either may be
    empty, and both are checkpointed.

    :meth:`extend` stores interaction data, dropping transitions flagged
    ``("next", "discard")`` (collision type 1 of the env). Demonstrations go into
    the demo buffer directly (``mixed.demo_buffer.extend(episodes)``).

    With ``collision_terminal``, a stored transition whose step collided
    (``("next", "collision")``) is stored with ``("next", "terminated")`` set: its TD
    target is its reward alone, not followed by the value of the state the arm was
    put back to (collision types 1 and 2 restore it), so the collision's value is
    its penalty wherever the arm stands. Only the stored copy changes: the episode
    goes on, and ``("next", "done")``, which marks episode boundaries, is kept.

    Args:
        demo_buffer: the :class:`DemoReplayBuffer` (any TorchRL replay buffer works).
        interaction_buffer: a TorchRL replay buffer; by default a
            ``TensorDictReplayBuffer(LazyTensorStorage(interaction_capacity, device=device))``.
        interaction_capacity: capacity of the default interaction buffer.
        demo_fraction: fraction of each batch drawn from demonstrations, in ``[0, 1]``,
            or ``"proportional"``: the number of demos in a batch is binomial with the
            demo buffer's share of all stored transitions, i.e. sampling as if both
            lived in one ordinary replay buffer (the paper's *-Demon baselines).
        batch_size: default ``sample`` size.
        keys: keys kept in both parts (must be present in both); by default the demo buffer's
            ``keys`` when it has them, else :data:`TRANSITION_KEYS`.
        device: where sampled batches are returned (default: where they are stored).
        collision_terminal: store collision steps as terminal (see above).

    Examples:
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from torchrl_silp import CollisionHandling, ReachEnv, UR5eReach
        >>> model = UR5eReach()
        >>> env = TransformedEnv(ReachEnv(model, num_envs=4, seed=0), Compose(CollisionHandling(2), model.observation_transform()))
        >>> from torchrl_silp.data import DemoReplayBuffer, MixedReplay
        >>> episodes = env.rollout(50, break_when_any_done=False)
        >>> mixed = MixedReplay(DemoReplayBuffer(env.model), demo_fraction=0.25, batch_size=64)
        >>> _ = mixed.extend(episodes)
        >>> mixed.sample()["is_demo"].sum().item()  # no demos planned yet
        0
        >>> _ = mixed.demo_buffer.extend(episodes)
        >>> mixed.sample()["is_demo"].sum().item()
        16
    """

    def __init__(
        self,
        demo_buffer: ReplayBuffer,
        interaction_buffer: ReplayBuffer | None = None,
        *,
        interaction_capacity: int = 1_000_000,
        demo_fraction: float = 0.25,
        batch_size: int | None = None,
        keys: Sequence[NestedKey] | None = None,
        device: torch.device | str | None = None,
        collision_terminal: bool = False,
    ):
        check_bool(collision_terminal, name="collision_terminal")
        if keys is None:
            keys = getattr(demo_buffer, "keys", None) or TRANSITION_KEYS
        if isinstance(demo_fraction, str):  # else a number in [0, 1]
            check_choice(demo_fraction, ("proportional",), name="demo_fraction")
        else:
            check_probability(demo_fraction, name="demo_fraction", closed=True)
        check_positive_int(batch_size, name="batch_size", optional=True)
        if interaction_buffer is None:
            check_positive_int(interaction_capacity, name="interaction_capacity")
            interaction_buffer = TensorDictReplayBuffer(
                storage=LazyTensorStorage(interaction_capacity, device=_storage_device(device)),
                checkpointer=FilledStorageCheckpointer(),
            )
        self.demo_buffer = demo_buffer
        self.interaction_buffer = interaction_buffer
        self.demo_fraction = demo_fraction if demo_fraction == "proportional" else float(demo_fraction)
        self.batch_size = batch_size
        self.keys = tuple(keys)
        self.device = None if device is None else torch.device(device)
        self.discarded = 0
        self.collision_terminal = collision_terminal

    def extend(self, data: TensorDictBase) -> torch.Tensor:
        """Store interaction transitions (any batch shape); returns their indices."""
        data = _flat(data)
        discard = data.get(("next", "discard"), None)
        if discard is not None:
            keep = ~discard.reshape(-1)
            self.discarded += int((~keep).sum())
            data = data[keep]
        if self.collision_terminal:
            collision = data.get(("next", "collision"), None)
            if collision is None:
                raise KeyError("MixedReplay(collision_terminal=True).extend: the data has no ('next', 'collision')")
            terminated = data.get(("next", "terminated")) | collision.reshape(data.get(("next", "terminated")).shape)
        data = data.select(*[k for k in self.keys if k != "is_demo"])
        if self.collision_terminal:
            data.set(("next", "terminated"), terminated)  # a new tensor: the caller's data keeps its flags
        data.set("is_demo", torch.zeros(*data.batch_size, 1, dtype=torch.bool, device=data.device))
        if data.numel() == 0:
            return torch.empty(0, dtype=torch.long)
        return self.interaction_buffer.extend(data)

    def split(self, batch_size: int) -> tuple[int, int]:
        """``(N_D, N_pi)`` for a batch of ``batch_size`` given what the buffers hold now (random when proportional)."""
        n_stored_demo, n_stored = len(self.demo_buffer), len(self)
        if self.demo_fraction == "proportional":
            share = torch.tensor(n_stored_demo / max(n_stored, 1), dtype=torch.float64)
            n_demo = int(torch.binomial(torch.tensor(float(batch_size), dtype=torch.float64), share))
        else:
            n_demo = round(self.demo_fraction * batch_size)
        if n_stored_demo == 0:
            n_demo = 0
        elif len(self.interaction_buffer) == 0:
            n_demo = batch_size
        return n_demo, batch_size - n_demo

    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        """A ``[batch_size]`` batch: ``N_D`` demos first, then ``N_pi`` interaction transitions."""
        batch_size = self.batch_size if batch_size is None else batch_size
        if batch_size is None:
            raise ValueError("batch_size must be given here or to MixedReplay(batch_size=...)")
        check_positive_int(batch_size, name="batch_size")
        if len(self.demo_buffer) == 0 and len(self.interaction_buffer) == 0:
            raise RuntimeError("MixedReplay.sample: both buffers are empty")
        n_demo, n_pi = self.split(batch_size)
        parts = []
        if n_demo:
            parts.append(self._take(self.demo_buffer, n_demo, True))
        if n_pi:
            parts.append(self._take(self.interaction_buffer, n_pi, False))
        out = torch.cat(parts) if len(parts) > 1 else parts[0]
        return out if self.device is None else out.to(self.device)

    def _take(self, buffer: ReplayBuffer, n: int, is_demo: bool) -> TensorDictBase:
        td = buffer.sample(n)
        missing = [k for k in self.keys if k != "is_demo" and k not in td.keys(include_nested=True)]
        if missing:
            raise KeyError(f"MixedReplay: the {'demo' if is_demo else 'interaction'} buffer lacks keys {missing}")
        td = td.select(*[k for k in self.keys if k != "is_demo"])
        td.set("is_demo", torch.full((n, 1), is_demo, dtype=torch.bool, device=td.device))
        return td

    def __len__(self) -> int:
        return len(self.demo_buffer) + len(self.interaction_buffer)

    def dumps(self, path) -> None:
        """Checkpoint both buffers (TorchRL storage checkpointers) under ``path``."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        _dump(self.demo_buffer, path / "demos")
        _dump(self.interaction_buffer, path / "interaction")
        meta = {"demo_fraction": self.demo_fraction, "batch_size": self.batch_size, "discarded": self.discarded}
        (path / "mixed.json").write_text(json.dumps(meta))

    def loads(self, path) -> None:
        """Restore both buffers from :meth:`dumps` output."""
        path = Path(path)
        _load(self.demo_buffer, path / "demos")
        _load(self.interaction_buffer, path / "interaction")
        meta = json.loads((path / "mixed.json").read_text())
        self.demo_fraction, self.batch_size, self.discarded = meta["demo_fraction"], meta["batch_size"], meta["discarded"]
