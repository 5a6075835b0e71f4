"""Hindsight goal relabelling for goals that live inside the observation (the *-HER baselines)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import HERReplayBuffer, LazyTensorStorage
from torchrl.data.replay_buffers.her import HindsightStrategy

from torchrl_silp.envs.reach import UR5eReachEnv

__all__ = ["GoalRelabelingReplayBuffer", "HER_STRATEGIES"]

HER_STRATEGIES = tuple(s.value for s in HindsightStrategy)

# where UR5eReachEnv's 15-D observation holds the TCP (the achieved goal) and the goal
_TCP = slice(3, 6)
_GOAL = slice(12, 15)


class GoalRelabelingReplayBuffer(HERReplayBuffer):
    """TorchRL's :class:`~torchrl.data.HERReplayBuffer` for :class:`~torchrl_silp.UR5eReachEnv` data.

    The env keeps its goal inside the observation (``obs[12:15]``) and the
    achieved goal is the next TCP (``next_obs[3:6]``). :meth:`extend` adds
    them as ``"desired_goal"`` / ``"achieved_goal"`` keys so that TorchRL's
    buffer can relabel; every sampled batch is then made consistent again:
    the relabelled goal is written back into both observations, the reward
    is the env's own (``-10`` for a stored collision, ``+1`` within
    ``success_distance`` of the new goal, else minus the distance), and
    ``terminated`` / ``done`` follow the new success (``HERReplayBuffer``
    itself only recomputes the reward).

    ``extend`` must receive whole episodes, each contiguous and in time order
    (e.g. what :class:`recipes.utils.EpisodeAssembler` returns), because
    episode boundaries are read from ``("next", "done")`` in storage order.

    Args:
        env: the env whose reward constants, success distance and collision type apply.
        her_ratio: fraction of each batch relabelled (0.8: 4 imagined goals per real one).
        strategy: ``"future"`` (default), ``"final"``, ``"episode"`` or ``"random"``.
        capacity: transitions kept when no ``storage`` is given.
        storage: a 1-D TorchRL storage (default ``LazyTensorStorage(capacity)``).
        device: device of the default storage.
        **kwargs: forwarded to :class:`~torchrl.data.HERReplayBuffer`.

    Examples:
        >>> from torchrl_silp import UR5eReachEnv
        >>> from torchrl_silp.data import GoalRelabelingReplayBuffer
        >>> env = UR5eReachEnv(num_envs=4, seed=0, max_steps=10)
        >>> episodes = env.rollout(10).reshape(-1)  # env-major: each env's episode is contiguous
        >>> rb = GoalRelabelingReplayBuffer(env, capacity=100, her_ratio=1.0)
        >>> _ = rb.extend(episodes)
        >>> batch = rb.sample(8)
        >>> bool((batch["observation"][:, 12:15] == batch["desired_goal"]).all())
        True
    """

    def __init__(
        self,
        env: UR5eReachEnv,
        *,
        her_ratio: float = 0.8,
        strategy: str = "future",
        capacity: int = 1_000_000,
        storage=None,
        device: torch.device | str | None = None,
        **kwargs,
    ):
        if strategy not in HER_STRATEGIES:
            raise ValueError(f"strategy must be one of {HER_STRATEGIES}, got {strategy!r}")
        if isinstance(her_ratio, bool) or not isinstance(her_ratio, (int, float)) or not 0 <= her_ratio <= 1:
            raise ValueError(f"her_ratio must be a number in [0, 1], got {her_ratio!r}")
        if storage is None:
            if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
                raise ValueError(f"capacity must be a positive int, got {capacity!r}")
            storage = LazyTensorStorage(capacity, device="auto" if device is None else torch.device(device))
        super().__init__(
            reward_fn=self._relabelled_reward,
            her_ratio=float(her_ratio),
            strategy=strategy,
            goal_key="desired_goal",
            achieved_goal_key="achieved_goal",
            storage=storage,
            **kwargs,
        )
        self.success_distance = float(env.success_distance)
        self.collision_reward = float(env.COLLISION_REWARD)
        self.success_reward = float(env.SUCCESS_REWARD)
        self.collision_ends_episode = env.collision_type == 0

    def extend(self, data: TensorDictBase, *args, **kwargs):
        data = data.reshape(-1) if data.batch_dims != 1 else data
        data = data.clone(recurse=False)
        data.set("desired_goal", data["observation"][..., _GOAL])
        data.set("achieved_goal", data["next", "observation"][..., _TCP])
        return super().extend(data, *args, **kwargs)

    def _collided(self, td: TensorDictBase) -> torch.Tensor:
        # a collision step keeps the -10 whatever the goal (type 1/2 put the arm back, so the
        # stored next observation alone no longer shows the collision)
        return td["next", "reward"] <= self.collision_reward

    def _relabelled_reward(self, td: TensorDictBase) -> torch.Tensor:
        dist = (td["next", "observation"][..., _TCP] - td["desired_goal"]).norm(dim=-1, keepdim=True)
        reward = torch.where(dist < self.success_distance, torch.full_like(dist, self.success_reward), -dist)
        return torch.where(self._collided(td), torch.full_like(dist, self.collision_reward), reward)

    def _sample(self, batch_size: int):
        data, info = super()._sample(batch_size)
        goal = data["desired_goal"]
        reward = data["next", "reward"]
        # rows that kept their goal are unchanged by this: their observations already hold it
        data["observation"][..., _GOAL] = goal
        data["next", "observation"][..., _GOAL] = goal
        terminated = reward >= self.success_reward
        if self.collision_ends_episode:
            terminated = terminated | self._collided(data)
        truncated = data.get(("next", "truncated"), torch.zeros_like(terminated)) & ~terminated
        with data.unlock_():
            data.set(("next", "terminated"), terminated)
            data.set(("next", "truncated"), truncated)
            data.set(("next", "done"), terminated | truncated)
        return data, info
