"""Experience roadmap, graph search and planned demonstrations (SILP+ sec. 3.2-3.3), over the task model."""

import math

import networkx as nx
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv

from torchrl_silp import CollisionHandling, UR5eReachEnv
from torchrl_silp.envs import ReachEnv
from torchrl_silp.models import UR5eReach
from torchrl_silp.planning import (
    ExperienceRoadmap,
    all_pairs_distances,
    astar_paths,
    greedy_paths,
    plan_demonstrations,
    roadmap_paths,
    shortest_paths,
    split_episodes,
)

SETTINGS = settings(max_examples=10, deadline=None, derandomize=True)
STATE_KEYS = ("joint_position", "achieved_goal", "obstacle", "desired_goal")


@pytest.fixture(scope="module")
def exact_model(model):
    # the same robot, motions checked at their samples without the Lipschitz margin
    return UR5eReach(model.robot, conservative=False)


@pytest.fixture(scope="module")
def envs(model):
    # one env per collision type and batch size over one shared model, reseeded per example
    return {
        (ct, b): TransformedEnv(
            ReachEnv(model, num_envs=b, seed=0), Compose(CollisionHandling(ct), model.observation_transform())
        )
        for ct in (0, 1, 2)
        for b in (1, 3)
    }


def make_policy(model, kind: str, gen: torch.Generator, noise: float = 0.4):
    """Random actions, or a scripted one that drives the joints to the goal configuration, with noise."""

    def policy(td):
        q = td["joint_position"]
        if kind == "random":
            a = torch.rand(q.shape, generator=gen) * 2 - 1
        else:
            a = ((td["goal_joint_position"] - q) / model.action_scale).clamp(-1, 1)
            a = a + noise * torch.randn(q.shape, generator=gen)
        td["action"] = a.clamp(-1, 1)
        return td

    return policy


def rollout(env, seed: int, T: int, kind: str):
    env.set_seed(seed)
    policy = make_policy(env.base_env.model, kind, torch.Generator().manual_seed(seed))
    return env.rollout(T, policy=policy, break_when_any_done=False)


def demo_bounds(demos):
    """(first, last) index of each demonstration, split by ("next", "done")."""
    ends = demos["next", "done"].squeeze(-1).nonzero().squeeze(-1)
    starts = torch.cat([ends.new_zeros(1), ends[:-1] + 1])
    return list(zip(starts.tolist(), ends.tolist()))


def scene_of(td):
    return td.select("obstacle")


def split_count(m: torch.Tensor) -> torch.Tensor:
    """InsertNodes by hand: the power of two P with m / P <= 1 < m / (P / 2) (1 when m <= 1)."""
    return torch.exp2(torch.ceil(torch.log2(m.double())).clamp(min=0)).to(m.dtype)


def edges_holding(roadmap, demos, model):
    """For every demo transition, the candidate edges (e, i, j) whose segment i -> j it moves along
    and whose InsertNodes split gives its action: bool ``[K, N, N]`` and the episode ``[K]``."""
    obstacle = demos["obstacle"]
    match = (obstacle.unsqueeze(1) == roadmap.scene["obstacle"].unsqueeze(0)).all(-1)  # [K, E]
    assert (match.sum(1) == 1).all(), "each demo step belongs to one episode (scene)"
    ep = match.long().argmax(1)
    cfg = roadmap.config[ep]  # [K, N, D]
    a, b = cfg.unsqueeze(2), cfg.unsqueeze(1)  # [K, N, 1, D], [K, 1, N, D]
    delta = b - a
    norm2 = delta.square().sum(-1).clamp(min=1e-12)

    def along(p):
        p = p.view(-1, 1, 1, p.shape[-1])
        s = ((p - a) * delta).sum(-1) / norm2
        off = (a + s.unsqueeze(-1) * delta - p).abs().amax(-1)
        return s, off < 1e-5

    s0, on0 = along(demos["joint_position"])
    s1, on1 = along(demos["next", "joint_position"])
    A = delta / model.action_scale
    P = split_count(A.abs().amax(-1))
    want_action = A / P.unsqueeze(-1)
    act = demos["action"].view(-1, 1, 1, A.shape[-1])
    same_action = (want_action - act).abs().amax(-1) < 1e-5
    ok = (
        roadmap.candidates[ep] & on0 & on1 & (s0 > -1e-5) & (s1 < 1 + 1e-5)
        & ((s1 - s0 - 1 / P).abs() < 1e-4) & same_action
    )
    return ok, ep


episodes_strategy = dict(
    seed=st.integers(0, 2**16),
    collision_type=st.sampled_from([0, 1, 2]),
    batch=st.sampled_from([1, 3]),
    T=st.integers(8, 30),
    kind=st.sampled_from(["random", "scripted"]),
)


# ---------------------------------------------------------------- demonstrations
@SETTINGS
@given(
    **episodes_strategy,
    d=st.sampled_from([0.1, 0.15, 0.25, 0.4]),
    n_pairs=st.integers(0, 5),
    method=st.sampled_from(["exact", "greedy"]),
    goal_node=st.booleans(),
)
def test_demonstrations_are_valid_mdp_transitions(
    model, exact_model, envs, seed, collision_type, batch, T, kind, d, n_pairs, method, goal_node
):
    env = envs[(collision_type, batch)]
    episodes = rollout(env, seed, T, kind)
    step = 0.02
    demos = plan_demonstrations(
        model, episodes, d=d, n_pairs=n_pairs, step_size=step, method=method, goal_node=goal_node,
        generator=torch.Generator().manual_seed(seed),
    )
    assert demos.batch_dims == 1
    if len(demos) == 0:
        return
    s0, s1, act = demos.select(*STATE_KEYS), demos["next"].select(*STATE_KEYS), demos["action"]
    assert demos["is_demo"].all()
    # every action within the action space
    assert (act.abs() <= 1.0).all()
    # the networks' input is the model's flat observation of the named state (the default transform)
    assert torch.equal(demos["observation"], model.observation(s0))
    assert torch.equal(demos["next", "observation"], model.observation(s1))
    # the achieved goal is the FK of the configuration; scene and goal stay
    torch.testing.assert_close(s0["achieved_goal"], model.robot.fk(s0["joint_position"]), atol=1e-5, rtol=0)
    torch.testing.assert_close(s1["achieved_goal"], model.robot.fk(s1["joint_position"]), atol=1e-5, rtol=0)
    assert torch.equal(s0["obstacle"], s1["obstacle"]) and torch.equal(s0["desired_goal"], s1["desired_goal"])
    # rewards and flags: a collision-free step scored by the goal distance, as the model scores it
    assert not demos["next", "collision"].any() and not demos["next", "collision_reason"].any()
    dist = (s1["achieved_goal"] - s1["desired_goal"]).norm(dim=-1, keepdim=True)
    hand = torch.where(dist < model.success_distance, 1.0, -dist)
    torch.testing.assert_close(demos["next", "reward"], hand)
    assert torch.equal(demos["next", "success"], dist < model.success_distance)
    reward, collision, success, _ = model.outcome(s0, s1)
    torch.testing.assert_close(demos["next", "reward"], reward)
    assert not collision.any() and torch.equal(demos["next", "success"], success)
    # no demo state collides, and every demo motion is free at every point: the exact check
    # on a 4x finer subdivision finds nothing (the conservative margin covers what lies between)
    assert not model.collides(s0["joint_position"], scene_of(s0)).any()
    assert not model.collides(s1["joint_position"], scene_of(s0)).any()
    assert exact_model.segment_collision_free(
        s0["joint_position"], s1["joint_position"], scene_of(s0), step / 4
    ).all()
    # every step moves along a roadmap edge whose check passed, with the InsertNodes action of that edge
    roadmap = ExperienceRoadmap(model, episodes, d=d, step_size=step, lazy=True, goal_node=goal_node)
    holding, ep = edges_holding(roadmap, demos, model)
    k, i, j = holding.nonzero(as_tuple=True)
    roadmap.check_edges(ep[k], i, j)
    assert (holding & roadmap.adjacency[ep]).flatten(1).any(1).all()

    bounds = demo_bounds(demos)
    for first, last in bounds:
        n = last - first + 1
        # one goal per demo, the achieved goal of its goal node's configuration, reached on the last step only
        goal = demos["desired_goal"][first]
        assert torch.equal(demos["desired_goal"][first : last + 1], goal.expand(n, 3))
        goal_q = demos["goal_joint_position"][first]
        assert torch.equal(demos["goal_joint_position"][first : last + 1], goal_q.expand(n, 3))
        torch.testing.assert_close(model.robot.fk(goal_q), goal, atol=1e-5, rtol=0)
        assert demos["next", "success"][last].item() and demos["next", "terminated"][last].item()
        assert not demos["next", "success"][first:last].any()
        assert not demos["next", "done"][first:last].any()
        # consecutive steps chain: a step starts where the previous one ended
        torch.testing.assert_close(
            demos["joint_position"][first + 1 : last + 1], demos["next", "joint_position"][first:last], atol=1e-5, rtol=0
        )
    assert not demos["next", "truncated"].any()
    assert torch.equal(demos["next", "done"], demos["next", "terminated"])
    assert not (demos["done"] | demos["terminated"] | demos["collision"]).any()

    # the env, replaying each demo's actions from the demo's first state, reproduces its states and
    # rewards (all demos in lock-step, the stateless env stepped from the demos' named states)
    first = torch.tensor([a for a, _ in bounds])
    last = torch.tensor([b for _, b in bounds])
    length = last - first + 1
    replay = TransformedEnv(ReachEnv(model, num_envs=len(bounds)), model.observation_transform())
    td = demos[first].select(*STATE_KEYS, "goal_joint_position")
    td["step_count"] = torch.zeros(len(bounds), 1, dtype=torch.long)
    for t in range(int(length.max())):
        row = torch.minimum(first + t, last)
        live = length > t
        td["action"] = act[row]
        nxt = replay.step(td)["next"]
        for key in (*STATE_KEYS, "observation", "reward"):
            torch.testing.assert_close(nxt[key][live], demos["next", key][row[live]], atol=1e-5, rtol=0)
        for key in ("success", "collision", "terminated", "done"):
            assert torch.equal(nxt[key][live], demos["next", key][row[live]]), key
        td = nxt.select(*STATE_KEYS, "goal_joint_position", "step_count")


def test_demonstrations_have_the_rollout_keys_and_dtypes(model, envs):
    env = envs[(2, 3)]
    episodes = rollout(env, 1, 30, "random")
    demos = plan_demonstrations(model, episodes, n_pairs=3, generator=torch.Generator().manual_seed(0))
    assert len(demos) > 0
    # everything a rollout holds but the env's step counter, plus the demo flag
    rollout_keys = set(episodes.keys(True, True)) - {"step_count", ("next", "step_count")}
    assert set(demos.keys(True, True)) == rollout_keys | {"is_demo"}
    for key in rollout_keys:
        assert demos[key].dtype == episodes[key].dtype, key
        assert demos[key].shape[1:] == episodes[key].shape[2:], key
    assert demos["is_demo"].shape == (len(demos), 1) and demos["is_demo"].dtype == torch.bool


def test_insert_nodes_halves_long_edges(model, envs):
    # d = 0.4 joins nodes several action units apart: their edges must be split
    env = envs[(2, 3)]
    episodes = rollout(env, 3, 30, "random")
    roadmap = ExperienceRoadmap(model, episodes, d=0.4)
    ep, s, g = roadmap.queries(6, torch.Generator().manual_seed(0))
    paths = roadmap_paths(roadmap, ep, s, g)
    demos = plan_demonstrations(model, episodes, d=0.4, n_pairs=6, generator=torch.Generator().manual_seed(0))
    e = ep.unsqueeze(-1)
    a, b = paths.nodes[:, :-1], paths.nodes[:, 1:]
    units = (roadmap.config[e, b] - roadmap.config[e, a]).abs().amax(-1) / model.action_scale
    assert units[paths.found].max() > 2  # the scenario has edges that need halving twice
    # InsertNodes adds steps: more transitions than path edges
    n_edges = int((paths.length[paths.found] - 1).sum())
    assert len(demos) > n_edges
    # every action is its edge's action over the smallest power of two that brings it within [-1, 1]
    holding, _ = edges_holding(roadmap, demos, model)
    assert holding.flatten(1).any(1).all()
    # so the largest joint of a step is more than half a unit, or the whole (short) edge
    biggest = demos["action"].abs().amax(-1)
    assert (biggest <= 1).all() and (biggest > 0.5 - 1e-6).float().mean() > 0.5


def alg2_steps(q_from, q_to, scale):
    """The paper's Alg. 2 for one edge, literally, on plain floats: the (configuration, action) of each step."""

    def f_a(s, s2):
        return [(b - a) / c for a, b, c in zip(s, s2, scale)]

    def f_s(s, a):
        return [x + u * c for x, u, c in zip(s, a, scale)]

    def inside(a):
        return max(abs(u) for u in a) <= 1.0

    def insert_nodes(s, a):
        a = [u / 2 for u in a]
        while not inside(a):
            a = [u / 2 for u in a]
        return f_s(s, a), a

    steps, s, a = [], list(q_from), f_a(q_from, q_to)
    while not inside(a):
        s2, a2 = insert_nodes(s, a)
        steps.append((s, a2))
        s = s2
        a = f_a(s, q_to)
    steps.append((s, a))
    return steps


@SETTINGS
@given(m=st.lists(st.floats(0.0, 12.0), min_size=1, max_size=20))
def test_halving_pieces_are_the_papers_alg2(m):
    from torchrl_silp.planning.demos import _edge_pieces

    m = torch.tensor(m, dtype=torch.float64)
    edge, start, length = _edge_pieces(m, "halving")
    for e, size in enumerate(m.tolist()):
        want = alg2_steps([0.0], [size], [1.0])
        got = edge == e
        if size == 0:
            assert int(got.sum()) == 1 and float(length[got]) == 0
            continue
        assert int(got.sum()) == len(want)
        torch.testing.assert_close(start[got] * size, torch.tensor([q[0] for q, _ in want], dtype=m.dtype))
        torch.testing.assert_close(length[got] * size, torch.tensor([a[0] for _, a in want], dtype=m.dtype))


def test_insert_nodes_halving_gives_the_papers_steps(model, envs):
    # the d = 0.4 scenario above; every demonstration is a prefix of its path's Alg. 2 steps, in order
    episodes = rollout(envs[(2, 3)], 3, 30, "random")
    gen = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    roadmap = ExperienceRoadmap(model, episodes, d=0.4)
    ep, s, g = roadmap.queries(6, gen(), own_query=True)
    paths = roadmap_paths(roadmap, ep, s, g)
    demos = plan_demonstrations(model, episodes, d=0.4, n_pairs=6, generator=gen(), insert_nodes="halving")
    equal = plan_demonstrations(model, episodes, d=0.4, n_pairs=6, generator=gen())
    scale = [float(model.action_scale)] * roadmap.config.shape[-1]
    wanted = []
    for i in paths.found.nonzero().squeeze(-1).tolist():
        nodes = paths.nodes[i, : int(paths.length[i])].tolist()
        cfg = roadmap.config[ep[i]].double().tolist()
        wanted.append([st for a, b in zip(nodes[:-1], nodes[1:]) for st in alg2_steps(cfg[a], cfg[b], scale)])
    bounds = demo_bounds(demos)
    assert bounds and len(bounds) == len(demo_bounds(equal))
    # the same paths, cut differently
    assert len(demos) != len(equal) or not torch.allclose(demos["action"], equal["action"])
    path = 0
    for first, last in bounds:
        q, a = demos["joint_position"][first:last + 1].double(), demos["action"][first:last + 1].double()
        while not torch.allclose(torch.tensor(wanted[path][0][0], dtype=q.dtype), q[0], atol=1e-5):
            path += 1  # a path whose demonstration was dropped (a colliding step)
        want = wanted[path][: len(q)]
        assert len(want) == len(q)
        torch.testing.assert_close(q, torch.tensor([w[0] for w in want], dtype=q.dtype), atol=1e-5, rtol=0)
        torch.testing.assert_close(a, torch.tensor([w[1] for w in want], dtype=q.dtype), atol=1e-5, rtol=0)
        path += 1
    assert (demos["action"].abs() <= 1).all()


def test_a_single_node_gives_no_queries_and_no_demonstrations(model, envs):
    env = envs[(2, 1)]
    env.set_seed(0)
    # one step that stays put: the next state repeats the first, so the roadmap has one node
    episodes = env.rollout(1, policy=lambda td: td.set("action", torch.zeros(1, 3)))
    roadmap = ExperienceRoadmap(model, episodes)
    assert roadmap.num_nodes.tolist() == [1]
    assert all(x.numel() == 0 for x in roadmap.queries(3, torch.Generator().manual_seed(0)))
    demos = plan_demonstrations(model, episodes, n_pairs=3)
    assert demos.batch_size == (0,)


# ---------------------------------------------------------------- roadmap
def hand_nodes(episodes):
    """Per episode: its first state, then its collision-free next states, exact repeats dropped; and its rows."""
    _, episode = split_episodes(episodes)
    ep = episode.reshape(-1)
    flat = episodes.reshape(-1)
    q0, q1 = flat["joint_position"], flat["next", "joint_position"]
    free = ~flat["next", "collision"].squeeze(-1)
    nodes, rows_of = [], []
    for e in range(int(ep.max()) + 1):
        rows = (ep == e).nonzero().squeeze(-1)
        unique = []
        for s in [q0[rows[0]]] + list(q1[rows][free[rows]]):
            if not any(torch.equal(s, u) for u in unique):
                unique.append(s)
        nodes.append(unique)
        rows_of.append(rows)
    return nodes, rows_of


def test_repeated_states_are_one_node(model, envs):
    env = envs[(2, 1)]
    env.set_seed(4)
    gen = torch.Generator().manual_seed(4)
    calls = []

    def policy(td):
        calls.append(None)
        # every third action is zero: the arm stays, and the state it stays in is one node
        td["action"] = (torch.rand(1, 3, generator=gen) * 2 - 1) * float(len(calls) % 3 != 0)
        return td

    episodes = env.rollout(24, policy=policy, break_when_any_done=False)
    roadmap = ExperienceRoadmap(model, episodes, lazy=True)
    nodes, _ = hand_nodes(episodes)
    free = int((~episodes["next", "collision"]).sum())
    assert sum(len(u) for u in nodes) < len(nodes) + free  # the scenario has repeats
    assert roadmap.num_nodes.tolist() == [len(u) for u in nodes]
    for e, unique in enumerate(nodes):
        assert torch.equal(roadmap.config[e, : len(unique)], torch.stack(unique))


@settings(max_examples=6, deadline=None, derandomize=True)
@given(**episodes_strategy, d=st.sampled_from([0.1, 0.2, 0.4]))
def test_roadmap_nodes_and_edges(model, envs, seed, collision_type, batch, T, kind, d):
    env = envs[(collision_type, batch)]
    episodes = rollout(env, seed, T, kind)
    roadmap = ExperienceRoadmap(model, episodes, d=d)
    assert roadmap.q is roadmap.config and roadmap.tcp is roadmap.achieved_goal
    flat = episodes.reshape(-1)
    nodes, rows_of = hand_nodes(episodes)
    assert roadmap.num_episodes == len(nodes)
    for e, unique in enumerate(nodes):
        rows = rows_of[e]
        n = int(roadmap.num_nodes[e])
        assert n == len(unique)
        assert torch.equal(roadmap.config[e, :n], torch.stack(unique))
        assert not roadmap.mask[e, n:].any()
        torch.testing.assert_close(roadmap.achieved_goal[e, :n], model.robot.fk(roadmap.config[e, :n]), atol=1e-5, rtol=0)
        # the episode's scene and goal, and whether it reached the goal
        assert torch.equal(roadmap.scene["obstacle"][e], flat["obstacle"][rows[0]])
        assert torch.equal(roadmap.goal[e], flat["desired_goal"][rows[0]])
        assert bool(roadmap.reached[e]) == bool(flat["next", "success"][rows].any())
        scene = roadmap.scene[e : e + 1].expand(n)
        assert not model.collides(roadmap.config[e, :n], scene).any()
        # candidates: node pairs within d of each other
        dist = torch.cdist(roadmap.achieved_goal[e, :n], roadmap.achieved_goal[e, :n])
        want = (dist <= d) & ~torch.eye(n, dtype=torch.bool)
        assert torch.equal(roadmap.candidates[e, :n, :n], want)
        assert not roadmap.candidates[e, n:].any() and not roadmap.candidates[e, :, n:].any()
    adj = roadmap.adjacency
    assert torch.equal(adj, adj.transpose(1, 2))
    assert (roadmap.distance[adj] <= d).all()
    assert torch.equal(roadmap.weights[adj], roadmap.distance[adj]) and torch.isinf(roadmap.weights[~adj]).all()
    # every candidate pair was checked, and the check is the model's motion check of each edge alone
    assert torch.equal(roadmap.checked, roadmap.candidates)
    e, i, j = torch.triu(roadmap.candidates, 1).nonzero(as_tuple=True)
    pick = torch.randperm(e.numel(), generator=torch.Generator().manual_seed(seed))[:12]
    for k in pick.tolist():
        a, b = roadmap.config[e[k], i[k]].unsqueeze(0), roadmap.config[e[k], j[k]].unsqueeze(0)
        flags, _ = model.motion_collision_flags(a, b, roadmap.scene[e[k] : e[k] + 1], roadmap.step_size)
        assert bool(flags.item() == 0) == bool(adj[e[k], i[k], j[k]])


def test_episodes_split_by_done_flags_and_traj_ids():
    done = torch.tensor([[0, 0, 1, 0, 0, 1, 0], [0, 1, 0, 0, 0, 0, 0]], dtype=torch.bool).unsqueeze(-1)
    td = TensorDict({("next", "done"): done}, batch_size=[2, 7])
    starts, episode = split_episodes(td)
    assert episode.tolist() == [[0, 0, 0, 1, 1, 1, 2], [3, 3, 4, 4, 4, 4, 4]]
    assert starts.tolist() == (episode != torch.nn.functional.pad(episode, (1, 0), value=-1)[:, :-1]).tolist()
    # a collector batch that begins mid-episode and switches trajectory without a done in it
    traj = torch.tensor([[5, 5, 5, 6, 6, 6, 9], [7, 7, 8, 8, 8, 8, 8]])
    td["collector", "traj_ids"] = traj
    td["next", "done"] = torch.zeros_like(done)
    assert split_episodes(td)[1].tolist() == [[0, 0, 0, 1, 1, 1, 2], [3, 3, 4, 4, 4, 4, 4]]


def test_collector_batches_with_auto_reset(model):
    from torchrl.collectors import Collector

    # the paper's env (which holds its own model): the planner takes the env for its model
    env = UR5eReachEnv(num_envs=2, seed=0, max_steps=10)
    collector = Collector(
        env, make_policy(env.model, "scripted", torch.Generator().manual_seed(0), 0.2),
        frames_per_batch=60, total_frames=60,
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert ("collector", "traj_ids") in batch.keys(True)
    n_traj = len(torch.unique(batch["collector", "traj_ids"]))
    roadmap = ExperienceRoadmap(env, batch)
    assert roadmap.num_episodes == n_traj > 2
    demos = plan_demonstrations(env, batch, n_pairs=2, generator=torch.Generator().manual_seed(0))
    again = plan_demonstrations(env.model, batch, n_pairs=2, generator=torch.Generator().manual_seed(0))
    assert len(demos) > 0 and (demos["action"].abs() <= 1).all()
    assert (demos == again).all()


def test_lazy_roadmap_finds_the_same_paths(model, envs):
    env = envs[(2, 3)]
    episodes = rollout(env, 5, 30, "random")
    eager = ExperienceRoadmap(model, episodes, lazy=False)
    lazy = ExperienceRoadmap(model, episodes, lazy=True)
    assert not lazy.checked.any()
    ep, s, g = eager.queries(8, torch.Generator().manual_seed(0))
    a, b = roadmap_paths(eager, ep, s, g), roadmap_paths(lazy, ep, s, g)
    torch.testing.assert_close(a.cost, b.cost)
    assert torch.equal(a.found, b.found) and a.found.any()
    assert 0 < int(lazy.checked.sum()) < int(eager.checked.sum())
    # what the lazy roadmap checked agrees with the eager one
    assert torch.equal(lazy.colliding[lazy.checked], eager.colliding[lazy.checked])
    # greedy checks edges as it walks (paper's step 4) and agrees with greedy on the checked graph
    lazy2 = ExperienceRoadmap(model, episodes, lazy=True)
    assert torch.equal(roadmap_paths(lazy2, ep, s, g, "greedy").nodes, roadmap_paths(eager, ep, s, g, "greedy").nodes)


def test_queries_include_each_episodes_own_start_to_goal(model, envs):
    env = envs[(2, 3)]
    roadmap = ExperienceRoadmap(model, rollout(env, 2, 20, "scripted"))
    ep, s, g = roadmap.queries(4, torch.Generator().manual_seed(1))
    assert (s != g).all() and (g < roadmap.num_nodes[ep]).all() and (s < roadmap.num_nodes[ep]).all()
    nearest = roadmap.nearest_goal_node()
    for e in range(roadmap.num_episodes):
        n = int(roadmap.num_nodes[e])
        dist = (roadmap.achieved_goal[e, :n] - roadmap.goal[e]).norm(dim=-1)
        assert int(nearest[e]) == int(dist.argmin())
        if nearest[e] != 0:
            assert ((ep == e) & (s == 0) & (g == nearest[e])).any()
    # seeded: the same draw twice
    again = roadmap.queries(4, torch.Generator().manual_seed(1))
    assert all(torch.equal(x, y) for x, y in zip((ep, s, g), again))
    # the paper's queries: the same random pairs without the episodes' own
    ep_p, s_p, g_p = roadmap.queries(4, torch.Generator().manual_seed(1), own_query=False)
    own = (s == 0) & (g == nearest[ep])
    for e in range(roadmap.num_episodes):
        mine, paper = (ep == e), (ep_p == e)
        # the own query comes first in an episode's group; the random pairs follow in the same order
        first_random = 1 if bool(own[mine][:1].any()) else 0
        assert torch.equal(s[mine][first_random:], s_p[paper]) and torch.equal(g[mine][first_random:], g_p[paper])
    assert int(paper_count := ep_p.numel()) <= 4 * roadmap.num_episodes and paper_count == ep.numel() - int(
        sum(bool(own[ep == e][:1].any()) for e in range(roadmap.num_episodes)))
    assert roadmap.queries(0, own_query=False)[0].numel() == 0


@settings(max_examples=6, deadline=None, derandomize=True)
@given(**episodes_strategy)
def test_goal_nodes(model, envs, seed, collision_type, batch, T, kind):
    env = envs[(collision_type, batch)]
    episodes = rollout(env, seed, T, kind)
    plain = ExperienceRoadmap(model, episodes, lazy=True)
    rm = ExperienceRoadmap(model, episodes, lazy=True, goal_node=True)
    starts, episode = split_episodes(episodes)
    goal_q = episodes["goal_joint_position"].reshape(-1, 3)[starts.reshape(-1)]
    for e in range(rm.num_episodes):
        n = int(plain.num_nodes[e])
        # the visited nodes are those of the plain roadmap, in order; the goal node, if any, comes last
        torch.testing.assert_close(rm.config[e, :n], plain.config[e, :n])
        goal_nodes = rm.is_goal_node[e].nonzero().squeeze(-1).tolist()
        if goal_nodes:
            assert goal_nodes == [n] and int(rm.num_nodes[e]) == n + 1
            torch.testing.assert_close(rm.config[e, n], goal_q[e])
            torch.testing.assert_close(rm.achieved_goal[e, n], rm.goal[e])
            torch.testing.assert_close(model.robot.fk(goal_q[e]), rm.goal[e], atol=1e-5, rtol=0)
        else:  # only when the episode visited the goal configuration exactly
            assert (plain.config[e, :n] == goal_q[e]).all(-1).any()
    assert torch.equal(rm.nearest_goal_node(), plain.nearest_goal_node())
    ep, s, g = rm.queries(3, torch.Generator().manual_seed(seed))
    assert (s != g).all() and not rm.is_goal_node[ep, s].any()
    to_goal = rm.is_goal_node[ep, g]
    # one query per episode ends at its goal node, from its first state
    assert torch.equal(ep[to_goal], rm.is_goal_node.any(-1).nonzero().squeeze(-1)) and (s[to_goal] == 0).all()


def test_goal_node_demonstrations_reach_the_real_goal(model, envs):
    env = envs[(2, 3)]
    episodes = rollout(env, 5, 30, "scripted")
    demos = plan_demonstrations(model, episodes, n_pairs=0, generator=torch.Generator().manual_seed(0), goal_node=True)
    plain = plan_demonstrations(model, episodes, n_pairs=0, generator=torch.Generator().manual_seed(0))
    starts, _ = split_episodes(episodes)
    first = episodes.reshape(-1)[starts.reshape(-1)]  # each episode's first step

    def towards_real_goals(demos):
        """(first, last, episode) of the demos whose desired goal is an episode's real goal."""
        out = []
        for lo, hi in demo_bounds(demos):
            e = (first["desired_goal"] == demos["desired_goal"][lo]).all(-1).nonzero().squeeze(-1)
            if e.numel():
                out.append((lo, hi, int(e[0])))
        return out

    real = towards_real_goals(demos)
    # only the goal nodes give demonstrations towards the real goals (a visited node is never exactly on it)
    assert len(real) >= 2 and not towards_real_goals(plain)
    assert demos.shape[0] > plain.shape[0]
    for lo, hi, e in real:
        # the episode's own query: from its first state to its goal configuration, reached within success_distance
        assert torch.equal(demos["joint_position"][lo], first["joint_position"][e])
        assert torch.equal(demos["goal_joint_position"][lo], first["goal_joint_position"][e])
        dist = (demos["next", "achieved_goal"][hi] - first["desired_goal"][e]).norm()
        assert dist < model.success_distance
        assert demos["next", "success"][hi].item() and demos["next", "terminated"][hi].item()


@pytest.mark.parametrize("spread", [None, 0.5])
def test_sampled_nodes_extend_the_roadmap_with_free_configurations_near_the_experience(model, envs, spread):
    env = envs[(2, 3)]
    episodes = rollout(env, 7, 40, "scripted")
    plain = ExperienceRoadmap(model, episodes, lazy=True, goal_node=True)
    rm = ExperienceRoadmap(model, episodes, lazy=True, goal_node=True, sampled_nodes=48, sample_spread=spread,
                           generator=torch.Generator().manual_seed(0))
    reach = 2 * model.action_scale if spread is None else spread
    assert rm.num_episodes == plain.num_episodes and (rm.num_nodes > plain.num_nodes).all()
    for e in range(rm.num_episodes):
        n, m = int(plain.num_nodes[e]), int(rm.num_nodes[e])
        visited = n - int(plain.is_goal_node[e].any())
        # the visited nodes first, as without sampling; the goal node last; the sampled ones between
        torch.testing.assert_close(rm.config[e, :visited], plain.config[e, :visited])
        assert int(rm.num_visited[e]) == visited == int(plain.num_visited[e])
        assert rm.is_sampled_node[e, visited: visited + m - n].all() and int(rm.is_sampled_node[e].sum()) == m - n
        assert torch.equal(rm.is_goal_node[e, :m].nonzero().squeeze(-1), plain.is_goal_node[e, :n].nonzero().squeeze(-1) + m - n)
        sampled = rm.config[e, visited: visited + m - n]
        # free in the episode's scene, within the joint limits, within the spread of a visited state or the goal
        scene = rm.scene[e].expand(sampled.shape[0])
        assert not model.collides(sampled, scene).any()
        assert ((sampled >= model.config_low - 1e-6) & (sampled <= model.config_high + 1e-6)).all()
        anchors = plain.config[e, :n]
        nearest = (sampled.unsqueeze(1) - anchors.unsqueeze(0)).abs().amax(-1).amin(-1)
        assert (nearest <= reach + 1e-5).all()
        torch.testing.assert_close(rm.achieved_goal[e, visited: visited + m - n], model.robot.fk(sampled), atol=1e-5, rtol=0)
    # more nodes, never fewer paths: every start-to-goal query the plain roadmap solves, the extended one
    # solves at most as long (its graph holds the plain one's)
    with_goal = plain.is_goal_node.any(-1).nonzero().squeeze(-1)
    zeros = torch.zeros_like(with_goal)
    p0 = roadmap_paths(plain, with_goal, zeros, plain.num_nodes[with_goal] - 1)
    p1 = roadmap_paths(rm, with_goal, zeros, rm.num_nodes[with_goal] - 1)
    assert p0.found.any() and (p1.found | ~p0.found).all() and (p1.cost[p0.found] <= p0.cost[p0.found] + 1e-5).all()


def test_random_pairs_start_and_end_at_visited_nodes_with_sampled_nodes(model, envs):
    # the sampled nodes are waypoints: a random pair's start and goal are visited nodes of its episode
    episodes = rollout(envs[(2, 3)], 5, 40, "scripted")
    rm = ExperienceRoadmap(model, episodes, lazy=True, goal_node=True, sampled_nodes=200, sample_spread=3.0,
                           generator=torch.Generator().manual_seed(0))
    assert (rm.is_sampled_node.sum(-1) > rm.num_visited).all()  # most nodes sampled: a uniform draw would hit them
    episode, start, goal = rm.queries(50, torch.Generator().manual_seed(1), own_query=False)
    assert episode.numel() > 0
    assert (start < rm.num_visited[episode]).all() and (goal < rm.num_visited[episode]).all()
    assert not rm.is_sampled_node[episode, start].any() and not rm.is_sampled_node[episode, goal].any()


def test_demonstrations_through_sampled_nodes_replay_in_the_model(model, envs):
    episodes = rollout(envs[(2, 3)], 3, 40, "scripted")
    demos = plan_demonstrations(model, episodes, n_pairs=2, goal_node=True, sampled_nodes=48,
                                generator=torch.Generator().manual_seed(0))
    plain = plan_demonstrations(model, episodes, n_pairs=2, goal_node=True, generator=torch.Generator().manual_seed(0))
    assert demos.shape[0] > 0 and not torch.equal(demos["joint_position"][: plain.shape[0]], plain["joint_position"])
    nxt, reward, collision, success, _ = model.step(demos.select(*STATE_KEYS, "goal_joint_position"), demos["action"])
    assert not collision.any()
    torch.testing.assert_close(nxt["joint_position"], demos["next", "joint_position"], atol=1e-5, rtol=0)
    torch.testing.assert_close(reward, demos["next", "reward"], atol=1e-5, rtol=0)
    assert torch.equal(success, demos["next", "success"]) and torch.equal(success, demos["next", "terminated"])


def test_the_demonstration_yield_of_episodes_with_and_without_sampled_nodes(model, envs):
    from omegaconf import OmegaConf

    from torchrl_silp.recipes.diagnose_demos import demonstration_yield

    episodes = rollout(envs[(2, 3)], 11, 40, "scripted")
    cfg = OmegaConf.create({"planner": {"d": 0.15, "step_size": None, "method": "exact", "sample_spread": None}})
    plain = demonstration_yield(model, cfg, episodes, 0, torch.Generator().manual_seed(0))
    more = demonstration_yield(model, cfg, episodes, 64, torch.Generator().manual_seed(0))
    # one entry per env (its first episode); the extra nodes never lose a path
    assert plain["found"].shape == (3,) and torch.equal(plain["reached"], more["reached"])
    assert (more["found"] | ~plain["found"]).all()
    # a path through achieved goals is never shorter than the straight line from the start to the goal
    found = plain["found"]
    assert found.any() and (plain["stretch"][found] >= 1 - 1e-5).all() and (~plain["stretch"][~found].isfinite()).all()
    # reached: a success before each env's first episode ended
    done, success = episodes["next", "done"].squeeze(-1), episodes["next", "success"].squeeze(-1)
    end = torch.where(done.any(-1), done.float().argmax(-1), done.shape[-1] - 1)
    steps = torch.arange(done.shape[-1])
    assert torch.equal(plain["reached"], (success & (steps <= end.unsqueeze(-1))).any(-1))


# ---------------------------------------------------------------- edge checks
def test_clearance_over_lipschitz_is_a_radius_free_of_collisions(model):
    gen = torch.Generator().manual_seed(0)
    tasks = model.sample_tasks(32, generator=gen)
    # around task configurations: a mix of free and colliding ones
    q = tasks["joint_position"].repeat(64, 1) + 0.6 * torch.randn(2048, 3, generator=gen)
    scene = tasks.select("obstacle").repeat(64)
    # each reason's clearance (m) over its Lipschitz bound (m/rad): a joint-space radius (rad, max-norm)
    lipschitz = torch.tensor([model.lipschitz()[r] for r in model.collision_reasons])
    rho = (model.clearance(q, scene) / lipschitz).amin(-1)
    col = model.collides(q, scene)
    assert 0.1 < col.float().mean() < 0.9
    assert torch.equal(rho < 0, col)
    # inside the radius nothing collides
    free = (~col).nonzero().squeeze(-1)[:256]
    u = torch.rand(free.numel(), 3, generator=gen) * 2 - 1
    assert not model.collides(q[free] + u * rho[free].unsqueeze(-1), scene[free]).any()


def hand_segment_free(model, a, b, scene, h):
    """One segment: max(ceil(span / h), 1) + 1 evenly spaced samples, each checked with the model's margin."""
    n = max(math.ceil(float((b - a).abs().max()) / h - 1e-9), 1) + 1
    t = torch.linspace(0, 1, n).unsqueeze(-1)
    flags, _ = model.collision_flags(a + t * (b - a), scene.expand(n), model.motion_margin(h))
    return not bool(flags.any())


def test_segment_check_against_a_hand_subdivision(model, exact_model):
    gen = torch.Generator().manual_seed(0)
    tasks = model.sample_tasks(24, generator=gen)
    q0 = tasks["joint_position"]
    q1 = q0 + 0.4 * torch.randn(24, 3, generator=gen)
    scene = tasks.select("obstacle")
    for m in (model, exact_model):
        free = m.segment_collision_free(q0, q1, scene, 0.02)
        single = torch.tensor([hand_segment_free(m, a, b, scene[k], 0.02) for k, (a, b) in enumerate(zip(q0, q1))])
        assert torch.equal(free, single)
        assert 0 < int(free.sum()) < 24
        # the default resolution is the model's
        assert torch.equal(m.segment_collision_free(q0, q1, scene), m.segment_collision_free(q0, q1, scene, 0.01))
    # the exact check (no margin) is the collision test of each sample
    assert set(exact_model.motion_margin(0.02).values()) == {0.0}
    assert min(model.motion_margin(0.02).values()) > 0
    # conservative: a passing segment is free at every point, which an exact 8x finer subdivision confirms
    conservative = model.segment_collision_free(q0, q1, scene, 0.02)
    fine = exact_model.segment_collision_free(q0, q1, scene, 0.0025)
    assert not (conservative & ~fine).any()
    # and it is stricter than the exact check at the same resolution
    assert not (conservative & ~exact_model.segment_collision_free(q0, q1, scene, 0.02)).any()
    with pytest.raises(ValueError, match="config_from and config_to"):
        model.segment_collision_free(q0, q1[:3], scene)
    with pytest.raises(ValueError, match="resolution"):
        model.segment_collision_free(q0, q1, scene, 0.0)


# ---------------------------------------------------------------- search
def random_graphs(seed: int, E: int, N: int, p: float):
    gen = torch.Generator().manual_seed(seed)
    pos = torch.rand(E, N, 3, generator=gen, dtype=torch.float64)
    w = torch.cdist(pos, pos)
    keep = torch.rand(E, N, N, generator=gen) < p
    keep = torch.triu(keep, 1)
    keep = keep | keep.transpose(1, 2)
    w = torch.where(keep, w, math.inf)
    return pos, w


def nx_lengths(w, ep, s, g):
    out = []
    for e, a, b in zip(ep.tolist(), s.tolist(), g.tolist()):
        G = nx.Graph()
        G.add_nodes_from(range(w.shape[1]))
        i, j = torch.isfinite(w[e]).nonzero(as_tuple=True)
        G.add_weighted_edges_from((x, y, float(w[e, x, y])) for x, y in zip(i.tolist(), j.tolist()))
        try:
            out.append(nx.shortest_path_length(G, a, b, weight="weight"))
        except nx.NetworkXNoPath:
            out.append(math.inf)
    return torch.tensor(out, dtype=torch.float64)


def assert_valid(paths, w, ep, s, g):
    for q in range(ep.numel()):
        n = int(paths.length[q])
        nodes = paths.nodes[q, :n].tolist()
        assert nodes[0] == s[q]
        assert (paths.nodes[q, n:] == nodes[-1]).all()  # padding repeats the last node
        if paths.found[q]:
            assert nodes[-1] == g[q] and len(set(nodes)) == n
            cost = sum(float(w[ep[q], a, b]) for a, b in zip(nodes, nodes[1:]))
            assert math.isclose(cost, float(paths.cost[q]), rel_tol=1e-9)
        else:
            assert math.isinf(paths.cost[q])


@settings(max_examples=20, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**16), E=st.integers(1, 4), N=st.integers(2, 14), p=st.floats(0.05, 0.6))
def test_search_against_networkx(seed, E, N, p):
    pos, w = random_graphs(seed, E, N, p)
    gen = torch.Generator().manual_seed(seed)
    Q = 3 * E
    ep = torch.randint(E, (Q,), generator=gen)
    s = torch.randint(N, (Q,), generator=gen)
    g = torch.randint(N, (Q,), generator=gen)
    want = nx_lengths(w, ep, s, g)
    exact = shortest_paths(w, ep, s, g)
    star = astar_paths(w, pos, ep, s, g)
    greedy = greedy_paths(w, pos, ep, s, g)
    for paths in (exact, star):
        torch.testing.assert_close(paths.cost, want)
        assert torch.equal(paths.found, torch.isfinite(want))
        assert_valid(paths, w, ep, s, g)
    assert_valid(greedy, w, ep, s, g)
    # greedy finds a path only where one exists, never a shorter one
    assert not (greedy.found & ~exact.found).any()
    assert (exact.cost[greedy.found] <= greedy.cost[greedy.found] + 1e-9).all()
    D = all_pairs_distances(w)
    torch.testing.assert_close(D[ep, s, g], want)


def test_greedy_walk_is_the_papers_and_can_fail():
    # 0 - 1 - 2 - 3 (goal) along a detour, and 0 - 4, a dead end that looks closer to the goal
    pos = torch.tensor([[[0.0, 0, 0], [0, 1, 0], [1, 1, 0], [1.5, 0, 0], [0.9, 0, 0]]], dtype=torch.float64)
    w = torch.full((1, 5, 5), math.inf, dtype=torch.float64)
    for a, b in ((0, 1), (1, 2), (2, 3), (0, 4)):
        w[0, a, b] = w[0, b, a] = float((pos[0, a] - pos[0, b]).norm())
    one = torch.zeros(1, dtype=torch.long)
    greedy = greedy_paths(w, pos, one, one, one + 3)
    assert greedy.nodes[0, :2].tolist() == [0, 4] and not greedy.found.item()
    exact = shortest_paths(w, one, one, one + 3)
    assert exact.nodes[0].tolist()[:4] == [0, 1, 2, 3] and exact.found.item()


@settings(max_examples=8, deadline=None, derandomize=True)
@given(**episodes_strategy, d=st.sampled_from([0.1, 0.15, 0.3]))
def test_exact_never_longer_than_greedy_on_roadmaps(model, envs, seed, collision_type, batch, T, kind, d):
    env = envs[(collision_type, batch)]
    roadmap = ExperienceRoadmap(model, rollout(env, seed, T, kind), d=d, lazy=True)
    ep, s, g = roadmap.queries(6, torch.Generator().manual_seed(seed))
    exact = roadmap_paths(roadmap, ep, s, g, "exact")
    greedy = roadmap_paths(roadmap, ep, s, g, "greedy")
    assert not (greedy.found & ~exact.found).any()
    assert (exact.cost[greedy.found] <= greedy.cost[greedy.found] + 1e-5).all()
    # against networkx on the edges checked so far, then on the fully checked roadmap
    roadmap.check_edges()
    want = nx_lengths(roadmap.weights.double(), ep, s, g)
    torch.testing.assert_close(exact.cost.double(), want, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------- configuration errors
def test_bad_arguments_raise(model, envs):
    env = envs[(2, 1)]
    episodes = rollout(env, 0, 5, "random")
    with pytest.raises(ValueError, match="d must be"):
        plan_demonstrations(model, episodes, d=0.0)
    with pytest.raises(ValueError, match="d must be"):
        ExperienceRoadmap(model, episodes, d=-1)
    with pytest.raises(ValueError, match="n_pairs must be"):
        plan_demonstrations(model, episodes, n_pairs=-1)
    with pytest.raises(ValueError, match="method must be one of"):
        plan_demonstrations(model, episodes, method="astar")
    with pytest.raises(ValueError, match="step_size must be"):
        plan_demonstrations(model, episodes, step_size=0)
    with pytest.raises(ValueError, match="episodes must"):
        ExperienceRoadmap(model, episodes.exclude(("next", "done")))
    with pytest.raises(ValueError, match="joint_position"):
        ExperienceRoadmap(model, episodes.exclude(("next", "joint_position")))
    with pytest.raises(ValueError, match="goal_joint_position"):
        ExperienceRoadmap(model, episodes.exclude("goal_joint_position"), goal_node=True)
    with pytest.raises(TypeError, match="TaskModel"):
        ExperienceRoadmap(object(), episodes)
    with pytest.raises(ValueError, match="weights must"):
        shortest_paths(torch.zeros(3, 3), *(torch.zeros(1, dtype=torch.long),) * 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_planning_on_cuda():
    env = UR5eReachEnv(num_envs=4, seed=0, device="cuda")
    episodes = env.rollout(30, break_when_any_done=False)
    demos = plan_demonstrations(env.model, episodes, generator=torch.Generator("cuda").manual_seed(0))
    assert demos.device.type == "cuda" and demos["observation"].is_cuda
    assert (demos["action"].abs() <= 1).all()
