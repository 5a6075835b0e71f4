"""OMPL's PRM baseline (PRM-0.1 / PRM-1) over a task model: collision-free paths in any configuration space,
the time budget, execution, demonstrations, arguments, the recipe."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict, TensorDictBase

pytest.importorskip("ompl")

from torchrl.envs import Compose, TransformedEnv  # noqa: E402

from torchrl_silp import CollisionHandling, ReachEnv, UR5eReachEnv, evaluate  # noqa: E402
from torchrl_silp.baselines import (  # noqa: E402
    PathReplayPolicy,
    PRMPlanner,
    collect_prm_demonstrations,
    evaluate_prm,
    path_to_actions,
    prm_demonstration_batches,
    prm_demonstration_stats,
)
from torchrl_silp.baselines import prm as prm_module  # noqa: E402
from torchrl_silp.data.demo_buffer import transition_keys  # noqa: E402
from torchrl_silp.eval import episode_outcomes  # noqa: E402
from torchrl_silp.geometry import CollisionReason  # noqa: E402
from torchrl_silp.models import TaskModel, UR5eReach  # noqa: E402

# planning may overrun its budget by at most 20 % plus 0.25 s. The overrun is the collision check under
# way and OMPL stopping its roadmap thread (a few milliseconds alone); on a loaded machine scheduling stalls
# add to it (up to 178 ms seen with two training runs beside the suite on 2 cores)
BUDGET_SLACK, BUDGET_SLACK_S = 1.2, 0.25


def within_budget(wall: float, budget_s: float) -> bool:
    return wall <= BUDGET_SLACK * budget_s + BUDGET_SLACK_S


pytestmark = pytest.mark.usefixtures("one_thread")  # single-state checks: one thread is fastest


def scene_of(model, task: TensorDictBase) -> TensorDictBase:
    return task.select(*model.scene_keys)


@pytest.fixture(scope="module")
def tasks(model):
    """Tasks whose straight start -> goal segment fails the edge check (a detour is needed), then one where it passes."""
    drawn = model.sample_tasks(64, torch.Generator().manual_seed(3))
    free = model.segment_collision_free(drawn["joint_position"], drawn["goal_joint_position"], scene_of(model, drawn))
    blocked = (~free).nonzero().squeeze(-1)[:5].tolist()  # 2 of them take PRM more than 1 s: others come quickly
    return drawn[blocked + free.nonzero().squeeze(-1)[:1].tolist()]


def dense_segments(path: torch.Tensor, spacing: float = 1e-3) -> torch.Tensor:
    """Every segment of ``path`` sampled at most ``spacing`` apart (max-norm), ends included: ``(M, D)``."""
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(int(math.ceil(float((b - a).abs().max()) / spacing)), 1)
        t = torch.linspace(0, 1, n + 1, dtype=path.dtype)[1:].unsqueeze(-1)
        out.append(a + t * (b - a))
    return torch.cat(out)


def assert_path_ok(model, path, task):
    D = model.config_dim
    assert path.dtype == torch.float32 and path.ndim == 2 and path.shape[-1] == D
    assert torch.equal(path[0], task["joint_position"]) and torch.equal(path[-1], task["goal_joint_position"])
    assert bool(((path >= model.config_low) & (path <= model.config_high)).all())
    # every segment sampled 10x finer than the planner's edge check, each sample checked exactly (no margin)
    dense = dense_segments(path, model.motion_resolution / 10)
    hits = model.collides(dense, scene_of(model, task).expand(dense.shape[0]))
    assert not bool(hits.any()), f"{int(hits.sum())} of {dense.shape[0]} configurations along the path collide"


# ------------------------------------------------------------- (a) paths
@pytest.mark.parametrize("simplify", [True, False])
def test_paths_are_collision_free_and_join_start_to_goal(model, tasks, simplify):
    planner = PRMPlanner(model, 1.0, seed=0, simplify=simplify)
    assert planner.edge_step == model.motion_resolution  # the env's own step check by default
    solved_detours = 0
    for i in range(tasks.batch_size[0] if simplify else tasks.batch_size[0] - 1):
        task = tasks[i]
        path, wall = planner.plan(task["joint_position"], task["goal_joint_position"], scene_of(model, task))
        assert within_budget(wall, planner.budget_s)
        if path is None:
            continue
        assert_path_ok(model, path, task)
        straight = model.segment_collision_free(path[:1], path[-1:], scene_of(model, task).expand(1))
        if not bool(straight):
            assert path.shape[0] > 2  # the straight segment fails the check: the path goes round
            solved_detours += 1
    assert solved_detours >= 1
    if simplify:  # the last task's straight segment is free: PRM connects start and goal directly
        task = tasks[-1]
        path, _ = planner.plan(task["joint_position"], task["goal_joint_position"], task)  # extra keys are ignored
        assert path is not None and path.shape[0] == 2


class PointReach(TaskModel):
    """A point in the unit cube ``[0, 1]^dim`` reaching round a slab with one gap: a task model of any ``config_dim``.

    The scene is one box ``"box"`` ``(lo_0, hi_0, lo_1, hi_1, ...)``: the slab ``0.4 <= x_0 <= 0.6``
    that blocks ``x_1`` below ``top`` (``top`` in ``[0.5, 0.65]``); start (``x_0 < 0.2``) and goal
    (``x_0 > 0.8``) have ``x_1 < 0.35``, so the straight motion always crosses the slab and a path
    must pass above it. Clearance is the max-norm distance to the box (1-Lipschitz per radian).
    """

    collision_reasons = ("obstacle",)
    action_scale = 0.1

    def __init__(self, dim: int, **kwargs):
        super().__init__(**kwargs)
        self.config_dim = self.goal_dim = dim
        self.scene_shapes = {"box": (2 * dim,)}
        self.config_low = torch.zeros(dim)
        self.config_high = torch.ones(dim)

    def achieved_goal(self, config):
        return config.clone()

    def clearance(self, config, scene):
        box = scene.get("box") if isinstance(scene, TensorDictBase) else scene
        lo, hi = box[..., 0::2], box[..., 1::2]
        return torch.maximum(lo - config, config - hi).amax(-1, keepdim=True)

    def collision_flags(self, config, scene, margin=None):
        clear = self.clearance(config, scene)
        flags = (clear < (margin or {}).get("obstacle", 0.0)).to(torch.uint8)
        return flags, config.expand(*flags.shape[:-1], self.config_dim)

    def lipschitz(self):
        return {"obstacle": 1.0}

    def sample_tasks(self, n, generator=None):
        D = self.config_dim
        u = lambda *shape: torch.rand(*shape, generator=generator)  # noqa: E731
        start = 0.05 + 0.3 * u(n, D)
        goal = 0.05 + 0.3 * u(n, D)
        start[:, 0] = 0.05 + 0.15 * u(n)
        goal[:, 0] = 0.8 + 0.15 * u(n)
        box = torch.tensor([-1.0, 2.0]).repeat(n, D)
        box[:, 0], box[:, 1] = 0.4, 0.6
        box[:, 3] = 0.5 + 0.15 * u(n)
        return TensorDict(
            {"joint_position": start, "achieved_goal": start.clone(), "box": box, "desired_goal": goal.clone(),
             "goal_joint_position": goal},
            batch_size=[n],
        )


@pytest.mark.parametrize("dim", [2, 7])
def test_plans_in_the_configuration_space_of_any_task_model(dim):
    point = PointReach(dim)
    tasks = point.sample_tasks(2, torch.Generator().manual_seed(dim))
    planner = PRMPlanner(point, 1.0, seed=0)
    for i in range(2):
        task = tasks[i]
        path, wall = planner.plan(task["joint_position"], task["goal_joint_position"], task.select("box"))
        assert within_budget(wall, planner.budget_s)
        assert path is not None and path.shape[-1] == dim
        assert torch.equal(path[0], task["joint_position"]) and torch.equal(path[-1], task["goal_joint_position"])
        assert bool(((path >= 0) & (path <= 1)).all())
        # the slab, by hand: a point is inside when every coordinate is within the box
        box = task["box"]
        dense = dense_segments(path)
        inside = ((dense >= box[0::2]) & (dense <= box[1::2])).all(-1)
        assert not bool(inside.any())
        assert bool((dense[:, 1] > box[3]).any())  # it passed through the gap above the slab


# ------------------------------------------------------- (b) time budget
class JointWallReach(UR5eReach):
    """The reach task plus a wall in joint space: shoulder_pan in ``[low, high]`` collides.

    The pan joint is bounded (+-2 pi), so no path joins configurations on
    either side of the wall: a problem no planner can solve, whatever its time.
    """

    def __init__(self, low: float, high: float, **kwargs):
        super().__init__(**kwargs)
        self.wall = (low, high)

    def collision_flags(self, config, scene, margin=None):
        flags, tcp = super().collision_flags(config, scene, margin)
        pan = config[..., 0:1]
        wall = (pan >= self.wall[0]) & (pan <= self.wall[1])
        return flags | (wall.to(torch.uint8) * int(CollisionReason.OBSTACLE)), tcp


@pytest.mark.parametrize("budget_s", [0.3, 0.6])
def test_unsolvable_problem_uses_the_budget(model, budget_s):
    drawn = model.sample_tasks(64, torch.Generator().manual_seed(5))
    start, goal = drawn["joint_position"], drawn["goal_joint_position"]
    i = int(((goal[:, 0] - start[:, 0]).abs() > 0.6).nonzero()[0])
    task = drawn[i]
    middle = float(start[i, 0] + goal[i, 0]) / 2
    walled = JointWallReach(middle - 0.1, middle + 0.1)
    scene = scene_of(walled, task)
    assert not bool(walled.collides(torch.stack([start[i], goal[i]]), scene.expand(2)).any())
    assert bool(walled.collides(torch.tensor([middle, *start[i, 1:].tolist()]), scene))
    path, wall = PRMPlanner(walled, budget_s, seed=0).plan(start[i], goal[i], scene)
    assert path is None
    assert 0.8 * budget_s <= wall and within_budget(wall, budget_s)



class SlowToBoundReach(JointWallReach):
    """A model whose one-off Lipschitz estimate takes longer than a planning budget."""

    def lipschitz(self):
        if self._lipschitz is None:
            time.sleep(0.5)
        return super().lipschitz()


def test_a_models_one_off_setup_is_not_charged_to_a_tasks_budget(model):
    drawn = model.sample_tasks(64, torch.Generator().manual_seed(5))
    start, goal = drawn["joint_position"], drawn["goal_joint_position"]
    i = int(((goal[:, 0] - start[:, 0]).abs() > 0.6).nonzero()[0])
    middle = float(start[i, 0] + goal[i, 0]) / 2
    slow = SlowToBoundReach(middle - 0.1, middle + 0.1)
    planner = PRMPlanner(slow, 0.2, seed=0)
    path, wall = planner.plan(start[i], goal[i], scene_of(slow, drawn[i]))
    assert path is None and wall < 0.2 + 0.25 < 0.5


# ------------------------------------------------------------ (c) execution
def test_path_to_actions_bounds_every_step():
    path = torch.tensor([[0.0, 0.0, 0.0], [1.0, -0.3, 0.2], [1.0, -0.3, 0.2], [0.9, 0.4, 0.2]])
    actions = path_to_actions(path, 0.125)
    assert actions.shape == (8 + 6, 3)  # ceil(1 / 0.125) = 8, repeated waypoint 0, ceil(0.7 / 0.125) = 6
    assert bool((actions.abs() <= 1).all())
    reached = path[0] + torch.cumsum(actions * 0.125, 0)
    assert torch.allclose(reached[7], path[1], atol=1e-6) and torch.allclose(reached[-1], path[-1], atol=1e-6)
    # any number of joints, any action scale
    path7 = torch.stack([torch.zeros(7), torch.linspace(-0.5, 0.35, 7)])
    actions7 = path_to_actions(path7, 0.1)
    assert actions7.shape == (5, 7)  # ceil(0.5 / 0.1)
    assert torch.allclose(actions7.sum(0) * 0.1, path7[1], atol=1e-6) and bool((actions7.abs() <= 1).all())


def test_replay_reads_the_step_counter_of_its_tensordict(model):
    paths = [torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, -0.2]]), None, torch.tensor([[0.1, 0.2, 0.3]])]
    policy = PathReplayPolicy(model, paths)
    assert policy.steps.tolist() == [3, 0, 0]  # ceil(0.3 / 0.125), no path, a path of one waypoint
    expected = path_to_actions(paths[0], model.action_scale)
    for t in (0, 2, 3, 40):
        td = TensorDict({"step_count": torch.tensor([[t], [t], [t]])}, batch_size=[3])
        action = policy(td)["action"]
        assert torch.equal(action[0], expected[t] if t < 3 else torch.zeros(3))
        assert bool((action[1:] == 0).all())
    td = TensorDict({"step_count": torch.tensor([[2], [0], [0]])}, batch_size=[3])
    assert torch.equal(policy(td)["action"][0], expected[2])  # each row its own counter
    with pytest.raises(KeyError, match="step_count"):
        policy(TensorDict({}, batch_size=[3]))
    with pytest.raises(ValueError, match="paths"):
        policy(TensorDict({"step_count": torch.zeros(2, 1, dtype=torch.long)}, batch_size=[2]))


def test_executed_paths_reach_the_goal():
    env = UR5eReachEnv(num_envs=6, seed=11, collision_type=0)
    td = env.reset()
    planner = PRMPlanner(env, 1.0, seed=0)  # an env holding a model is accepted for the model
    assert planner.model is env.model
    paths = []
    for i in range(6):
        path, wall = planner.plan(td["joint_position"][i], td["goal_joint_position"][i], td[i].select("obstacle"))
        assert within_budget(wall, planner.budget_s)
        paths.append(path)
    paths[-1] = None  # a failed plan: the arm is left standing
    policy = PathReplayPolicy(env.model, paths)
    rollout = env.rollout(env.max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=False,
                          break_when_all_done=True)
    assert bool((rollout["action"].abs() <= 1).all())
    alive, success, collision = episode_outcomes(rollout)
    short = torch.tensor([p is not None for p in paths]) & (policy.steps <= env.max_steps)
    assert short.sum() >= 3
    assert bool(success[short].all()) and not bool(collision.any())
    assert not bool(success[-1]) and bool(rollout["action"][-1].eq(0).all())
    assert bool(rollout["next", "joint_position"][-1].eq(td["joint_position"][-1]).all())
    # a successful episode ends within the steps its path needs
    steps = alive.sum(-1)
    assert bool((steps[short] <= policy.steps[short]).all())
    # the arm follows its path step by step: start + the cumulated actions of path_to_actions, by hand
    for b in short.nonzero().squeeze(-1).tolist():
        k = int(steps[b])
        along = paths[b][0] + torch.cumsum(path_to_actions(paths[b], 0.125)[:k] * 0.125, 0)
        assert torch.allclose(rollout["next", "joint_position"][b, :k], along, atol=1e-5)


def test_evaluate_prm_matches_evaluate(model):
    out = evaluate_prm(model, 0.3, n_tasks=6, ompl_seed=0)
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, 3))  # noqa: E731
    assert evaluate(still, n_tasks=2, model=model).keys() <= out.keys()  # evaluate()'s keys, and more
    assert out["n_tasks"] == 6 and 0 <= out["success_rate"] <= out["solved_rate"] <= 1
    assert out["collision_rate"] == 0.0  # a planned path passes the env's own step check
    assert within_budget(out["planning_time_max_s"], 0.3)
    assert out["time_per_rollout_s"] == pytest.approx(out["planning_time_s"] + out["execution_time_per_rollout_s"])
    assert out["budget_s"] == 0.3


def test_evaluate_prm_on_another_task_model():
    point = PointReach(4)
    out = evaluate_prm(point, 0.3, n_tasks=4, seed=1, ompl_seed=0)
    # every task is solvable in the free cube and the paths are ~10 steps of 0.1: all reach their goal
    assert out["solved_rate"] == 1.0 and out["success_rate"] == 1.0 and out["collision_rate"] == 0.0
    assert 5 <= out["mean_steps"] <= 50  # a max-norm distance >= 0.6 in steps of 0.1, within 0.05


def test_collected_demonstrations_replay_in_the_env(model):
    n, seed = 4, 1
    demos, stats = collect_prm_demonstrations(model, n, budget_s=0.3, seed=seed)
    assert stats["n_attempted"] == n and stats["n_kept"] == demos["episode"].unique().numel()
    assert stats["n_transitions"] == demos.numel() and stats["wall_s"] > 0
    assert stats["n_kept"] >= 2 and 0 <= stats["success_rate"] <= stats["solved_rate"] <= 1
    assert within_budget(stats["planning_time_max_s"], 0.3)
    assert set(demos.keys(True, True)) == {*transition_keys(model), "is_demo", "episode"}
    assert bool(demos["is_demo"].all())
    assert torch.equal(demos["observation"], model.observation(demos))
    assert torch.equal(demos["next", "observation"], model.observation(demos["next"]))
    # each kept episode ends on its successful, terminating step, and no step before ends it
    last = torch.cat([demos["episode"][1:] != demos["episode"][:-1], torch.tensor([True])])
    assert bool(demos["next", "terminated"][last].all()) and bool((demos["next", "reward"][last] == 1).all())
    assert not bool(demos["next", "done"][~last].any())
    # the same actions, played by the env on the tasks of its first reset, give the same transitions
    env = TransformedEnv(ReachEnv(model, num_envs=n, seed=seed), Compose(CollisionHandling(0), model.observation_transform()))
    T = env.max_steps
    actions = torch.zeros(n, T + 1, 3)
    length = torch.zeros(n, dtype=torch.long)
    for e in demos["episode"].unique().tolist():
        a = demos["action"][demos["episode"] == e]
        actions[e, : a.shape[0]], length[e] = a, a.shape[0]
    rows = torch.arange(n)
    rollout = env.rollout(T, lambda td: td.set("action", actions[rows, td["step_count"].reshape(-1).clamp(max=T)]),
                          break_when_any_done=False, break_when_all_done=True)
    _, success, collision = episode_outcomes(rollout)
    kept = length > 0
    assert bool(success[kept].all()) and not bool(collision[kept].any())
    for e in kept.nonzero().squeeze(-1).tolist():
        mine, played = demos[demos["episode"] == e], rollout[e, : int(length[e])]
        for key in ("joint_position", "observation", "action", ("next", "joint_position"), ("next", "achieved_goal"),
                    ("next", "observation"), ("next", "reward"), ("next", "terminated"), ("next", "done")):
            assert torch.allclose(mine[key].float(), played[key].float(), atol=1e-5), key


def test_collected_demonstrations_of_another_task_model():
    point = PointReach(3)
    demos, stats = collect_prm_demonstrations(point, 3, budget_s=0.3, seed=2)
    assert stats["n_kept"] == 3 and set(demos.keys(True, True)) == {*transition_keys(point), "is_demo", "episode"}
    # the kinematics and the reward, by hand: x' = clip(x + 0.1 a, 0, 1), reward -|x' - g| or 1 within 0.05
    x, a, nxt = demos["joint_position"], demos["action"], demos["next", "joint_position"]
    assert torch.allclose(nxt, (x + 0.1 * a).clamp(0, 1), atol=1e-6)
    dist = (nxt - demos["desired_goal"]).norm(dim=-1, keepdim=True)
    assert torch.allclose(demos["next", "reward"], torch.where(dist < 0.05, torch.ones_like(dist), -dist))
    assert torch.equal(demos["next", "achieved_goal"], nxt)
    # episodes chain: each step starts where the previous one ended; the first starts at the task's start
    same = demos["episode"][1:] == demos["episode"][:-1]
    assert torch.equal(nxt[:-1][same], x[1:][same])
    starts = ReachEnv(point, num_envs=3, seed=2).reset()["joint_position"]
    first = torch.cat([torch.tensor([True]), ~same])
    assert torch.equal(x[first], starts[demos["episode"][first]])
    # and each ends on its first success: within 0.05 of its goal there, and nowhere before
    last = torch.cat([~same, torch.tensor([True])])
    assert bool((dist[last] < 0.05).all()) and not bool((dist[~last] < 0.05).any())
    assert bool(demos["next", "terminated"][last].all()) and not bool(demos["next", "done"][~last].any())


def test_a_collection_started_at_a_later_batch_attempts_the_same_tasks_with_the_same_seeds(monkeypatch):
    point, seed = PointReach(2), 3
    monkeypatch.setattr(prm_module, "_COLLECT_BATCH", 2)
    seeds: list[int] = []
    monkeypatch.setattr(prm_module.ou.RNG, "setSeed", staticmethod(seeds.append))  # OMPL's seed per task
    whole = list(prm_demonstration_batches(point, 6, 0.3, seed=seed))
    seeds_whole, seeds[:] = list(seeds), []
    later = list(prm_demonstration_batches(point, 6, 0.3, start_episode=2, seed=seed))
    assert len(seeds_whole) == 6 and seeds == seeds_whole[2:]
    assert [b["n_attempted"] for _, b in whole] == [2, 2, 2] and [b["n_attempted"] for _, b in later] == [2, 2]
    # the tasks: those of the env's 2nd and 3rd resets, by their episode's index in the whole collection
    env = ReachEnv(point, num_envs=2, seed=seed)
    tasks = torch.cat([env.reset().select("joint_position", "desired_goal") for _ in range(3)])
    for demos, stats in later:
        first = torch.cat([torch.tensor([True]), demos["episode"][1:] != demos["episode"][:-1]])
        episodes = demos["episode"][first]
        assert episodes.numel() == stats["n_kept"] and bool((episodes >= 2).all())
        assert torch.equal(demos["joint_position"][first], tasks["joint_position"][episodes])
        assert torch.equal(demos["desired_goal"][first], tasks["desired_goal"][episodes])
    assert sum(b["n_kept"] for _, b in later) >= 3  # the gap is found in most tasks within 0.3 s


def test_demonstration_stats_add_up_the_batches():
    batches = [
        {"n_attempted": 2, "n_kept": 1, "planning_times": torch.tensor([0.1, 0.2], dtype=torch.float64),
         "solved": torch.tensor([True, False])},
        {"n_attempted": 1, "n_kept": 1, "planning_times": torch.tensor([0.4], dtype=torch.float64),
         "solved": torch.tensor([True])},
    ]
    stats = prm_demonstration_stats(batches, 17, 2.5)
    assert stats == pytest.approx({"n_attempted": 3, "n_kept": 2, "n_transitions": 17, "success_rate": 2 / 3,
                                   "solved_rate": 2 / 3, "planning_s": 0.7, "planning_time_max_s": 0.4, "wall_s": 2.5})
    with pytest.raises(ValueError, match="batch_stats"):
        prm_demonstration_stats([], 0, 0.0)


@pytest.mark.parametrize("start_episode,error", [(1, ValueError), (6, ValueError), (8, ValueError),
                                                 (-2, ValueError), (2.0, TypeError), (True, TypeError)])
def test_a_start_episode_off_the_batches_is_refused_before_planning(model, monkeypatch, start_episode, error):
    monkeypatch.setattr(prm_module, "_COLLECT_BATCH", 2)
    monkeypatch.setattr(prm_module, "_plan_tasks", lambda *a: pytest.fail("planned before the check"))
    with pytest.raises(error, match="start_episode"):
        prm_demonstration_batches(model, 6, 0.1, start_episode=start_episode)


# ------------------------------------------------------------ (d) arguments
@pytest.mark.parametrize(
    "kwargs,name,error",
    [
        ({"budget_s": 0}, "budget_s", ValueError),
        ({"budget_s": -0.1}, "budget_s", ValueError),
        ({"budget_s": float("nan")}, "budget_s", ValueError),
        ({"budget_s": True}, "budget_s", TypeError),
        ({"budget_s": 0.1, "edge_step": 0}, "edge_step", ValueError),
        ({"budget_s": 0.1, "seed": -1}, "seed", ValueError),
        ({"budget_s": 0.1, "seed": 1.5}, "seed", TypeError),
        ({"budget_s": 0.1, "simplify": "yes"}, "simplify", TypeError),
    ],
)
def test_planner_rejects_bad_arguments(model, kwargs, name, error):
    with pytest.raises(error, match=name):
        PRMPlanner(model, **kwargs)


def test_bad_queries_and_calls_name_the_parameter(model, tasks):
    planner = PRMPlanner(model, 0.1)
    task = tasks[0]
    start, goal, scene = task["joint_position"], task["goal_joint_position"], scene_of(model, task)
    with pytest.raises(ValueError, match="start"):
        planner.plan(start[:2], goal, scene)
    with pytest.raises(ValueError, match="goal"):
        planner.plan(start, goal + 10.0, scene)
    with pytest.raises(ValueError, match="obstacle"):
        planner.plan(start, goal, TensorDict({"obstacle": task["obstacle"][:3]}, batch_size=[]))
    with pytest.raises(ValueError, match="scene"):
        planner.plan(start, goal, task["obstacle"])
    with pytest.raises(TypeError, match="model"):
        PRMPlanner("env", 0.1)
    with pytest.raises(ValueError, match="budget_s"):
        evaluate_prm(model, 0.0, n_tasks=2)
    with pytest.raises(ValueError, match="n_tasks"):
        evaluate_prm(model, 0.1, n_tasks=0)
    with pytest.raises(ValueError, match="n_episodes"):
        collect_prm_demonstrations(model, 0)
    with pytest.raises(ValueError, match="path"):
        path_to_actions(torch.zeros(4), 0.125)
    with pytest.raises(ValueError, match="action_scale"):
        path_to_actions(torch.zeros(4, 3), 0.0)
    with pytest.raises(ValueError, match="paths"):
        PathReplayPolicy(model, [torch.zeros(2, 2)])
    with pytest.raises(ValueError, match="paths"):
        PathReplayPolicy(model, [])


def test_missing_ompl_names_the_extra(model, monkeypatch):
    monkeypatch.setattr(prm_module, "_has_ompl", False)
    with pytest.raises(ImportError, match=r"torchrl_silp\[planning\]"):
        PRMPlanner(model, 0.1)


def test_the_baseline_knows_no_env_class():
    source = (Path(prm_module.__file__)).read_text()
    assert "UR5eReachEnv" not in source and "[:, :3]" not in source


# ------------------------------------------------------------- (e) recipe
def recipe_and_config(*overrides: str):
    """recipes/prm.py imported in-process, and its hydra config composed with ``overrides``."""
    from torchrl_silp.recipes import prm as recipe
    from torchrl_silp.recipes.schema import load_config

    return recipe, load_config("prm", overrides)


def test_recipe_writes_a_summary_consistent_with_evaluate_prm(tmp_path):
    run_dir = tmp_path / "run"
    recipe, cfg = recipe_and_config("budget_s=0.3", "eval.n_tasks=20", "threads=1", "progress=false",
                                    f"run_dir={run_dir}")
    returned = recipe.run(cfg)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary == json.loads(json.dumps(returned))
    assert summary["method"] == "prm" and summary["budget_s"] == 0.3 and summary["seed"] == 0
    assert summary["train_wall_s"] is None and summary["episodes"] == 0 and summary["frames"] == 0
    assert 0.0 <= summary["success_rate"] <= summary["solved_rate"] <= 1.0
    assert within_budget(summary["planning_time_max_s"], 0.3)
    assert summary["rollout_time_per_episode_s"] >= summary["planning_time_s"] > 0
    assert json.loads((run_dir / "history.json").read_text()) == {"history": []}
    assert "budget_s: 0.3" in (run_dir / "config.yaml").read_text()
    # the same tasks planned directly: a timed planner may differ on a task or two
    direct = evaluate_prm(UR5eReach(), 0.3, n_tasks=20, ompl_seed=0)
    assert abs(direct["success_rate"] - summary["success_rate"]) <= 0.15
    assert abs(direct["solved_rate"] - summary["solved_rate"]) <= 0.15


@pytest.mark.parametrize("override,name", [("budget_s=-1", "budget_s"), ("edge_step=0", "edge_step"),
                                           ("env.task_branch=back", "env.task_branch")])
def test_recipe_rejects_bad_config(tmp_path, override, name):
    recipe, cfg = recipe_and_config(override, f"run_dir={tmp_path}")
    with pytest.raises(ValueError, match=name):
        recipe.run(cfg)
