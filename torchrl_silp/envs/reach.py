"""Batched reach envs over a task model: the generic :class:`ReachEnv` and the paper's :class:`UR5eReachEnv`."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, TransformedEnv

from torchrl_silp.models.base import TaskModel
from torchrl_silp.models.check import ensure_checked
from torchrl_silp.models.ur5e import TASK_BRANCHES, WORKSPACE_EXIT_MODES, UR5eReach
from torchrl_silp.robots import UR5e
from torchrl_silp.transforms import COLLISION_TYPES, CollisionHandling
from torchrl_silp.validation import check_positive_int

__all__ = ["ReachEnv", "UR5eReachEnv", "COLLISION_TYPES", "TASK_BRANCHES", "WORKSPACE_EXIT_MODES"]


def _as_batch_size(num_envs, batch_size) -> torch.Size:
    if num_envs is not None and batch_size is not None:
        raise ValueError("pass either num_envs or batch_size, not both")
    if num_envs is not None:
        return torch.Size([check_positive_int(num_envs, name="num_envs")])
    if batch_size is None:
        return torch.Size([])
    if isinstance(batch_size, int):
        batch_size = (batch_size,)
    if not isinstance(batch_size, Sequence):
        raise TypeError(f"batch_size must be a tuple of positive ints, got {batch_size!r}")
    return torch.Size([check_positive_int(b, name=f"batch_size[{i}]") for i, b in enumerate(batch_size)])


class ReachEnv(EnvBase):
    """A batched goal-reaching env over any :class:`~torchrl_silp.models.TaskModel`; state in the TensorDict.

    Each episode draws a task from the model (start state, scene, goal). A step
    moves the configuration by the action through the model (f_s), scores the
    motion (f_r: the collision test covers the segment moved along) and reports
    ``("next", "collision")``, ``"success"`` and ``"collision_reason"``. The env
    itself only *reports* collisions (``("next", "swept_collision")`` marks the
    collisions of a motion whose end configuration is free: the motion passes
    through something, or within the motion check's margin of it, and a check of
    the reached state alone would have let it pass): the arm moves into the colliding state and
    the episode goes on; :class:`~torchrl_silp.transforms.CollisionHandling`
    applies the paper's type 0/1/2 handling. Success terminates, ``max_steps``
    truncates.

    The state lives in the TensorDict under the model's names (``"joint_position"``,
    ``"achieved_goal"``, the scene keys such as ``"obstacle"``, ``"desired_goal"``),
    with ``"goal_joint_position"`` and ``"step_count"``, as in TorchRL's stateless
    pendulum; ``_step`` reads it from its input, so transforms may change it. The
    flat ``"observation"`` is built by :meth:`TaskModel.observation_transform`
    (a :class:`~torchrl_silp.transforms.FlatCatTensors`), as :class:`UR5eReachEnv` does.

    Args:
        model: the task model.
        num_envs: number of parallel envs (batch size ``(num_envs,)``).
        batch_size: alternatively any batch shape; ``()`` if neither is given.
        device: device of the env (the model is moved there).
        seed: seed of the env's task generator; ``None`` leaves it unseeded.
        max_steps: episode length before truncation (50 in our tables; the paper does not state it).

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_silp.envs import ReachEnv
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> env = TransformedEnv(ReachEnv(model, num_envs=4, seed=0), model.observation_transform())
        >>> td = env.rollout(10)
        >>> td["observation"].shape, td["next", "achieved_goal"].shape
        (torch.Size([4, 10, 15]), torch.Size([4, 10, 3]))
    """

    batch_locked = True

    def __init__(
        self,
        model: TaskModel,
        num_envs: int | None = None,
        *,
        batch_size: Sequence[int] | None = None,
        device: torch.device | str | None = None,
        seed: int | None = None,
        max_steps: int = 50,
    ):
        if not isinstance(model, TaskModel):
            raise TypeError(f"model must be a torchrl_silp.models.TaskModel, got {type(model).__name__}")
        batch = _as_batch_size(num_envs, batch_size)
        check_positive_int(max_steps, name="max_steps")
        device = torch.device(model.device if device is None else device)
        super().__init__(device=device, batch_size=batch)
        if model.device != device:
            model.to(device)
        ensure_checked(model)  # a broken model fails here, naming the member and the rule, not deep in a step
        self.model = model
        self.max_steps = max_steps
        self.dtype = model.dtype
        self.rng = torch.Generator(device=device)
        if seed is not None:
            self.set_seed(seed)
        else:
            self.rng.seed()
        self._make_specs()

    def _make_specs(self) -> None:
        b, d, model = self.batch_size, self.device, self.model
        spec = model.state_spec(b, d)
        spec.update(model.flag_spec(b, d))
        spec["step_count"] = Bounded(low=0, high=self.max_steps, shape=(*b, 1), dtype=torch.long, device=d)
        self.observation_spec = spec
        self.action_spec = Bounded(low=-1.0, high=1.0, shape=(*b, model.action_dim), dtype=model.dtype, device=d)
        self.reward_spec = Unbounded(shape=(*b, 1), dtype=model.dtype, device=d)
        self.full_done_spec = Composite(
            done=Binary(n=1, shape=(*b, 1), dtype=torch.bool, device=d),
            terminated=Binary(n=1, shape=(*b, 1), dtype=torch.bool, device=d),
            truncated=Binary(n=1, shape=(*b, 1), dtype=torch.bool, device=d),
            shape=b,
            device=d,
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            self.rng.seed()
        else:
            self.rng.manual_seed(int(seed))

    def sample_tasks(self, n: int) -> TensorDict:
        """``n`` tasks from the model, drawn with the env's generator."""
        return self.model.sample_tasks(n, self.rng)

    def _state_keys(self) -> tuple[str, ...]:
        return (*self.model.state_keys, self.model.goal_config_key)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        batch, device = self.batch_size, self.device
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if mask is None:
            mask = torch.ones(*batch, 1, dtype=torch.bool, device=device)
        flat = mask.reshape(-1)
        n = int(flat.sum())
        state = self.observation_spec.zero().select(*self._state_keys())
        if n:
            tasks = self.sample_tasks(n)
            flat_state = state.reshape(-1)
            flat_state[flat] = tasks.select(*self._state_keys()).to(device)
            state = flat_state.reshape(batch)
        if n < flat.numel() and tensordict is not None:
            # rows not reset keep the state they hold (when the caller passed it)
            keep = ~mask.reshape(*batch)
            for key in self._state_keys():
                old = tensordict.get(key, None)
                if old is not None:
                    value = state.get(key)
                    state.set(key, torch.where(keep.view(*batch, *([1] * (value.dim() - len(batch)))), old, value))
        false = torch.zeros(*batch, 1, dtype=torch.bool, device=device)
        state.update(
            {
                "step_count": torch.zeros(*batch, 1, dtype=torch.long, device=device),
                "collision": false,
                "swept_collision": false.clone(),
                "success": false.clone(),
                "collision_reason": torch.zeros(*batch, 1, dtype=torch.uint8, device=device),
                "done": false.clone(),
                "terminated": false.clone(),
                "truncated": false.clone(),
            }
        )
        return state

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action", None)
        if action is None:
            raise KeyError('action: the step\'s TensorDict holds no "action" (did the policy write one?)')
        if action.shape != (*self.batch_size, self.model.action_dim):
            raise ValueError(f"action must have shape {(*self.batch_size, self.model.action_dim)}, got {tuple(action.shape)}")
        if torch.isnan(action).any():
            raise ValueError("action contains NaN")
        model = self.model
        state = tensordict.select(*model.state_keys)
        nxt, reward, collision, success, flags = model.step(state, action.to(self.dtype))
        # collisions of the motion only: the reached configuration itself is free
        end_free = model.collision_flags(nxt.get(model.config_key), nxt.select(*model.scene_keys))[0] == 0
        steps = tensordict.get("step_count") + 1
        terminated = success
        truncated = (steps >= self.max_steps) & ~terminated
        nxt.update(
            {
                model.goal_config_key: tensordict.get(model.goal_config_key).clone(),
                "step_count": steps,
                "reward": reward,
                "collision": collision,
                "swept_collision": collision & end_free,
                "success": success,
                "collision_reason": flags,
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            }
        )
        return nxt


class UR5eReachEnv(TransformedEnv):
    """Reach a goal with a UR5e around a box obstacle: the SILP+ paper's task, batched, on any device.

    A :class:`ReachEnv` over the :class:`~torchrl_silp.models.UR5eReach` model with
    the paper's collision handling (:class:`~torchrl_silp.transforms.CollisionHandling`)
    and the flat observation (:meth:`TaskModel.observation_transform`). The env holds
    the model (:attr:`model`); it is not the model.

    Observation ``(15,)``: joint angles (3), TCP xyz (3), obstacle AABB
    ``(xmin, xmax, ymin, ymax, zmin, zmax)`` (6), goal xyz (3), each also under
    its own key (``"joint_position"``, ``"achieved_goal"``, ``"obstacle"``,
    ``"desired_goal"``). Reward: -10 if the step's motion collides, +1 if the TCP
    ends within ``success_distance`` of the goal, else minus the distance.

    Collision handling (paper sec. 4.3), ``collision_type``: ``0`` ends the
    episode; ``1`` puts the arm back and flags ``("next", "discard")``; ``2`` puts
    it back and keeps the transition; ``None``: no handling (the arm moves into
    the colliding state).

    Args:
        num_envs, batch_size, device, seed, max_steps: see :class:`ReachEnv`.
        collision_type: 0, 1, 2 or None.
        success_distance, workspace_exit, table_contact, task_branch, motion_resolution, compile_collision:
            see :class:`~torchrl_silp.models.UR5eReach`.
        robot: a :class:`~torchrl_silp.robots.UR5e` to share.
        dtype: floating dtype of the model, observations and actions.

    Examples:
        >>> from torchrl_silp import UR5eReachEnv
        >>> env = UR5eReachEnv(num_envs=4, seed=0)
        >>> td = env.rollout(10)
        >>> td["next", "reward"].shape, td["observation"].shape
        (torch.Size([4, 10, 1]), torch.Size([4, 10, 15]))
    """

    def __init__(
        self,
        num_envs: int | None = None,
        *,
        batch_size: Sequence[int] | None = None,
        device: torch.device | str | None = None,
        seed: int | None = None,
        max_steps: int = 50,
        collision_type: int | None = 2,
        success_distance: float = 0.05,
        robot: UR5e | None = None,
        dtype: torch.dtype = torch.float32,
        compile_collision: bool = False,
        workspace_exit: str = "collision",
        task_branch: str = "front",
        motion_resolution: float = 0.01,
        table_contact: str = "collision",
    ):
        model = UR5eReach(
            robot, success_distance=success_distance, motion_resolution=motion_resolution,
            workspace_exit=workspace_exit, table_contact=table_contact, task_branch=task_branch, compile_collision=compile_collision,
            device=device, dtype=dtype,
        )
        base = ReachEnv(model, num_envs, batch_size=batch_size, device=device, seed=seed, max_steps=max_steps)
        transforms = [] if collision_type is None else [CollisionHandling(collision_type, model=model)]
        super().__init__(base, Compose(*transforms, model.observation_transform()))

    @property
    def model(self) -> UR5eReach:
        return self.base_env.model

    @property
    def robot(self) -> UR5e:
        """The model's :class:`~torchrl_silp.robots.UR5e`."""
        return self.base_env.model.robot

    @property
    def collision_type(self) -> int | None:
        for t in self.transform:
            if isinstance(t, CollisionHandling):
                return t.collision_type
        return None
