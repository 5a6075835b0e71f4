"""Task models and envs cross process boundaries (multi-process collectors pickle them)."""

from __future__ import annotations

import pickle

import pytest
import torch

from torchrl_silp import UR5eReachEnv
from torchrl_silp.models import PandaReach, UR5eReach
from torchrl_silp.models.learned_collision import CollisionNet, with_learned_edges


@pytest.mark.parametrize("make", [UR5eReach, PandaReach], ids=["ur5e", "panda"])
def test_a_pickled_model_steps_like_the_original(make):
    model = make()
    copy = pickle.loads(pickle.dumps(model))
    tasks = model.sample_tasks(16, torch.Generator().manual_seed(0))
    action = torch.rand(16, model.action_dim, generator=torch.Generator().manual_seed(1)) * 2 - 1
    ours, theirs = model.step(tasks, action), copy.step(tasks, action)
    assert (ours[0] == theirs[0]).all()
    for a, b in zip(ours[1:], theirs[1:]):
        assert torch.equal(a, b)


def test_a_pickled_env_rolls_out_the_same_tasks():
    env = UR5eReachEnv(num_envs=4, seed=3)
    copy = pickle.loads(pickle.dumps(env))
    assert torch.equal(env.reset()["joint_position"], copy.reset()["joint_position"])


def test_a_model_with_a_learned_edge_check_pickles_with_its_net():
    model = UR5eReach()
    torch.manual_seed(0)
    learned = with_learned_edges(model, CollisionNet(3 + 6, hidden_sizes=(16,)), threshold=0.5)
    copy = pickle.loads(pickle.dumps(learned))
    assert type(copy) is UR5eReach and copy.edge_check.threshold == 0.5
    tasks = model.sample_tasks(32, torch.Generator().manual_seed(0))
    q0 = tasks["joint_position"]
    q1 = q0 + torch.rand(32, 3, generator=torch.Generator().manual_seed(1)) - 0.5
    scene = tasks.select("obstacle")
    free = learned.segment_collision_free(q0, q1, scene)
    assert torch.equal(copy.segment_collision_free(q0, q1, scene), free)
