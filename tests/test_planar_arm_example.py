"""examples/planar_arm.py, the repository's task of a user's own: its task distribution and the search that
says which of its tasks an ideal policy could solve."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_silp.models import check_task_model

_SPEC = importlib.util.spec_from_file_location("planar_arm", Path(__file__).parents[1] / "examples" / "planar_arm.py")
planar_arm = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(planar_arm)


@pytest.fixture(scope="module")
def planar_model():
    m = planar_arm.PlanarArmReach(n_discs=3)
    check_task_model(m)
    return m


def _task(model, start, goal_config, discs):
    start, goal_config = torch.tensor([start]), torch.tensor([goal_config])
    return TensorDict({model.config_key: start, model.achieved_goal_key: model.achieved_goal(start),
                       model.desired_goal_key: model.achieved_goal(goal_config), "discs": torch.tensor([discs])},
                      batch_size=[1])


def test_tasks_turn_the_base_within_one_turn_and_put_the_discs_in_the_outer_links_ring(planar_model):
    tasks = planar_model.sample_tasks(2000, torch.Generator().manual_seed(0))
    for key in (planar_model.config_key, planar_model.goal_config_key):
        q = tasks[key]
        assert q[:, 0].abs().max() <= math.pi and q[:, 1:].abs().max() <= 2.5
    distance = tasks["discs"][..., :2].norm(dim=-1)
    assert 0.5 <= distance.min() and distance.max() <= 0.8
    assert float(planar_model.config_low[0]) == pytest.approx(-2 * math.pi) and float(planar_model.config_high[0]) == pytest.approx(2 * math.pi)


def test_the_search_keeps_within_the_straight_paths_steps_and_the_tips_speed_on_free_reaches(planar_model):
    """Discs out of reach: a straight joint path of ceil(max |dq| / 0.1) steps always gets there, and no
    path gets there in fewer steps than the tip's distance over its fastest step (the arm's 0.9 + 0.5 +
    0.2 m of lever arms times 0.1 rad) allows."""
    tasks = planar_model.sample_tasks(12, torch.Generator().manual_seed(3))
    tasks.set("discs", torch.tensor([[5.0, 5.0, 0.01]]).expand(12, 3, 3).clone())
    dq = (tasks[planar_model.goal_config_key] - tasks[planar_model.config_key]).abs().amax(-1)
    straight = torch.ceil(dq / planar_model.action_scale - 1e-4).long()
    gap = (tasks[planar_model.achieved_goal_key] - tasks[planar_model.desired_goal_key]).norm(dim=-1) - planar_model.success_distance
    fastest = (0.9 + 0.5 + 0.2) * planar_model.action_scale
    too_few = torch.ceil(gap / fastest).long() - 1
    for i in range(12):
        assert bool(planar_arm.solvable(planar_model, tasks[i:i + 1], max_steps=int(straight[i]) + 1)[0]), i
        if too_few[i] >= 1:
            assert not bool(planar_arm.solvable(planar_model, tasks[i:i + 1], max_steps=int(too_few[i]))[0]), i


def test_the_search_finds_no_way_to_a_goal_inside_a_disc_or_out_of_reach(planar_model):
    task = _task(planar_model, [0.0, 0.5, 0.5], [0.0, 0.0, 0.0], [[0.9, 0.0, 0.12], [5.0, 5.0, 0.01], [5.0, 5.0, 0.01]])
    assert not bool(planar_arm.solvable(planar_model, task, max_steps=80)[0])  # the tip's goal (0.9, 0) lies in a disc
    task = _task(planar_model, [0.0, 0.5, 0.5], [0.0, 0.0, 0.0], [[5.0, 5.0, 0.01]] * 3)
    task.set(planar_model.desired_goal_key, torch.tensor([[1.2, 0.0]]))  # beyond the 0.9 m reach
    assert not bool(planar_arm.solvable(planar_model, task, max_steps=80)[0])


def test_a_straight_path_solves_a_task_when_its_motion_is_free_and_short_enough(planar_model):
    far, near = [[5.0, 5.0, 0.01]] * 3, [[0.0, 0.6, 0.1], [5.0, 5.0, 0.01], [5.0, 5.0, 0.01]]
    clear = _task(planar_model, [0.0, 0.5, 0.5], [0.0, 0.5, -0.5], far)
    clear.set(planar_model.goal_config_key, torch.tensor([[0.0, 0.5, -0.5]]))
    assert bool(planar_arm.straight_path_free(planar_model, clear, max_steps=10)[0])  # 1.0 rad of the wrist: 10 steps
    assert not bool(planar_arm.straight_path_free(planar_model, clear, max_steps=9)[0])
    # the base turning a quarter turn sweeps the arm through a disc on the y axis
    swept = _task(planar_model, [0.0, 0.0, 0.0], [math.pi / 2 + 0.4, 0.0, 0.0], near)
    swept.set(planar_model.goal_config_key, torch.tensor([[math.pi / 2 + 0.4, 0.0, 0.0]]))
    flags, _ = planar_model.collision_flags(torch.tensor([[math.pi / 2, 0.0, 0.0]]), torch.tensor([near]))
    assert int(flags) != 0 and not bool(planar_arm.straight_path_free(planar_model, swept, max_steps=50)[0])
