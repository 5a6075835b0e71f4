"""The task-model interface: everything SILP+ needs to know about a goal-conditioned task.

A task model is stateless and batched. A *state* is a TensorDict holding the
model's named keys (:attr:`TaskModel.state_keys`): the configuration the
planner connects (``"joint_position"``), the goal the arm achieves there
(``"achieved_goal"``, e.g. the TCP), the scene that stays fixed during an
episode (:attr:`TaskModel.scene_keys`, e.g. ``"obstacle"``) and the goal to
reach (``"desired_goal"``), the names TorchRL's ``HERReplayBuffer`` and
Gymnasium-Robotics use. Components (planner, demo buffer, loss, exploration,
relabelling, evaluation) read these names and call the model; none of them
knows a robot or an index into a flat observation. The flat ``"observation"``
the networks read is built from the names by TorchRL's
:class:`~torchrl_silp.transforms.FlatCatTensors` (:meth:`TaskModel.observation_transform`).

A robot task implements the abstract members (kinematics, collision test of
configurations, its clearance, task sampling); transition, reward, the swept
collision test of a motion and relabelling follow from them here.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Composite, Unbounded

from torchrl_silp.transforms import FlatCatTensors
from torchrl_silp.validation import all_finite, check_bool, check_finite, check_positive_float, check_tensor

__all__ = ["TaskModel", "as_model", "CONFIG_KEY", "ACHIEVED_GOAL_KEY", "DESIRED_GOAL_KEY", "GOAL_CONFIG_KEY"]

CONFIG_KEY = "joint_position"
ACHIEVED_GOAL_KEY = "achieved_goal"
DESIRED_GOAL_KEY = "desired_goal"
GOAL_CONFIG_KEY = "goal_joint_position"

# configurations per collision-kernel call: bounds the (configurations x spheres) temporaries
_CHUNK = 32768


def check_boxes(name: str, boxes: torch.Tensor) -> None:
    """Boxes ``(..., 6k)`` ``(xmin, xmax, ymin, ymax, zmin, zmax)``: finite, each min <= max."""
    if torch.compiler.is_compiling():
        return
    b = boxes.reshape(-1, 3, 2)
    if b.numel() == 0:
        return
    # one host sync on the hot path (a NaN fails the comparison too); the messages are told apart after
    if bool(((b[..., 1] - b[..., 0]).amin() >= 0) & all_finite(b)):
        return
    check_finite(boxes, name=name)
    raise ValueError(f"{name}: a box has min > max (boxes are (xmin, xmax, ymin, ymax, zmin, zmax))")


# the robot layer's names for check_finite / check_tensor, with the name first
def _check_finite(name: str, value: torch.Tensor) -> None:
    check_finite(value, name=name)


def _check_tensor(name: str, value, last_dim: int | None = None) -> None:
    check_tensor(value, name=name, last_dim=last_dim)


def as_model(obj, name: str = "model") -> "TaskModel":
    """``obj`` if it is a :class:`TaskModel`, else the model an env holds (``env.model``); TypeError otherwise."""
    if isinstance(obj, TaskModel):
        return obj
    held = getattr(obj, "model", None)
    if isinstance(held, TaskModel):
        return held
    raise TypeError(
        f"{name} must be a torchrl_silp.models.TaskModel (or an env holding one as .model), got {type(obj).__name__}"
    )


class TaskModel(ABC):
    """A goal-conditioned reaching task among obstacles: f_s, f_r, collisions, goals.

    Subclasses set :attr:`config_dim`, :attr:`goal_dim`, :attr:`scene_shapes`,
    :attr:`config_low` / :attr:`config_high` and :attr:`action_scale`, and
    implement :meth:`achieved_goal`, :meth:`collision_flags`, :meth:`clearance`,
    :meth:`lipschitz` and :meth:`sample_tasks`.

    The reward of the paper (sec. 3.1): ``collision_reward`` when the motion
    collides, ``success_reward`` when the achieved goal is within
    ``success_distance`` of the desired goal, else minus that distance.

    A motion (a step, a roadmap edge) is judged along its whole joint-space
    segment, not only where it ends (:meth:`motion_collision_flags`): evenly
    spaced configurations no more than ``motion_resolution`` apart are
    checked, each with a margin of ``L * motion_resolution / 2`` (``L`` from
    :meth:`lipschitz`), so that every point between two samples is proven
    free. With ``conservative=False`` the samples are checked exactly (the
    paper's subdivision check, which can miss a graze between two samples).
    """

    config_key: str = CONFIG_KEY
    achieved_goal_key: str = ACHIEVED_GOAL_KEY
    desired_goal_key: str = DESIRED_GOAL_KEY
    goal_config_key: str = GOAL_CONFIG_KEY
    #: key -> trailing shape of the scene entries (constant during an episode)
    scene_shapes: dict[str, tuple[int, ...]] = {}
    config_dim: int
    goal_dim: int
    collision_reward: float = -10.0
    success_reward: float = 1.0
    #: names of the bits of :meth:`collision_flags`, lowest bit first
    collision_reasons: tuple[str, ...] = ()
    #: the planner's test of the configurations sampled along an edge, if not the model's collision test:
    #: ``edge_check(model, config, scene, margin)`` -> bool ``config.shape[:-1]`` (True: collides), e.g.
    #: :class:`~torchrl_silp.models.learned_collision.LearnedEdgeCheck`. Read by
    #: :meth:`segment_collision_free` only: the env's step and the rewards stay exact.
    edge_check = None

    def __init__(
        self,
        *,
        success_distance: float = 0.05,
        motion_resolution: float = 0.01,
        conservative: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        self.success_distance = check_positive_float(success_distance, name="success_distance", unit="metres")
        self.motion_resolution = check_positive_float(motion_resolution, name="motion_resolution", unit="radians")
        self.conservative = check_bool(conservative, name="conservative")
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.device = torch.device("cpu" if device is None else device)
        self.dtype = dtype

    # ------------------------------------------------------------ names
    @property
    def scene_keys(self) -> tuple[str, ...]:
        return tuple(self.scene_shapes)

    @property
    def action_dim(self) -> int:
        return self.config_dim

    @property
    def state_keys(self) -> tuple[str, ...]:
        """The named parts of a state, in the order of the flat observation."""
        return (self.config_key, self.achieved_goal_key, *self.scene_keys, self.desired_goal_key)

    @property
    def observation_keys(self) -> tuple[str, ...]:
        return self.state_keys

    def observation_transform(self, out_key: str = "observation") -> FlatCatTensors:
        """The transform that builds the flat observation from the named keys (:meth:`observation`):
        a :class:`~torchrl_silp.transforms.FlatCatTensors`, so that a scene entry of any trailing shape
        is flattened as :meth:`observation` flattens it.

        The named keys are kept (``del_keys=False``): components read them.
        """
        return FlatCatTensors({key: self._trailing_shape(key) for key in self.observation_keys}, out_key=out_key)

    def _trailing_shape(self, key: str) -> tuple[int, ...]:
        if key in (self.config_key,):
            return (self.config_dim,)
        if key in (self.achieved_goal_key, self.desired_goal_key):
            return (self.goal_dim,)
        if key in self.scene_shapes:
            return tuple(self.scene_shapes[key])
        raise KeyError(f"{type(self).__name__}.observation_keys: {key!r} is neither the configuration, a goal "
                       "nor a key of scene_shapes, so its trailing shape is unknown")

    def observation(self, state: TensorDictBase) -> torch.Tensor:
        """The flat observation of ``state`` (what :meth:`observation_transform` writes)."""
        return torch.cat([state.get(k).reshape(*state.batch_size, -1) for k in self.observation_keys], dim=-1)

    def state_spec(self, batch_size: torch.Size, device: torch.device) -> Composite:
        """Specs of the named state keys, the goal configuration and the flags an env writes."""
        b, f = tuple(batch_size), dict(dtype=self.dtype, device=device)
        entries = {
            self.config_key: Bounded(
                low=self.config_low.expand(*b, self.config_dim).to(device),
                high=self.config_high.expand(*b, self.config_dim).to(device),
                shape=(*b, self.config_dim), **f,
            ),
            self.achieved_goal_key: Unbounded(shape=(*b, self.goal_dim), **f),
            self.desired_goal_key: Unbounded(shape=(*b, self.goal_dim), **f),
            self.goal_config_key: Unbounded(shape=(*b, self.config_dim), **f),
        }
        for key, shape in self.scene_shapes.items():
            entries[key] = Unbounded(shape=(*b, *shape), **f)
        return Composite(entries, shape=b, device=device)

    def flag_spec(self, batch_size: torch.Size, device: torch.device) -> Composite:
        b = tuple(batch_size)
        return Composite(
            collision=Binary(n=1, shape=(*b, 1), dtype=torch.bool, device=device),
            swept_collision=Binary(n=1, shape=(*b, 1), dtype=torch.bool, device=device),
            success=Binary(n=1, shape=(*b, 1), dtype=torch.bool, device=device),
            collision_reason=Bounded(
                low=0, high=2 ** max(len(self.collision_reasons), 1) - 1, shape=(*b, 1), dtype=torch.uint8, device=device
            ),
            shape=b,
            device=device,
        )

    # --------------------------------------------------------- abstract
    config_low: torch.Tensor
    config_high: torch.Tensor
    action_scale: float

    @abstractmethod
    def achieved_goal(self, config: torch.Tensor) -> torch.Tensor:
        """The goal a configuration achieves (e.g. the TCP position): ``(..., config_dim) -> (..., goal_dim)``."""

    @abstractmethod
    def collision_flags(
        self, config: torch.Tensor, scene: TensorDictBase, margin: dict[str, float] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Collision bit flags ``(..., 1)`` (uint8, bits named by :attr:`collision_reasons`) and achieved goals.

        Args:
            config: ``(..., config_dim)`` configurations.
            scene: TensorDict with the scene keys, batch shape ``config.shape[:-1]``.
            margin: per-reason clearance (metres) a configuration must keep to count as free;
                ``None`` or 0: exact.
        """

    @abstractmethod
    def clearance(self, config: torch.Tensor, scene: TensorDictBase) -> torch.Tensor:
        """Per-reason clearance ``(..., R)`` in metres (negative: that reason collides).

        A critic may read it inside ``vmap`` and ``torch.compile``
        (:class:`~torchrl_silp.modules.NextGoalOffsetQ` with ``clearance=True``): check shapes, not values
        (no host sync), and keep the shapes independent of the values (``torch.where``, not a mask index).
        """

    @abstractmethod
    def lipschitz(self) -> dict[str, float]:
        """Per-reason bound on how far the checked geometry moves per radian (max-norm of the joint step)."""

    @abstractmethod
    def sample_tasks(self, n: int, generator: torch.Generator | None = None) -> TensorDict:
        """``n`` tasks: a TensorDict ``[n]`` with the state keys and the goal configuration.

        Start and goal configurations keep the motion check's margin (:meth:`motion_margin`),
        so every motion out of them can be judged.
        """

    # --------------------------------------------------------- provided
    def to(self, device: torch.device | str) -> "TaskModel":
        """Move the model's tensors to ``device`` (in place); returns the model.

        Every tensor attribute of the instance moves, also inside lists, tuples and dicts, and every
        attribute with a ``to(device)`` method of its own (an ``nn.Module``, a robot's kinematics, a
        learned edge check), so that a subclass's own tensors follow without a ``to`` of its own.
        """
        self.device = torch.device(device)
        for name, value in list(vars(self).items()):
            if not isinstance(value, (torch.Tensor, type)) and callable(getattr(value, "to", None)):
                moved = value.to(self.device)
                if moved is not None:
                    setattr(self, name, moved)
            else:
                setattr(self, name, _moved(value, self.device))
        return self

    def motion_margin(self, resolution: float | None = None) -> dict[str, float]:
        """The per-reason margins that make samples ``resolution`` apart cover a whole segment."""
        if not self.conservative:
            return {name: 0.0 for name in self.collision_reasons}
        h = self.motion_resolution if resolution is None else float(resolution)
        return {name: bound * h / 2 for name, bound in self.lipschitz().items()}

    def collides(self, config: torch.Tensor, scene: TensorDictBase) -> torch.Tensor:
        """Whether configurations collide (exactly, no margin): bool ``config.shape[:-1]``."""
        return self.collision_flags(config, scene)[0].squeeze(-1) != 0

    def next_config(self, config: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``config + action_scale * clip(action, -1, 1)``, clipped to the joint limits."""
        check_tensor(action, name="action", last_dim=self.action_dim)
        step = action.to(config.dtype).clamp(-1.0, 1.0) * self.action_scale
        return torch.minimum(torch.maximum(config + step, self.config_low), self.config_high)

    def motion_collision_flags(
        self, config_from: torch.Tensor, config_to: torch.Tensor, scene: TensorDictBase,
        resolution: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Collision flags of the straight joint-space motions ``config_from -> config_to``.

        Checks ``max(ceil(span / resolution), 1) + 1`` evenly spaced configurations per motion
        (``span`` the largest joint difference of the batch), both ends included, each with
        :meth:`motion_margin`; the flags are OR-ed over the samples. Inside ``torch.compile``
        ``span`` is the largest action step (``action_scale``), whatever the data: check longer
        motions eagerly there.

        Returns:
            flags ``(..., 1)`` (uint8) and the achieved goal at ``config_to`` ``(..., goal_dim)``.
        """
        h = self.motion_resolution if resolution is None else float(resolution)
        batch = config_from.shape[:-1]
        delta = config_to - config_from
        if torch.compiler.is_compiling():
            # the count may not depend on the data inside a compiled graph: that of a full action step
            scale = self.action_scale
            span = float(scale) if isinstance(scale, (int, float)) else float(torch.as_tensor(scale).max())
        else:
            span = float(delta.detach().abs().amax()) if delta.numel() else 0.0
        n = max(int(math.ceil(span / h - 1e-9)), 1) + 1
        if scene.batch_size != batch:
            scene = scene.expand(*batch)
        margin = self.motion_margin(h)
        t = torch.linspace(0, 1, n, dtype=config_from.dtype, device=config_from.device).view(n, 1, 1)
        flat_from, flat_delta = config_from.reshape(-1, self.config_dim), delta.reshape(-1, self.config_dim)
        flat_to = config_to.reshape(-1, self.config_dim)
        flat_scene = scene.reshape(flat_from.shape[0])
        rows = flat_from.shape[0]
        # chunks of rows bound the (samples x rows x spheres) temporaries however large the batch
        step = max(1, _CHUNK // n)
        flag_parts, goal_parts = [], []
        for lo in range(0, max(rows, 1), step):
            q = flat_from[lo : lo + step] + t * flat_delta[lo : lo + step]  # (n, r, D)
            # the last sample is the end itself (from + delta can differ from it in the last bits)
            q = torch.cat([q[:-1], flat_to[lo : lo + step].unsqueeze(0)])
            part = flat_scene[lo : lo + step]
            flags, goals = self.collision_flags(q, part.unsqueeze(0).expand(n, *part.batch_size), margin)
            combined = flags[0]
            for k in range(1, n):  # over the samples, not the batch
                combined = combined | flags[k]
            flag_parts.append(combined)
            goal_parts.append(goals[-1])
        flags = torch.cat(flag_parts) if len(flag_parts) > 1 else flag_parts[0]
        goals = torch.cat(goal_parts) if len(goal_parts) > 1 else goal_parts[0]
        return flags.reshape(*batch, 1), goals.reshape(*batch, self.goal_dim)

    def segment_collision_free(
        self, config_from: torch.Tensor, config_to: torch.Tensor, scene: TensorDictBase,
        resolution: float | None = None,
    ) -> torch.Tensor:
        """A flat batch of segments ``(P, D)``, each sampled at its own count (ragged): bool ``(P,)``.

        The predicate of :meth:`motion_collision_flags` on each segment alone (or of
        :attr:`edge_check`, where set); a batch costs the sum of its segments' counts, not the
        longest one's count times ``P``.

        Examples:
            >>> import torch
            >>> from torchrl_silp.models import UR5eReach
            >>> model = UR5eReach()
            >>> task = model.sample_tasks(2, torch.Generator().manual_seed(0))
            >>> q = task["joint_position"]
            >>> model.segment_collision_free(q, q + 0.05, task.select("obstacle")).shape
            torch.Size([2])
        """
        h = self.motion_resolution if resolution is None else check_positive_float(resolution, name="resolution", unit="radians")
        if config_from.shape != config_to.shape or config_from.dim() != 2 or config_from.shape[-1] != self.config_dim:
            raise ValueError(f"config_from and config_to must have one shape (P, {self.config_dim}), "
                             f"got {tuple(config_from.shape)} and {tuple(config_to.shape)}")
        P = config_from.shape[0]
        device = config_from.device
        if P == 0:
            return torch.ones(0, dtype=torch.bool, device=device)
        delta = config_to - config_from
        # float64 for the count, as motion_collision_flags computes it on the host
        span = delta.abs().amax(-1).double()
        n_seg = torch.ceil(span / h - 1e-9).clamp(min=1).long()
        count = n_seg + 1
        total = int(count.sum())
        edge = torch.repeat_interleave(torch.arange(P, device=device), count, output_size=total)
        first = torch.cumsum(count, 0) - count
        k = torch.arange(total, device=device) - first[edge]
        t = (k.to(config_from.dtype) / n_seg[edge].to(config_from.dtype)).unsqueeze(-1)
        margin = self.motion_margin(h)
        hit = torch.zeros(P, dtype=torch.bool, device=device)
        for lo in range(0, total, _CHUNK):
            e = edge[lo : lo + _CHUNK]
            q = config_from[e] + t[lo : lo + _CHUNK] * delta[e]
            hit.index_fill_(0, e[self.edge_samples_collide(q, scene[e], margin)], True)
        return ~hit

    def edge_samples_collide(self, config: torch.Tensor, scene: TensorDictBase, margin: dict[str, float]) -> torch.Tensor:
        """The test :meth:`segment_collision_free` applies to each configuration it samples along a segment:
        bool ``config.shape[:-1]``. :attr:`edge_check` if set (e.g. a learned collision model), else the
        collision test with the motion ``margin``."""
        if self.edge_check is not None:
            return self.edge_check(self, config, scene, margin)
        flags, _ = self.collision_flags(config, scene, margin)
        return flags.squeeze(-1) != 0

    def transition(self, state: TensorDictBase, action: torch.Tensor) -> TensorDict:
        """The kinematic transition f_s: the next state (configuration and achieved goal; scene and goal kept).

        NaN or infinite inputs raise ``ValueError`` (as the env's step does); a differentiable
        caller inside ``vmap`` (a critic) uses :meth:`next_config` and :meth:`achieved_goal`.
        """
        self._check_state(state, "state")
        check_tensor(action, name="action", last_dim=self.action_dim)
        check_finite(action, name="action")
        config = self.next_config(state.get(self.config_key), action)
        out = state.select(*self.state_keys).clone(False)
        out.set(self.config_key, config)
        out.set(self.achieved_goal_key, self.achieved_goal(config).to(config.dtype))
        return out

    def outcome(self, state: TensorDictBase, next_state: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """``(reward, collision, success, collision_reason)`` of moving from ``state`` to ``next_state``, each ``(..., 1)``.

        The motion collides when its segment does (:meth:`motion_collision_flags`); the distance
        to the goal is that of ``next_state``'s achieved goal.
        """
        self._check_state(state, "state")
        self._check_state(next_state, "next_state")
        scene = state.select(*self.scene_keys)
        flags, _ = self.motion_collision_flags(state.get(self.config_key), next_state.get(self.config_key), scene)
        return self.score(flags, next_state.get(self.achieved_goal_key), next_state.get(self.desired_goal_key))

    def reward(self, state: TensorDictBase, next_state: TensorDictBase) -> torch.Tensor:
        """The reward f_r ``(..., 1)`` of moving from ``state`` to ``next_state``."""
        return self.outcome(state, next_state)[0]

    def step(self, state: TensorDictBase, action: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`transition` and :meth:`outcome` in one pass: ``(next_state, reward, collision, success, flags)``.

        Equal to them bit for bit: the achieved goal is :meth:`achieved_goal` of the end
        configuration, not the one the motion check computes among its samples (a batched
        product of another shape can round differently in the last bit).
        """
        self._check_state(state, "state")
        check_tensor(action, name="action", last_dim=self.action_dim)
        check_finite(action, name="action")
        config = state.get(self.config_key)
        nxt = self.next_config(config, action)
        flags, _ = self.motion_collision_flags(config, nxt, state.select(*self.scene_keys))
        out = state.select(*self.state_keys).clone(False)
        out.set(self.config_key, nxt)
        out.set(self.achieved_goal_key, self.achieved_goal(nxt).to(nxt.dtype))
        reward, collision, success, flags = self.score(flags, out.get(self.achieved_goal_key), out.get(self.desired_goal_key))
        return out, reward, collision, success, flags

    def score(self, flags: torch.Tensor, achieved: torch.Tensor, desired: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(reward, collision, success, flags)`` from collision flags and goals."""
        collision = flags != 0
        dist = (achieved - desired).norm(dim=-1, keepdim=True)
        success = (dist < self.success_distance) & ~collision
        reward = torch.where(
            collision,
            torch.full_like(dist, self.collision_reward),
            torch.where(success, torch.full_like(dist, self.success_reward), -dist),
        )
        return reward, collision, success, flags

    def goal_reward(self, achieved: torch.Tensor, desired: torch.Tensor) -> torch.Tensor:
        """The reward of a collision-free step that achieves ``achieved`` while ``desired`` is the goal."""
        dist = (achieved - desired).norm(dim=-1, keepdim=True)
        return torch.where(dist < self.success_distance, torch.full_like(dist, self.success_reward), -dist)

    def scene_boxes(self, scene: TensorDictBase) -> torch.Tensor | None:
        """The scene's obstacles as boxes in the goal space, for pictures: ``(..., K, 2 * goal_dim)``, each row
        ``(min_0, max_0, min_1, max_1, ...)``; None (the default) where the scene is not boxes in that space.

        :func:`~torchrl_silp.viz.save_rollout_png` draws them beside the achieved-goal paths.
        """
        return None

    def relabel(self, state: TensorDictBase, goal: torch.Tensor) -> TensorDictBase:
        """``state`` with ``goal`` as its desired goal (a shallow copy)."""
        check_tensor(goal, name="goal", last_dim=self.goal_dim)
        out = state.clone(False)
        out.set(self.desired_goal_key, goal.to(state.get(self.desired_goal_key).dtype).expand_as(state.get(self.desired_goal_key)))
        return out

    def state_at(self, config: torch.Tensor, scene: TensorDictBase, desired_goal: torch.Tensor) -> TensorDict:
        """A state TensorDict from a configuration, its scene and a goal (the achieved goal computed)."""
        out = scene.select(*self.scene_keys).clone(False)
        out.set(self.config_key, config)
        out.set(self.achieved_goal_key, self.achieved_goal(config).to(config.dtype))
        out.set(self.desired_goal_key, desired_goal)
        return out

    def _check_state(self, state, name: str) -> None:
        if not isinstance(state, TensorDictBase):
            raise TypeError(f"{name} must be a TensorDict with the keys {self.state_keys}, got {type(state).__name__}")
        missing = [k for k in self.state_keys if k not in state.keys()]
        if missing:
            raise KeyError(f"{name} lacks the keys {missing} (a state holds {self.state_keys})")
        for key in self.state_keys:
            check_finite(state.get(key), name=f"{name}[{key!r}]")


def _moved(value, device: torch.device):
    """``value`` with its tensors on ``device``: a tensor, or a list, tuple or dict holding tensors."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if type(value) is dict:
        return {k: _moved(v, device) for k, v in value.items()}
    if type(value) in (list, tuple):
        return type(value)(_moved(v, device) for v in value)
    return value
