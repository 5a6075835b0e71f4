"""Evaluation on a fixed set of test tasks, the same for every method."""

from __future__ import annotations

import time

import torch
from tensordict import TensorDictBase
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp.choices import DEFAULT_TEST_SEED, DEFAULT_VALIDATION_SEED
from torchrl_silp.envs.reach import ReachEnv
from torchrl_silp.models.base import as_model
from torchrl_silp.transforms import CollisionHandling
from torchrl_silp.validation import check_positive_int

__all__ = ["evaluate", "episode_outcomes", "straight_path_free", "DEFAULT_TEST_SEED", "DEFAULT_VALIDATION_SEED"]



@torch.no_grad()
def straight_path_free(model, tasks: TensorDictBase, max_steps: int = 50) -> torch.Tensor:
    """Which tasks ``[n]`` the straight joint-space path to the goal configuration solves within ``max_steps``
    steps of ``model.action_scale``, its motion checked as a step's is (bool ``[n]``): the tasks that need no
    detour, a measure of how hard a task distribution is.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> tasks = model.sample_tasks(200, torch.Generator().manual_seed(0))
        >>> free = straight_path_free(model, tasks)
        >>> free.shape, 0 < free.float().mean() < 1
        (torch.Size([200]), tensor(True))
    """
    model = as_model(model)
    start, goal = tasks.get(model.config_key), tasks.get(model.goal_config_key)
    steps = torch.ceil((goal - start).abs().amax(-1) / model.action_scale - 1e-6)
    flags, _ = model.motion_collision_flags(start, goal, tasks.select(*model.scene_keys))
    return (flags.squeeze(-1) == 0) & (steps <= max_steps)


@torch.no_grad()
def episode_outcomes(rollout: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(alive, success, collision)`` of a ``[n, T]`` rollout that ran on past each episode's end.

    ``alive`` (bool ``[n, T]``) masks the steps after an episode's first done
    flag; ``success`` and ``collision`` (bool ``[n]``) say whether an episode
    had such a step before it ended.
    """
    done = rollout["next", "done"].squeeze(-1)
    alive = torch.ones_like(done)
    alive[..., 1:] = ~done[..., :-1].cumsum(-1).bool()
    success = (rollout["next", "success"].squeeze(-1) & alive).any(-1)
    collision = (rollout["next", "collision"].squeeze(-1) & alive).any(-1)
    return alive, success, collision


def evaluate(
    policy,
    n_tasks: int = 1000,
    seed: int = DEFAULT_TEST_SEED,
    *,
    model=None,
    env=None,
    observation_transform=None,
    max_steps: int = 50,
    collision_type: int = 0,
    device: torch.device | str | None = None,
    return_rollout: bool = False,
    exploration_type: ExplorationType = ExplorationType.DETERMINISTIC,
    split_by_straight_path: bool = False,
) -> dict | tuple[dict, TensorDictBase]:
    """Roll a policy out deterministically on ``n_tasks`` fixed test tasks of a task model.

    The tasks are those of ``ReachEnv(model, num_envs=n_tasks, seed=seed)`` after
    its first reset, so every method sees the same ones for the same model and
    seed. All tasks run as one batch under ``exploration_type``: ``DETERMINISTIC``
    (default), a stochastic policy's mode, as the paper tests; ``RANDOM``, its samples,
    as it acts in training. With ``collision_type=0`` (default) a collision ends the
    episode as a failure, as it would on a real arm.

    Args:
        policy: a TensorDict module (or any callable ``td -> td`` writing ``"action"``).
        n_tasks: number of test tasks (paper: 1000).
        seed: seed of the test tasks.
        model: the :class:`~torchrl_silp.models.TaskModel` of the task (or an env holding one).
        env: an env to evaluate in instead of one built from ``model`` (its batch size is
            the number of tasks; it must end episodes on collision for a collision to count
            as the end of an episode).
        observation_transform: builds the policy's inputs from the named state (the env's
            observation transforms); the model's :class:`~torchrl.envs.CatTensors` by default.
        max_steps: episode length (50 in our tables).
        collision_type: collision handling during the test (0, 1 or 2).
        device: device of the test env; defaults to the policy's parameters' device.
        return_rollout: also return the rollout TensorDict ``[n_tasks, T]``.
        exploration_type: how the policy acts (TorchRL's ``set_exploration_type``).
        split_by_straight_path: also split the success by :func:`straight_path_free`
            (a motion check of every task's straight path: about as long as the rollout).

    Returns:
        ``success_rate``, ``collision_rate`` (episodes with a collision),
        ``mean_steps`` (steps of the successful episodes), ``mean_return``,
        ``time_per_rollout_s`` (wall time of the batched rollout divided by the
        number of tasks), ``rollout_wall_s`` and ``n_tasks``; with ``split_by_straight_path``,
        ``free_task_share`` (the tasks whose straight joint path solves them),
        ``free_success_rate`` and ``blocked_success_rate`` (the success rate on those and
        on the others; NaN where there are none).

    Examples:
        >>> import torch
        >>> from torchrl_silp import evaluate
        >>> from torchrl_silp.models import UR5eReach
        >>> def still(td):  # a policy that never moves
        ...     return td.set("action", torch.zeros(*td.batch_size, 3))
        >>> evaluate(still, n_tasks=8, model=UR5eReach())["success_rate"]
        0.0
    """
    if not callable(policy):
        raise TypeError(f"policy must be a TensorDict module or a callable td -> td, got {type(policy).__name__}")
    check_positive_int(n_tasks, name="n_tasks")
    if env is None and model is None:
        raise ValueError("evaluate needs model (the task model) or env")
    if device is None:
        params = list(policy.parameters()) if hasattr(policy, "parameters") else []
        device = params[0].device if params else torch.device("cpu")
    if env is None:
        model = as_model(model)
        if observation_transform is None:
            observation_transform = model.observation_transform()
        env = TransformedEnv(
            ReachEnv(model, num_envs=n_tasks, seed=seed, max_steps=max_steps, device=device),
            Compose(CollisionHandling(collision_type), observation_transform),
        )
    n = env.batch_size.numel()
    with set_exploration_type(exploration_type):
        start = time.perf_counter()
        rollout = env.rollout(env.max_steps, policy, break_when_all_done=True, break_when_any_done=False)
        wall = time.perf_counter() - start
    alive, success, collision = episode_outcomes(rollout)
    steps = alive.sum(-1)
    returns = (rollout["next", "reward"].squeeze(-1) * alive).sum(-1)
    metrics = {
        "success_rate": success.float().mean().item(),
        "collision_rate": collision.float().mean().item(),
        "mean_steps": steps[success].float().mean().item() if success.any() else float("nan"),
        "mean_return": returns.mean().item(),
        "time_per_rollout_s": wall / n,
        "rollout_wall_s": wall,
        "n_tasks": n,
    }
    if split_by_straight_path:  # the tasks as drawn: the first step's named state, flat
        task_model = as_model(model if model is not None else env)
        free = straight_path_free(task_model, rollout[..., 0].reshape(-1), env.max_steps).reshape(success.shape)
        metrics.update(free_task_share=free.float().mean().item(), free_success_rate=_share(success, free),
                       blocked_success_rate=_share(success, ~free))
    return (metrics, rollout) if return_rollout else metrics


def _share(hit: torch.Tensor, among: torch.Tensor) -> float:
    """The share of ``among`` that ``hit`` marks (NaN where ``among`` marks nothing)."""
    return hit[among].float().mean().item() if among.any() else float("nan")
