"""The learned collision model of appendix B (torchrl_silp.models.learned_collision) and the planner option."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp.envs import ReachEnv
from torchrl_silp.models import UR5eReach
from torchrl_silp.models.learned_collision import (
    CollisionNet,
    LearnedEdgeCheck,
    classification_metrics,
    collision_dataset,
    load_collision_net,
    roc_curve,
    train_collision_net,
    with_learned_edges,
)
from torchrl_silp.planning import plan_demonstrations


def constant_net(logit: float) -> CollisionNet:
    """A net that says the same logit everywhere: every weight 0, the output bias ``logit``."""
    net = CollisionNet(3 + 6, hidden_sizes=(8,))
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        net.mlp[-1].bias.fill_(logit)
    return net


def test_metrics_count_the_confusion_matrix():
    prob = torch.tensor([0.9, 0.8, 0.2, 0.6, 0.1, 0.4])
    labels = torch.tensor([True, True, True, False, False, False])
    m = classification_metrics(prob, labels)
    # tp 2, fn 1, fp 1, tn 2
    assert m["accuracy"] == 4 / 6 and m["recall"] == 2 / 3 and m["precision"] == 2 / 3 and m["specificity"] == 2 / 3


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.integers(0, 10), st.booleans()), min_size=2, max_size=40))
def test_roc_area_is_the_probability_a_positive_outranks_a_negative(pairs):
    prob = torch.tensor([p / 10 for p, _ in pairs], dtype=torch.float64)
    labels = torch.tensor([y for _, y in pairs])
    pos, neg = prob[labels].tolist(), prob[~labels].tolist()
    if not pos or not neg:
        return
    want = np.mean([1.0 if a > b else 0.5 if a == b else 0.0 for a in pos for b in neg])
    roc = roc_curve(prob, labels)
    assert roc["auc"] == pytest.approx(want, abs=1e-12)
    assert roc["tpr"][0] == 1.0 and roc["fpr"][0] == 1.0  # threshold 0: everything is a collision


def test_the_planner_asks_the_net_and_the_step_stays_exact(model):
    env = ReachEnv(model, num_envs=4, seed=0)
    episodes = env.rollout(30, break_when_any_done=False)
    gen = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    exact = plan_demonstrations(model, episodes, n_pairs=6, generator=gen())
    blocked = plan_demonstrations(with_learned_edges(model, constant_net(20.0)), episodes, n_pairs=6, generator=gen())
    free = with_learned_edges(model, constant_net(-20.0))
    assert len(exact) > 0 and len(blocked) == 0  # every edge "collides": no path, no demonstration
    q = episodes["joint_position"][:, 0]
    far = q + 2.0
    assert free.segment_collision_free(q, far, episodes[:, 0].select("obstacle")).all()
    assert not model.segment_collision_free(q, far, episodes[:, 0].select("obstacle")).all()
    # the step (the env's own, with the swept check) is the model's
    state = episodes[:, 0].select(*model.state_keys)
    action = torch.ones(4, 3)
    for a, b in zip(free.step(state, action)[1:], model.step(state, action)[1:]):
        assert torch.equal(a, b)


def test_any_edge_check_decides_the_planners_segments_and_nothing_else(model):
    # a check that calls a sample colliding where joint 0 exceeds 0.5: joint 0 moves linearly along a
    # segment whose ends are both sampled, so a segment collides exactly where one of its ends does
    planner_model = copy.copy(model)
    planner_model.edge_check = lambda m, config, scene, margin: config[..., 0] > 0.5
    gen = torch.Generator().manual_seed(0)
    tasks = model.sample_tasks(64, gen)
    q0 = tasks["joint_position"]
    q1 = q0 + 0.6 * torch.randn(64, 3, generator=gen)
    free = planner_model.segment_collision_free(q0, q1, tasks.select("obstacle"))
    assert torch.equal(free, torch.maximum(q0[:, 0], q1[:, 0]) <= 0.5)
    assert 0 < int(free.sum()) < 64
    assert model.edge_check is None and not torch.equal(free, model.segment_collision_free(q0, q1, tasks.select("obstacle")))
    # the motion check of the env's steps stays the model's collision test
    flags, goals = planner_model.motion_collision_flags(q0, q1, tasks.select("obstacle"))
    exact_flags, exact_goals = model.motion_collision_flags(q0, q1, tasks.select("obstacle"))
    assert torch.equal(flags, exact_flags) and torch.equal(goals, exact_goals)


def test_the_learned_edge_check_refuses_a_bad_net_or_threshold():
    with pytest.raises(TypeError, match="net"):
        LearnedEdgeCheck(torch.nn.Linear(9, 1))
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="threshold"):
            LearnedEdgeCheck(constant_net(0.0), bad)


def test_a_trained_net_separates_the_classes(model):
    inputs, labels, _, _ = collision_dataset(model, 30_000, torch.Generator().manual_seed(1), n_scenes=300)
    net, result = train_collision_net(inputs, labels, epochs=4, batch_size=256, lr=2e-3, seed=0)
    m = result["metrics"]
    majority = max(labels.float().mean().item(), 1 - labels.float().mean().item())
    assert m["accuracy"] > majority + 0.08 and m["specificity"] > 0.6 and result["roc"]["auc"] > 0.95
    assert result["test_n"] == 3000 and result["train_n"] == 27_000


def test_the_recipe_option_loads_the_net_into_the_planners_model(model, tmp_path):
    from torchrl_silp.recipes import builders
    from torchrl_silp.recipes.schema import load_config

    net = constant_net(20.0)
    path = tmp_path / "net.pt"
    torch.save({"state_dict": net.state_dict(), "in_features": 9, "hidden_sizes": (8,)}, path)
    loaded = load_collision_net(path)
    x = torch.randn(5, 9)
    torch.testing.assert_close(loaded(x), net(x))
    cfg = load_config("sac_silp", [f"planner.collision_net={path}", "planner.collision_threshold=0.7"])
    buffers = builders.make_buffers(cfg, model, torch.device("cpu"))
    planner_model = buffers.demo_buffer.model
    assert planner_model.edge_check.threshold == 0.7 and type(planner_model) is UR5eReach
    assert planner_model.edge_check.net.mlp[-1].bias.item() == 20.0
    assert model.edge_check is None  # the env's model keeps the exact check
