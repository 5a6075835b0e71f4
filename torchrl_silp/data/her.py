"""Hindsight goal relabelling on the task model's named keys (the *-HER baselines)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import HERReplayBuffer, LazyTensorStorage

from torchrl_silp.choices import HER_STRATEGIES
from torchrl_silp.data.demo_buffer import own_signature
from torchrl_silp.data.storage import FilledStorageCheckpointer
from torchrl_silp.models.base import as_model
from torchrl_silp.validation import check_bool, check_choice, check_positive_int, check_probability

__all__ = ["GoalRelabelingReplayBuffer", "HER_STRATEGIES"]



@own_signature
class GoalRelabelingReplayBuffer(HERReplayBuffer):
    """TorchRL's :class:`~torchrl.data.HERReplayBuffer` over a task model's named keys, kept consistent.

    The relabelled goal is the model's ``"desired_goal"`` (root and ``"next"``); the
    achieved goal of a transition is the one it reached, ``("next", "achieved_goal")``.
    Every sampled batch is then made consistent again: the networks' inputs are
    rebuilt from the named keys by ``observation_transform`` (the model's
    :class:`~torchrl.envs.CatTensors` by default), the reward is the model's own
    (a stored collision keeps ``collision_reward``; else ``success_reward`` within
    ``success_distance`` of the new goal, minus the distance otherwise), and
    ``terminated`` / ``done`` follow the new success (``HERReplayBuffer`` itself
    only recomputes the reward).

    ``extend`` must receive whole episodes, each contiguous and in time order
    (e.g. what :class:`~torchrl_silp.data.EpisodeAssembler` returns), because
    episode boundaries are read from ``("next", "done")`` in storage order.

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` (or an env holding one).
        her_ratio: fraction of each batch relabelled (0.8: 4 imagined goals per real one).
        strategy: ``"future"`` (default), ``"final"``, ``"episode"`` or ``"random"``.
        capacity: transitions kept when no ``storage`` is given.
        storage: a 1-D TorchRL storage (default ``LazyTensorStorage(capacity)``).
        device: device of the default storage.
        observation_transform: rebuilds the networks' inputs from a named state.
        collision_ends_episode: a collision terminates (collision type 0).
        **kwargs: forwarded to :class:`~torchrl.data.HERReplayBuffer`.

    Examples:
        >>> from torchrl_silp import ReachEnv, UR5eReach
        >>> from torchrl_silp.data import GoalRelabelingReplayBuffer
        >>> env = ReachEnv(UR5eReach(), num_envs=4, seed=0, max_steps=10)
        >>> episodes = env.rollout(10).reshape(-1)  # env-major: each env's episode is contiguous
        >>> rb = GoalRelabelingReplayBuffer(env.model, capacity=100, her_ratio=1.0)
        >>> _ = rb.extend(episodes)
        >>> batch = rb.sample(8)
        >>> bool((batch["observation"] == env.model.observation(batch)).all())  # rebuilt with the new goals
        True
    """

    def __init__(
        self,
        model,
        *,
        her_ratio: float = 0.8,
        strategy: str = "future",
        capacity: int = 1_000_000,
        storage=None,
        device: torch.device | str | None = None,
        observation_transform=None,
        collision_ends_episode: bool = False,
        **kwargs,
    ):
        model = as_model(model)
        check_choice(strategy, HER_STRATEGIES, name="strategy")
        check_probability(her_ratio, name="her_ratio", closed=True)
        check_bool(collision_ends_episode, name="collision_ends_episode")
        if storage is None:
            check_positive_int(capacity, name="capacity")
            storage = LazyTensorStorage(capacity, device="auto" if device is None else torch.device(device))
            kwargs.setdefault("checkpointer", FilledStorageCheckpointer())
        super().__init__(
            reward_fn=self._relabelled_reward,
            her_ratio=float(her_ratio),
            strategy=strategy,
            goal_key=model.desired_goal_key,
            achieved_goal_key=("next", model.achieved_goal_key),
            storage=storage,
            **kwargs,
        )
        self.model = model
        self.observation_transform = model.observation_transform() if observation_transform is None else observation_transform
        self.collision_ends_episode = collision_ends_episode

    def extend(self, data: TensorDictBase, *args, **kwargs):
        data = data.reshape(-1) if data.batch_dims != 1 else data
        return super().extend(data, *args, **kwargs)

    def _collided(self, td: TensorDictBase) -> torch.Tensor:
        # a collision step keeps its reward whatever the goal (type 1/2 put the arm back, so the
        # stored next state alone no longer shows the collision)
        return td["next", "reward"] <= self.model.collision_reward

    def _relabelled_reward(self, td: TensorDictBase) -> torch.Tensor:
        model = self.model
        reward = model.goal_reward(td["next", model.achieved_goal_key], td[model.desired_goal_key])
        return torch.where(self._collided(td), torch.full_like(reward, model.collision_reward), reward)

    def _sample(self, batch_size: int):
        data, info = super()._sample(batch_size)
        reward = data["next", "reward"]
        terminated = reward >= self.model.success_reward
        if self.collision_ends_episode:
            terminated = terminated | self._collided(data)
        truncated = data.get(("next", "truncated"), torch.zeros_like(terminated)) & ~terminated
        with data.unlock_():
            # rows that kept their goal are rebuilt unchanged
            data.update(self.observation_transform(data.exclude("next")))
            data.set("next", self.observation_transform(data.get("next")))
            data.set(("next", "terminated"), terminated)
            data.set(("next", "truncated"), truncated)
            data.set(("next", "done"), terminated | truncated)
        return data, info
