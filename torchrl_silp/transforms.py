"""SILP+ as TorchRL transforms: collision handling, the goal-relative input, perception noise, the
flat observation of named entries of any trailing shape, and a running, clipped observation normaliser.

Each works on any env whose base env holds a :class:`~torchrl_silp.models.TaskModel`
(``env.base_env.model``) and keeps its state under the model's names, such as
:class:`~torchrl_silp.envs.ReachEnv`; the model may also be passed explicitly.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs import CatTensors, Transform

from torchrl_silp.choices import COLLISION_TYPES
from torchrl_silp.validation import check_choice, check_nonnegative_float, check_positive_float

__all__ = ["CollisionHandling", "GoalRelative", "PerceptionNoise", "FlatCatTensors", "RunningObservationNorm",
           "COLLISION_TYPES"]


class _ModelTransform(Transform):
    def __init__(self, model=None, **kwargs):
        super().__init__(**kwargs)
        self._model = model

    @property
    def model(self):
        if self._model is not None:
            return self._model
        parent = self.parent
        base = getattr(parent, "base_env", parent)
        model = getattr(base, "model", None)
        if model is None:
            raise RuntimeError(
                f"{type(self).__name__} needs a task model: pass model=... or use it on an env whose base env has .model"
            )
        self._model = model  # resolving the parent builds a container each time: once is enough
        return model


class CollisionHandling(_ModelTransform):
    """The paper's collision handling (sec. 4.3) on an env that only reports collisions.

    * ``0``: a collision terminates the episode (the next state is the colliding one).
    * ``1``: the arm is put back to the state before the collision (configuration and
      achieved goal) and the episode goes on; ``("next", "discard")`` flags the
      transition so the replay buffer drops it.
    * ``2``: as 1, but the transition is kept for learning (the paper's choice).

    Writes ``"discard"`` (bool ``(..., 1)``) for every type. Reads ``("next", "collision")``.

    Args:
        collision_type: 0, 1 or 2.
        model: the task model (whose configuration and achieved-goal keys are put back);
            read from the parent env's base env when not given.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_silp import CollisionHandling
        >>> from torchrl_silp.envs import ReachEnv
        >>> from torchrl_silp.models import UR5eReach
        >>> env = TransformedEnv(ReachEnv(UR5eReach(), num_envs=8, seed=0), CollisionHandling(2))
        >>> check_env_specs(env, seed=0)
        >>> td = env.rollout(20)
        >>> moved_back = td["next", "collision"].squeeze(-1)
        >>> bool((td["next", "joint_position"][moved_back] == td["joint_position"][moved_back]).all())
        True
    """

    def __init__(self, collision_type: int = 2, model=None):
        check_choice(collision_type, COLLISION_TYPES, name="collision_type")
        super().__init__(model, in_keys=[], out_keys=["discard"])
        self.collision_type = collision_type

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        collision = next_tensordict.get("collision")
        if self.collision_type == 0:
            terminated = next_tensordict.get("terminated") | collision
            truncated = next_tensordict.get("truncated") & ~terminated
            next_tensordict.set("terminated", terminated)
            next_tensordict.set("truncated", truncated)
            next_tensordict.set("done", terminated | truncated)
            next_tensordict.set("discard", torch.zeros_like(collision))
            return next_tensordict
        model = self.model
        for key in (model.config_key, model.achieved_goal_key):
            new = next_tensordict.get(key)
            shape = (*collision.shape[:-1], *([1] * (new.dim() - collision.dim() + 1)))
            next_tensordict.set(key, torch.where(collision.reshape(shape), tensordict.get(key).to(new.dtype), new))
        discard = collision.clone() if self.collision_type == 1 else torch.zeros_like(collision)
        next_tensordict.set("discard", discard)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        done = tensordict_reset.get("done")
        tensordict_reset.set("discard", torch.zeros_like(done))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = (*observation_spec.shape, 1)
        observation_spec["discard"] = Binary(n=1, shape=shape, dtype=torch.bool, device=observation_spec.device)
        return observation_spec


class GoalRelative(_ModelTransform):
    """Adds the vector from the achieved goal to the desired goal, ``"goal_offset"``.

    Success is decided at the scale of this difference (5 cm for the reach tasks),
    which an MLP reading the two positions separately must learn to subtract. Put it
    before the observation's :class:`~torchrl.envs.CatTensors` and list
    ``"goal_offset"`` there, or give the networks ``"goal_offset"`` as a second input.

    Args:
        model: the task model (for the key names and the goal size); read from the parent
            env's base env when not given.
        out_key: where to write the offset.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_silp import GoalRelative, UR5eReachEnv
        >>> env = TransformedEnv(UR5eReachEnv(num_envs=4, seed=0), GoalRelative())
        >>> check_env_specs(env, seed=0)
        >>> td = env.reset()
        >>> bool((td["goal_offset"] == td["desired_goal"] - td["achieved_goal"]).all())
        True
    """

    def __init__(self, model=None, out_key: str = "goal_offset"):
        super().__init__(model, in_keys=[], out_keys=[out_key])
        self.out_key = out_key

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        model = self.model
        offset = next_tensordict.get(model.desired_goal_key) - next_tensordict.get(model.achieved_goal_key)
        next_tensordict.set(self.out_key, offset)
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        goal = observation_spec[self.model.desired_goal_key]
        observation_spec[self.out_key] = Unbounded(shape=goal.shape, dtype=goal.dtype, device=goal.device)
        return observation_spec


class PerceptionNoise(_ModelTransform):
    """Gaussian noise on what the policy perceives of the joints and the scene (the Sim2Real proxy).

    Rebuilds the flat ``out_key`` observation from the named state with noise added to
    the keys of ``std`` (by default the configuration and the obstacle), freshly drawn
    at every step. The named keys keep the true state, which the env steps from and the
    planner reads. Place it where the model's observation :class:`~torchrl.envs.CatTensors`
    is (it replaces that observation).

    Args:
        std: key -> standard deviation of its noise (radians for joints, metres for positions);
            default ``{"joint_position": 0.01, "obstacle": 0.01}``.
        model: the task model; read from the parent env's base env when not given.
        out_key: the flat observation to rebuild.
        generator: a ``torch.Generator`` for the noise; the global one by default.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_silp import PerceptionNoise, UR5eReachEnv
        >>> env = TransformedEnv(UR5eReachEnv(num_envs=4, seed=0), PerceptionNoise({"obstacle": 0.02}))
        >>> check_env_specs(env, seed=0)
        >>> td = env.reset()
        >>> clean = env.model.observation(td)  # what the policy would see without noise
        >>> bool((td["observation"] != clean).any()), bool((td["observation"] == clean).any())
        (True, True)
    """

    def __init__(self, std: dict | None = None, model=None, out_key: str = "observation", generator=None):
        std = {"joint_position": 0.01, "obstacle": 0.01} if std is None else dict(std)
        for key, value in std.items():
            check_nonnegative_float(value, name=f"std[{key!r}]")
        super().__init__(model, in_keys=[], out_keys=[out_key])
        self.std = std
        self.out_key = out_key
        self.generator = generator

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        model = self.model
        unknown = set(self.std) - set(model.observation_keys)
        if unknown:
            raise ValueError(f"std: keys {sorted(unknown)} are not in the observation {model.observation_keys}")
        parts = []
        for key in model.observation_keys:
            value = next_tensordict.get(key)
            value = value.reshape(*next_tensordict.batch_size, -1)
            if self.std.get(key, 0.0) > 0:
                noise = torch.randn(value.shape, generator=self.generator, dtype=value.dtype, device=value.device)
                value = value + self.std[key] * noise
            parts.append(value)
        next_tensordict.set(self.out_key, torch.cat(parts, dim=-1))
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        # the noisy observation is unbounded; declared here so that the transform also
        # works without the model's CatTensors before it (it then builds the observation)
        batch = observation_spec.shape
        parts = [observation_spec[key] for key in self.model.observation_keys]
        size = sum(math.prod(p.shape[len(batch):]) for p in parts)
        observation_spec[self.out_key] = Unbounded(
            shape=(*batch, size), dtype=parts[0].dtype, device=observation_spec.device
        )
        return observation_spec


class FlatCatTensors(CatTensors):
    """:class:`~torchrl.envs.CatTensors` over entries of any trailing shape: each is flattened after its
    batch dims, in the order given, then concatenated along the last dim (what ``reshape(*batch, -1)``
    and ``torch.cat(..., -1)`` give).

    Args:
        shapes: each input key's trailing shape, e.g. ``{"joint_position": (3,), "discs": (2, 3)}``.
        out_key: where the flat tensor goes.
        del_keys: drop the inputs (False: keep them, as the task-model components read them).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> cat = FlatCatTensors({"q": (3,), "discs": (2, 3)}, out_key="observation")
        >>> td = cat(TensorDict({"q": torch.zeros(4, 3), "discs": torch.ones(4, 2, 3)}, batch_size=[4]))
        >>> td["observation"].shape, td["observation"][0, 3:].tolist()
        (torch.Size([4, 9]), [1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    """

    def __init__(self, shapes: dict, out_key: str = "observation", del_keys: bool = False):
        self.shapes = {key: tuple(int(d) for d in shape) for key, shape in shapes.items()}
        super().__init__(in_keys=list(self.shapes), out_key=out_key, del_keys=del_keys, sort=False)

    def _flat(self, key, value: torch.Tensor) -> torch.Tensor:
        shape = self.shapes[key]
        return value.reshape(*value.shape[: value.ndim - len(shape)], math.prod(shape))  # (an empty batch too)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        missing = [key for key in self.in_keys if next_tensordict.get(key, None) is None]
        if missing:
            raise KeyError(f"{type(self).__name__}: the tensordict has no {missing}")
        flat = [self._flat(key, next_tensordict.get(key)) for key in self.in_keys]
        next_tensordict.set(self.out_keys[0], torch.cat(flat, dim=-1))
        if self._del_keys:
            next_tensordict.exclude(*self.keys_to_exclude, inplace=True)
        return next_tensordict

    forward = _call

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec0 = observation_spec[self.in_keys[0]]
        batch = spec0.shape[: len(spec0.shape) - len(self.shapes[self.in_keys[0]])]
        size = sum(math.prod(shape) for shape in self.shapes.values())
        observation_spec[self.out_keys[0]] = Unbounded(shape=(*batch, size), dtype=spec0.dtype, device=spec0.device)
        if self._del_keys:
            for key in self.keys_to_exclude:
                if key in observation_spec.keys(True):
                    del observation_spec[key]
        return observation_spec


class RunningObservationNorm(Transform):
    """Observations standardised by running statistics of the data seen so far, then clipped.

    Writes ``((x - mean) / max(std, eps)).clamp(-clip, clip)`` of each ``in_keys`` entry to the
    matching ``out_keys`` entry. The statistics change only through :meth:`update`, which merges a
    batch of raw observations into the running count, mean and sum of squared deviations (``m2``);
    applying the transform reads them and changes nothing. So a replay buffer can store the raw
    observations and a sampled batch be normalised with the statistics current at sample time
    (apply the transform to the batch and to its ``"next"``), while in an env the transform
    normalises every reset and step with the statistics of the moment. Before the first update the
    mean is 0 and the standard deviation 1 (the output is the clipped input).

    ``count``, ``mean`` and ``m2`` are buffers (in a ``state_dict``, moved by ``.to()``); ``mean`` and
    ``m2`` take the feature size of the first update (a ``state_dict`` of any size loads). The variance
    is the population one, ``m2 / count``. One instance may sit in several transform chains (an
    env's and a planner's :class:`~torchrl.envs.Compose`), which then share its statistics: it reads
    nothing from its parent, so adding it to another chain only moves its ``parent``.

    Args:
        in_keys: the raw entries (last dim: the features; the statistics are shared by all in_keys).
        out_keys: where the normalised entries go.
        clip: the bound of the normalised values.
        eps: the floor of the standard deviation.
        dtype: the buffers' dtype.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> norm = RunningObservationNorm(clip=5.0)
        >>> x = torch.tensor([[0.0, 10.0], [2.0, 10.0], [4.0, 10.0]])
        >>> norm.update(x)  # mean (2, 10); std (1.633, 0), the second floored at eps = 0.01
        >>> norm.mean.tolist(), int(norm.count)
        ([2.0, 10.0], 3)
        >>> td = norm(TensorDict({"observation": torch.tensor([[4.0, 10.5]])}, batch_size=[1]))
        >>> td["observation_normalized"]  # (4 - 2) / 1.633, and (10.5 - 10) / 0.01 clipped at 5
        tensor([[1.2247, 5.0000]])
        >>> norm.update(torch.tensor([[6.0, 10.0]]))  # one more row: the statistics of all four
        >>> norm.mean.tolist(), round(float(norm.var[0]), 4)
        ([3.0, 10.0], 5.0)
    """

    def __init__(self, in_keys=("observation",), out_keys=("observation_normalized",), clip: float = 5.0,
                 eps: float = 1e-2, dtype: torch.dtype = torch.float32):
        in_keys, out_keys = list(in_keys), list(out_keys)
        if len(in_keys) != len(out_keys):
            raise ValueError(f"in_keys and out_keys must have the same length, got {in_keys} and {out_keys}")
        clip, eps = check_positive_float(clip, name="clip"), check_positive_float(eps, name="eps")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.clip, self.eps = clip, eps
        self.register_buffer("count", torch.zeros((), dtype=dtype))
        self.register_buffer("mean", torch.zeros(0, dtype=dtype))  # sized by the first update
        self.register_buffer("m2", torch.zeros(0, dtype=dtype))

    @property
    def var(self) -> torch.Tensor:
        """The population variance of the data seen so far (``m2 / count``; ones before any update)."""
        if not self.mean.numel():
            return torch.ones_like(self.mean)
        return self.m2 / self.count.clamp_min(1)

    @property
    def std(self) -> torch.Tensor:
        """The standard deviation the transform divides by: ``sqrt(var)``, at least ``eps``."""
        return self.var.sqrt().clamp_min(self.eps)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge the rows of ``x`` (any leading dims, the features last) into the statistics (Chan et
        al.'s parallel formula: the batch's own mean and ``m2``, then one weighted merge)."""
        x = x.detach().reshape(-1, x.shape[-1]).to(self.mean.dtype)
        n_b = x.shape[0]
        if n_b == 0:
            return
        if not self.mean.numel():
            self.mean = torch.zeros(x.shape[-1], dtype=x.dtype, device=self.count.device)
            self.m2 = torch.zeros_like(self.mean)
        elif self.mean.shape[-1] != x.shape[-1]:
            raise ValueError(f"{type(self).__name__}.update: {x.shape[-1]} features, the statistics have "
                             f"{self.mean.shape[-1]}")
        x = x.to(self.mean.device)
        mean_b = x.mean(0)
        m2_b = (x - mean_b).square().sum(0)
        n_a = self.count.clone()
        n = n_a + n_b
        delta = mean_b - self.mean
        # in place: whatever holds these tensors (a compiled graph, a shared chain) sees the new values
        self.mean.add_(delta * (n_b / n))
        self.m2.add_(m2_b + delta.square() * (n_a * n_b / n))
        self.count.copy_(n)

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        if not self.mean.numel():  # no data yet: mean 0, std 1
            return obs.clamp(-self.clip, self.clip)
        mean, std = self.mean.to(obs.dtype), self.std.to(obs.dtype)
        return ((obs - mean) / std).clamp(-self.clip, self.clip)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        for in_key, out_key in zip(self.in_keys, self.out_keys):
            spec = observation_spec[in_key]
            observation_spec[out_key] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        return observation_spec

    def set_container(self, container) -> None:
        # in several chains at once (see the class docstring): the latest container is kept, without
        # Transform's refusal of a second parent
        self.reset_parent()
        super().set_container(container)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the statistics' size is that of the data they saw: take the saved one before loading
        for name in ("mean", "m2"):
            saved = state_dict.get(prefix + name)
            if saved is not None and saved.shape != getattr(self, name).shape:
                setattr(self, name, torch.zeros(saved.shape, dtype=self.count.dtype, device=self.count.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(in_keys={self.in_keys}, out_keys={self.out_keys}, clip={self.clip}, "
                f"eps={self.eps}, count={int(self.count)})")
