"""Evaluation on a fixed set of test tasks, the same for every method."""

from __future__ import annotations

import time

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp.envs.reach import UR5eReachEnv

__all__ = ["evaluate", "episode_outcomes", "DEFAULT_TEST_SEED"]

DEFAULT_TEST_SEED = 20231101  # the 1000 test tasks every recipe and baseline reports on


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
    max_steps: int = 50,
    collision_type: int = 0,
    workspace_exit: str = "collision",
    task_branch: str = "front",
    device: torch.device | str | None = None,
    env: UR5eReachEnv | None = None,
    return_rollout: bool = False,
) -> dict | tuple[dict, TensorDictBase]:
    """Roll a policy out deterministically on ``n_tasks`` fixed test tasks.

    The tasks are those of ``UR5eReachEnv(num_envs=n_tasks, seed=seed)`` after
    its first reset, so every method sees the same ones for the same seed. All
    tasks run as one batch under ``ExplorationType.DETERMINISTIC``. With
    ``collision_type=0`` (default) a collision ends the episode as a failure,
    as it would on a real arm.

    Args:
        policy: a TensorDict module (or any callable ``td -> td`` writing ``"action"``).
        n_tasks: number of test tasks (paper: 1000).
        seed: seed of the test tasks.
        max_steps: episode length (paper: 50).
        collision_type: collision handling during the test (0, 1 or 2).
        workspace_exit: ``"collision"`` or ``"block"`` (see :class:`~torchrl_silp.UR5eReachEnv`).
        task_branch: ``"front"`` or ``"any"``: the IK branch of the tasks (see :class:`~torchrl_silp.UR5eReachEnv`).
        device: device of the test env; defaults to the policy's parameters' device.
        env: an env to evaluate in instead (its batch size is the number of tasks).
        return_rollout: also return the rollout TensorDict ``[n_tasks, T]``.

    Returns:
        ``success_rate``, ``collision_rate`` (episodes with a collision),
        ``mean_steps`` (steps of the successful episodes), ``mean_return``,
        ``time_per_rollout_s`` (wall time of the batched rollout divided by the
        number of tasks), ``rollout_wall_s`` and ``n_tasks``.

    Examples:
        >>> import torch
        >>> from torchrl_silp import evaluate
        >>> def still(td):  # a policy that never moves
        ...     return td.set("action", torch.zeros(*td.batch_size, 3))
        >>> evaluate(still, n_tasks=8)["success_rate"]
        0.0
    """
    if isinstance(n_tasks, bool) or not isinstance(n_tasks, int) or n_tasks < 1:
        raise ValueError(f"n_tasks must be a positive int, got {n_tasks!r}")
    if device is None:
        params = list(policy.parameters()) if hasattr(policy, "parameters") else []
        device = params[0].device if params else torch.device("cpu")
    if env is None:
        env = UR5eReachEnv(
            num_envs=n_tasks, seed=seed, max_steps=max_steps, collision_type=collision_type,
            workspace_exit=workspace_exit, task_branch=task_branch, device=device,
        )
    n = env.batch_size.numel()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
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
    return (metrics, rollout) if return_rollout else metrics
