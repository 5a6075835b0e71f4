"""Experience roadmap, graph search and planned demonstrations (SILP+ sec. 3.2-3.3)."""

import math

import networkx as nx
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from torchrl_silp import UR5eReachEnv
from torchrl_silp.planning import (
    ExperienceRoadmap,
    all_pairs_distances,
    astar_paths,
    clearance_radius,
    greedy_paths,
    plan_demonstrations,
    roadmap_paths,
    segment_collision_free,
    shortest_paths,
    split_episodes,
)

SETTINGS = settings(max_examples=12, deadline=None, derandomize=True)


@pytest.fixture(scope="module")
def envs():
    # one env per collision type and batch size, reseeded per example (building one parses the URDF)
    return {(ct, b): UR5eReachEnv(num_envs=b, seed=0, collision_type=ct) for ct in (0, 1, 2) for b in (1, 3)}


def make_policy(kind: str, gen: torch.Generator, noise: float = 0.4):
    """Random actions, or a scripted one that drives the joints to goal_q, with noise."""

    def policy(td):
        q = td["observation"][..., :3]
        if kind == "random":
            a = torch.rand(q.shape, generator=gen) * 2 - 1
        else:
            a = ((td["goal_q"] - q) / UR5eReachEnv.ACTION_SCALE).clamp(-1, 1)
            a = a + noise * torch.randn(q.shape, generator=gen)
        td["action"] = a.clamp(-1, 1)
        return td

    return policy


def rollout(env, seed: int, T: int, kind: str):
    env.set_seed(seed)
    return env.rollout(T, policy=make_policy(kind, torch.Generator().manual_seed(seed)), break_when_any_done=False)


def demo_bounds(demos):
    """(first, last) index of each demonstration, split by ("next", "done")."""
    ends = demos["next", "done"].squeeze(-1).nonzero().squeeze(-1)
    starts = torch.cat([ends.new_zeros(1), ends[:-1] + 1])
    return list(zip(starts.tolist(), ends.tolist()))


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
    certify=st.booleans(),
)
def test_demonstrations_are_valid_mdp_transitions(envs, seed, collision_type, batch, T, kind, d, n_pairs, method, certify):
    env = envs[(collision_type, batch)]
    episodes = rollout(env, seed, T, kind)
    step = 0.02
    demos = plan_demonstrations(
        env, episodes, d=d, n_pairs=n_pairs, step_size=step, method=method, certify=certify,
        generator=torch.Generator().manual_seed(seed),
    )
    assert demos.batch_dims == 1
    if len(demos) == 0:
        return
    obs, act, nxt = demos["observation"], demos["action"], demos["next", "observation"]
    # every action within the action space
    assert (act.abs() <= 1.0).all()
    # rewards and flags are the env's
    reward, collision, success, _ = env.outcome(obs, nxt)
    torch.testing.assert_close(demos["next", "reward"], env.reward(obs, nxt))
    assert torch.equal(demos["next", "success"], success)
    # no demo state collides (start states and next states)
    assert not collision.any()
    assert not env.collides(obs[:, :3], obs[:, 6:12]).any()
    assert not env.collides(nxt[:, :3], obs[:, 6:12]).any()
    if certify:
        # certified edges are free at every point: a 4x finer subdivision finds nothing
        assert env.edge_collision_free(obs[:, :3], nxt[:, :3], obs[:, 6:12], step_size=step / 4).all()
    assert demos["is_demo"].all()
    bounds = demo_bounds(demos)
    # replaying each demo's actions from its first state reproduces its next observations
    # (all demos in lock-step, one env.transition per step)
    first = torch.tensor([a for a, _ in bounds])
    length = torch.tensor([b - a + 1 for a, b in bounds])
    state = obs[first]
    for t in range(int(length.max())):
        live = (length > t).nonzero().squeeze(-1)
        state[live] = env.transition(state[live], act[first[live] + t])
        assert (state[live] - nxt[first[live] + t]).abs().max() < 1e-5
    for first, last in bounds:
        # one goal per demo, the TCP of its goal node (goal_q), reached on the last step only
        goal = obs[first, 12:15]
        assert torch.equal(obs[first : last + 1, 12:15], goal.expand(last - first + 1, 3))
        assert torch.equal(nxt[first : last + 1, 12:15], goal.expand(last - first + 1, 3))
        torch.testing.assert_close(env.robot.fk(demos["goal_q"][first]), goal, atol=1e-5, rtol=0)
        assert demos["next", "success"][last].item() and demos["next", "terminated"][last].item()
        assert not demos["next", "success"][first:last].any()
        assert not demos["next", "done"][first:last].any()
    assert not demos["next", "truncated"].any()
    torch.testing.assert_close(demos["next", "done"], demos["next", "terminated"])


def test_demonstrations_have_the_rollout_keys_and_dtypes(envs):
    env = envs[(2, 3)]
    episodes = rollout(env, 1, 30, "random")
    demos = plan_demonstrations(env, episodes, n_pairs=3, generator=torch.Generator().manual_seed(0))
    assert len(demos) > 0
    want = set(episodes.keys(True, True)) | {"is_demo"}
    assert set(demos.keys(True, True)) == want
    for key in episodes.keys(True, True):
        assert demos[key].dtype == episodes[key].dtype, key
        assert demos[key].shape[1:] == episodes[key].shape[2:], key
    assert demos["is_demo"].shape == (len(demos), 1) and demos["is_demo"].dtype == torch.bool


def test_insert_nodes_halves_long_edges(envs):
    # d = 0.4 joins nodes several action units apart: their edges must be split
    env = envs[(2, 3)]
    episodes = rollout(env, 3, 30, "random")
    roadmap = ExperienceRoadmap(env, episodes, d=0.4)
    ep, s, g = roadmap.queries(6, torch.Generator().manual_seed(0))
    paths = roadmap_paths(roadmap, ep, s, g)
    demos = plan_demonstrations(env, episodes, d=0.4, n_pairs=6, generator=torch.Generator().manual_seed(0))
    e = ep.unsqueeze(-1)
    a, b = paths.nodes[:, :-1], paths.nodes[:, 1:]
    units = (roadmap.q[e, b] - roadmap.q[e, a]).abs().amax(-1) / env.ACTION_SCALE
    assert units.max() > 1  # the scenario has long edges
    # InsertNodes adds steps: more transitions than path edges
    n_edges = int((paths.length[paths.found] - 1).sum())
    assert len(demos) > n_edges
    assert (demos["action"].abs() <= 1).all()
    # halving: every |action| is an edge's |action| over a power of two, so at least half a unit
    # on the longest joint of each step, or the whole (short) edge
    biggest = demos["action"].abs().amax(-1)
    assert (biggest > 0.5 - 1e-6).float().mean() > 0.5


def test_empty_queries_give_an_empty_tensordict(envs):
    env = envs[(2, 1)]
    episodes = rollout(env, 0, 1, "random")[..., :1]
    demos = plan_demonstrations(env, episodes, n_pairs=0)
    assert demos.batch_size == (0,)


# ---------------------------------------------------------------- roadmap
@settings(max_examples=8, deadline=None, derandomize=True)
@given(**episodes_strategy, d=st.sampled_from([0.1, 0.2, 0.4]))
def test_roadmap_nodes_and_edges(envs, seed, collision_type, batch, T, kind, d):
    env = envs[(collision_type, batch)]
    episodes = rollout(env, seed, T, kind)
    roadmap = ExperienceRoadmap(env, episodes, d=d)
    starts, episode = split_episodes(episodes)
    assert roadmap.num_episodes == int(episode.max()) + 1
    ep = episode.reshape(-1)
    obs = episodes["observation"].reshape(-1, 15)[:, :3]
    nxt = episodes["next", "observation"].reshape(-1, 15)[:, :3]
    free = ~episodes["next", "collision"].reshape(-1)
    for e in range(roadmap.num_episodes):
        rows = (ep == e).nonzero().squeeze(-1)
        # the first state, then the collision-free next states, exact repeats dropped
        states = [obs[rows[0]]] + list(nxt[rows][free[rows]])
        unique = []
        for s in states:
            if not any(torch.equal(s, u) for u in unique):
                unique.append(s)
        n = int(roadmap.num_nodes[e])
        assert n == len(unique)
        assert torch.equal(roadmap.q[e, :n], torch.stack(unique))
        assert not roadmap.mask[e, n:].any()
        assert not env.collides(roadmap.q[e, :n], roadmap.obstacle[e]).any()
    adj = roadmap.adjacency
    assert torch.equal(adj, adj.transpose(1, 2))
    assert (roadmap.distance[adj] <= d).all()
    # every candidate pair was checked, and the check is env.edge_collision_free on each edge alone
    assert torch.equal(roadmap.checked, roadmap.candidates)
    e, i, j = torch.triu(roadmap.candidates, 1).nonzero(as_tuple=True)
    pick = torch.randperm(e.numel(), generator=torch.Generator().manual_seed(seed))[:12]
    for k in pick.tolist():
        single = env.edge_collision_free(roadmap.q[e[k], i[k]], roadmap.q[e[k], j[k]], roadmap.obstacle[e[k]], 0.02)
        assert bool(single) == bool(adj[e[k], i[k], j[k]])


def test_episodes_split_by_done_flags_and_traj_ids():
    done = torch.tensor([[0, 0, 1, 0, 0, 1, 0], [0, 1, 0, 0, 0, 0, 0]], dtype=torch.bool).unsqueeze(-1)
    td = TensorDict({("next", "done"): done}, batch_size=[2, 7])
    starts, episode = split_episodes(td)
    assert episode.tolist() == [[0, 0, 0, 1, 1, 1, 2], [3, 3, 4, 4, 4, 4, 4]]
    # a collector batch that begins mid-episode and switches trajectory without a done in it
    traj = torch.tensor([[5, 5, 5, 6, 6, 6, 9], [7, 7, 8, 8, 8, 8, 8]])
    td["collector", "traj_ids"] = traj
    td["next", "done"] = torch.zeros_like(done)
    assert split_episodes(td)[1].tolist() == [[0, 0, 0, 1, 1, 1, 2], [3, 3, 4, 4, 4, 4, 4]]


def test_collector_batches_with_auto_reset(envs):
    from torchrl.collectors import Collector

    env = UR5eReachEnv(num_envs=2, seed=0, max_steps=10)
    collector = Collector(
        env, make_policy("scripted", torch.Generator().manual_seed(0), 0.2), frames_per_batch=60, total_frames=60
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert ("collector", "traj_ids") in batch.keys(True)
    n_traj = len(torch.unique(batch["collector", "traj_ids"]))
    roadmap = ExperienceRoadmap(env, batch)
    assert roadmap.num_episodes == n_traj > 2
    demos = plan_demonstrations(env, batch, n_pairs=2, generator=torch.Generator().manual_seed(0))
    assert len(demos) > 0 and (demos["action"].abs() <= 1).all()


def test_lazy_roadmap_finds_the_same_paths(envs):
    env = envs[(2, 3)]
    episodes = rollout(env, 5, 30, "random")
    eager = ExperienceRoadmap(env, episodes, lazy=False)
    lazy = ExperienceRoadmap(env, episodes, lazy=True)
    ep, s, g = eager.queries(8, torch.Generator().manual_seed(0))
    a, b = roadmap_paths(eager, ep, s, g), roadmap_paths(lazy, ep, s, g)
    torch.testing.assert_close(a.cost, b.cost)
    assert torch.equal(a.found, b.found)
    assert int(lazy.checked.sum()) < int(eager.checked.sum())
    # greedy checks edges as it walks (paper's step 4) and agrees with greedy on the checked graph
    lazy2 = ExperienceRoadmap(env, episodes, lazy=True)
    assert torch.equal(roadmap_paths(lazy2, ep, s, g, "greedy").nodes, roadmap_paths(eager, ep, s, g, "greedy").nodes)


def test_queries_include_each_episodes_own_start_to_goal(envs):
    env = envs[(2, 3)]
    roadmap = ExperienceRoadmap(env, rollout(env, 2, 20, "scripted"))
    ep, s, g = roadmap.queries(4, torch.Generator().manual_seed(1))
    assert (s != g).all() and (g < roadmap.num_nodes[ep]).all() and (s < roadmap.num_nodes[ep]).all()
    nearest = roadmap.nearest_goal_node()
    for e in range(roadmap.num_episodes):
        if nearest[e] != 0:
            assert ((ep == e) & (s == 0) & (g == nearest[e])).any()
    # seeded: the same draw twice
    again = roadmap.queries(4, torch.Generator().manual_seed(1))
    assert all(torch.equal(x, y) for x, y in zip((ep, s, g), again))


@SETTINGS
@given(**episodes_strategy)
def test_goal_nodes(envs, seed, collision_type, batch, T, kind):
    env = envs[(collision_type, batch)]
    episodes = rollout(env, seed, T, kind)
    plain = ExperienceRoadmap(env, episodes, lazy=True)
    rm = ExperienceRoadmap(env, episodes, lazy=True, goal_node=True)
    starts, episode = split_episodes(episodes)
    goal_q = episodes["goal_q"].reshape(-1, 3)[starts.reshape(-1)]
    for e in range(rm.num_episodes):
        n = int(plain.num_nodes[e])
        # the visited nodes are those of the plain roadmap, in order; the goal node, if any, comes last
        torch.testing.assert_close(rm.q[e, :n], plain.q[e, :n])
        goal_nodes = rm.is_goal_node[e].nonzero().squeeze(-1).tolist()
        if goal_nodes:
            assert goal_nodes == [n] and int(rm.num_nodes[e]) == n + 1
            torch.testing.assert_close(rm.q[e, n], goal_q[e])
            torch.testing.assert_close(rm.tcp[e, n], rm.goal[e])
        else:  # only when the episode visited the goal configuration exactly
            assert (plain.q[e, :n] == goal_q[e]).all(-1).any()
    assert torch.equal(rm.nearest_goal_node(), plain.nearest_goal_node())
    ep, s, g = rm.queries(3, torch.Generator().manual_seed(seed))
    assert (s != g).all() and not rm.is_goal_node[ep, s].any()
    to_goal = rm.is_goal_node[ep, g]
    # one query per episode ends at its goal node, from its first state
    assert torch.equal(ep[to_goal], rm.is_goal_node.any(-1).nonzero().squeeze(-1)) and (s[to_goal] == 0).all()


def test_goal_node_demonstrations_reach_the_real_goal(envs):
    env = envs[(2, 3)]
    episodes = rollout(env, 5, 30, "scripted")
    gen = torch.Generator().manual_seed(0)
    demos = plan_demonstrations(env, episodes, n_pairs=0, generator=gen, goal_node=True)
    plain = plan_demonstrations(env, episodes, n_pairs=0, generator=torch.Generator().manual_seed(0))
    goals = episodes["observation"][:, 0, 12:15]
    reached = []
    for lo, hi in demo_bounds(demos):
        obs, last = demos["observation"][lo:hi + 1], demos["next", "observation"][hi]
        assert demos["next", "success"][hi].item() and demos["next", "terminated"][hi].item()
        real = (goals == obs[0, 12:15]).all(-1).any()
        # a demo towards the real goal ends on the goal configuration itself
        reached.append(bool(real) and bool((last[:3] == demos["goal_q"][lo]).all()))
    assert any(reached)
    assert demos.shape[0] > plain.shape[0]


def test_clearance_radius_agrees_with_the_env_collision_check(envs):
    env = envs[(2, 1)]
    gen = torch.Generator().manual_seed(0)
    tasks = env.sample_tasks(32, generator=gen)
    # around task configurations: a mix of free and colliding ones
    q = tasks["q"].repeat(64, 1) + 0.6 * torch.randn(2048, 3, generator=gen)
    box = tasks["obstacle"].repeat(64, 1)
    rho = clearance_radius(env, q, box)
    col = env.collides(q, box)
    assert 0.1 < col.float().mean() < 0.9
    assert torch.equal(rho < 0, col)
    # inside the radius nothing collides
    free = (~col).nonzero().squeeze(-1)[:256]
    u = torch.rand(free.numel(), 3, generator=gen) * 2 - 1
    assert not env.collides(q[free] + u * rho[free].unsqueeze(-1), box[free]).any()


def test_segment_check_matches_env_per_edge(envs):
    env = envs[(2, 1)]
    gen = torch.Generator().manual_seed(0)
    tasks = env.sample_tasks(16, generator=gen)
    q0 = tasks["q"]
    q1 = q0 + 0.4 * torch.randn(16, 3, generator=gen)
    free = segment_collision_free(env, q0, q1, tasks["obstacle"], 0.02)
    ends_free = ~env.collides(q0, tasks["obstacle"]) & ~env.collides(q1, tasks["obstacle"])
    single = torch.stack([env.edge_collision_free(a, b, o, 0.02) for a, b, o in zip(q0, q1, tasks["obstacle"])])
    assert torch.equal(free & ends_free, single)
    certified = segment_collision_free(env, q0, q1, tasks["obstacle"], 0.005, certify=True)
    assert not (certified & ~single).any()


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


@SETTINGS
@given(**episodes_strategy, d=st.sampled_from([0.1, 0.15, 0.3]))
def test_exact_never_longer_than_greedy_on_roadmaps(envs, seed, collision_type, batch, T, kind, d):
    env = envs[(collision_type, batch)]
    roadmap = ExperienceRoadmap(env, rollout(env, seed, T, kind), d=d, lazy=True)
    ep, s, g = roadmap.queries(6, torch.Generator().manual_seed(seed))
    exact = roadmap_paths(roadmap, ep, s, g, "exact")
    greedy = roadmap_paths(roadmap, ep, s, g, "greedy")
    assert not (greedy.found & ~exact.found).any()
    assert (exact.cost[greedy.found] <= greedy.cost[greedy.found] + 1e-5).all()
    want = nx_lengths(roadmap.weights.double(), ep, s, g)
    torch.testing.assert_close(exact.cost.double(), want, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------- configuration errors
def test_bad_arguments_raise_value_errors(envs):
    env = envs[(2, 1)]
    episodes = rollout(env, 0, 5, "random")
    with pytest.raises(ValueError, match="d must be"):
        plan_demonstrations(env, episodes, d=0.0)
    with pytest.raises(ValueError, match="d must be"):
        ExperienceRoadmap(env, episodes, d=-1)
    with pytest.raises(ValueError, match="n_pairs must be"):
        plan_demonstrations(env, episodes, n_pairs=-1)
    with pytest.raises(ValueError, match="method must be one of"):
        plan_demonstrations(env, episodes, method="astar")
    with pytest.raises(ValueError, match="step_size must be"):
        plan_demonstrations(env, episodes, step_size=0)
    with pytest.raises(ValueError, match="episodes must"):
        ExperienceRoadmap(env, episodes.exclude(("next", "done")))
    with pytest.raises(ValueError, match="weights must"):
        shortest_paths(torch.zeros(3, 3), *(torch.zeros(1, dtype=torch.long),) * 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_planning_on_cuda():
    env = UR5eReachEnv(num_envs=4, seed=0, device="cuda")
    episodes = env.rollout(30, break_when_any_done=False)
    demos = plan_demonstrations(env, episodes, generator=torch.Generator("cuda").manual_seed(0))
    assert demos.device.type == "cuda" and demos["observation"].is_cuda
    assert (demos["action"].abs() <= 1).all()
