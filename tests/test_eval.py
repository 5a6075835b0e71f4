"""``evaluate``'s figures: the split of the test tasks by whether the straight joint path solves them, and the
policy's exploration type."""

from __future__ import annotations

import math

import torch
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_silp import evaluate
from torchrl_silp.envs import ReachEnv
from torchrl_silp.eval import episode_outcomes, straight_path_free

N_TASKS, SEED = 300, 7


def straight_to_the_goal(model):
    """A policy that moves along the straight joint path to the goal configuration, the largest joint at full
    speed: it solves what :func:`straight_path_free` says the straight path solves."""

    def act(td):
        delta = (td[model.goal_config_key] - td[model.config_key]) / model.action_scale
        return td.set("action", delta / delta.abs().amax(-1, keepdim=True).clamp_min(1.0))

    return act


def test_the_success_split_follows_the_tasks_the_straight_path_solves(model):
    metrics, rollout = evaluate(straight_to_the_goal(model), n_tasks=N_TASKS, seed=SEED, model=model,
                                return_rollout=True, split_by_straight_path=True)
    # the same tasks, drawn independently of evaluate
    tasks = ReachEnv(model, num_envs=N_TASKS, seed=SEED).reset()
    free = straight_path_free(model, tasks)
    _, success, _ = episode_outcomes(rollout)
    assert 0.2 < metrics["free_task_share"] < 0.9  # the paper's task has both kinds
    assert metrics["free_task_share"] == free.float().mean().item()
    # the straight policy solves every free task, and the split is the per-task success on each kind
    assert metrics["free_success_rate"] == 1.0
    assert bool(success[free].all())
    assert metrics["blocked_success_rate"] == success[~free].float().mean().item()
    assert metrics["blocked_success_rate"] < 0.5


def test_a_split_with_no_task_of_a_kind_is_nan(model):
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, model.action_dim))  # noqa: E731
    metrics = evaluate(still, n_tasks=1, seed=SEED, model=model, split_by_straight_path=True)
    kinds = [metrics["free_success_rate"], metrics["blocked_success_rate"]]
    assert sum(math.isnan(k) for k in kinds) == 1


def test_without_the_split_no_split_figure_is_given(model):
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, model.action_dim))  # noqa: E731
    metrics = evaluate(still, n_tasks=4, seed=SEED, model=model, max_steps=3)
    assert not {"free_task_share", "free_success_rate", "blocked_success_rate"} & set(metrics)


def test_the_policy_acts_under_the_exploration_type_asked_for(model):
    seen = []

    def record(td):
        seen.append(exploration_type())
        return td.set("action", torch.zeros(*td.batch_size, model.action_dim))

    evaluate(record, n_tasks=4, model=model, max_steps=3)
    evaluate(record, n_tasks=4, model=model, max_steps=3, exploration_type=ExplorationType.RANDOM)
    assert seen == [ExplorationType.DETERMINISTIC] * 3 + [ExplorationType.RANDOM] * 3
