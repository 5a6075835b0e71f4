"""Batched graph search on padded roadmaps: exact shortest paths and the paper's greedy walk.

A batch of graphs is a weight tensor ``[E, N, N]`` (edge cost, ``inf`` where
there is no edge); a batch of queries is three long tensors ``[Q]``: the graph
(episode) of each query, its start node and its goal node. Results come back
as :class:`Paths`.

Choice of the exact algorithm: Floyd-Warshall (:func:`all_pairs_distances`,
min-plus over ``[E, N, N]`` with ``N`` in-place ``torch.minimum`` updates) plus
the path read-out of :func:`shortest_paths` is the default (``method="exact"``):
its ``N`` steps are two large vectorised ops each, while batched A* with the
Euclidean TCP heuristic (:func:`astar_paths`) needs ~10 small ops per expansion
and tens of expansions until the slowest query closes its goal, and is slower on
roadmaps of an episode's size (``benchmarks/planner.py --search`` times both,
with Dijkstra and SciPy's). A* stays available and is tested to agree.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from torchrl_silp.choices import SEARCH_METHODS
from torchrl_silp.validation import check_choice, check_nonnegative_int, check_positive_int

__all__ = [
    "Paths",
    "all_pairs_distances",
    "shortest_paths",
    "astar_paths",
    "greedy_paths",
    "roadmap_paths",
    "SEARCH_METHODS",
]



class Paths(NamedTuple):
    """A batch of paths, one per query.

    Attributes:
        nodes: long ``[Q, L]`` node indices from start to goal, padded by
            repeating the last node.
        length: long ``[Q]`` number of nodes on the path (1: the start only).
        found: bool ``[Q]`` whether the path ends at the query's goal.
        cost: ``[Q]`` sum of the edge costs, ``inf`` where not found.
    """

    nodes: torch.Tensor
    length: torch.Tensor
    found: torch.Tensor
    cost: torch.Tensor


def _check_graph(weights: torch.Tensor, episode: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> None:
    if not isinstance(weights, torch.Tensor) or weights.dim() != 3 or weights.shape[1] != weights.shape[2]:
        raise ValueError(f"weights must be a tensor [E, N, N], got {getattr(weights, 'shape', type(weights))}")
    if not weights.is_floating_point():
        raise TypeError(f"weights must be a floating tensor, got {weights.dtype}")
    for name, t in (("episode", episode), ("start", start), ("goal", goal)):
        if not isinstance(t, torch.Tensor) or t.dim() != 1 or t.dtype != torch.long:
            raise ValueError(f"{name} must be a long tensor [Q], got {getattr(t, 'shape', type(t))}")
    if not (episode.shape == start.shape == goal.shape):
        raise ValueError(f"episode, start and goal must have one shape [Q], got {episode.shape}, {start.shape}, {goal.shape}")


def all_pairs_distances(weights: torch.Tensor) -> torch.Tensor:
    """Shortest-path distances between all node pairs of every graph (Floyd-Warshall).

    Args:
        weights: ``[E, N, N]`` non-negative edge costs, ``inf`` where there is no edge.

    Returns:
        ``[E, N, N]`` distances (``inf`` between disconnected nodes, 0 on the diagonal).

    Examples:
        >>> import math, torch
        >>> w = torch.full((1, 3, 3), math.inf)
        >>> w[0, 0, 1] = w[0, 1, 2] = 1.0
        >>> all_pairs_distances(w)[0, 0, 2].item()
        2.0
    """
    D = weights.clone()
    D.diagonal(dim1=1, dim2=2).zero_()
    # in-place minimum, no boolean masks: torch.where over [E, N, N] costs ~25x
    # a minimum on this CPU build
    for k in range(D.shape[1]):
        torch.minimum(D, D[:, :, k : k + 1] + D[:, k : k + 1, :], out=D)
    return D


def _rows(weights: torch.Tensor, episode: torch.Tensor, node: torch.Tensor) -> torch.Tensor:
    # [Q, N]: the outgoing edge costs of node[q] in graph episode[q]
    E, N, _ = weights.shape
    return weights.reshape(E * N, N).index_select(0, episode * N + node)


def _walk_down(weights, episode, start, goal, to_goal, max_len) -> torch.Tensor:
    # Follow, from the start, the neighbour minimising edge cost + remaining
    # distance, which is a next hop of a shortest path. Queries that reached
    # their goal stay there.
    cur = start
    path = [cur]
    for _ in range(max_len - 1):
        if bool((cur == goal).all()):
            break
        nxt = (_rows(weights, episode, cur) + to_goal).argmin(-1)
        cur = torch.where(cur == goal, cur, nxt)
        path.append(cur)
    return torch.stack(path, -1)


def _edge_costs(weights: torch.Tensor, episode: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    # [Q, L-1]: the cost of each step of padded node sequences
    return weights[episode.unsqueeze(-1), nodes[:, :-1], nodes[:, 1:]]


def _finish(nodes: torch.Tensor, edge_cost: torch.Tensor, start, goal) -> Paths:
    # length, cost and found of padded node sequences, from the cost of each
    # step (steps that repeat a node are padding and cost nothing)
    moved = nodes[:, 1:] != nodes[:, :-1]
    length = 1 + moved.sum(-1)
    cost = torch.where(moved, edge_cost, torch.zeros_like(edge_cost)).sum(-1)
    found = (nodes[:, 0] == start) & (nodes[:, -1] == goal) & torch.isfinite(cost)
    cost = torch.where(found, cost, torch.full_like(cost, math.inf))
    return Paths(nodes, length, found, cost)


def shortest_paths(
    weights: torch.Tensor,
    episode: torch.Tensor,
    start: torch.Tensor,
    goal: torch.Tensor,
    distances: torch.Tensor | None = None,
) -> Paths:
    """Exact shortest paths for a batch of queries, from all-pairs distances.

    Args:
        weights: ``[E, N, N]`` edge costs, ``inf`` where there is no edge.
        episode, start, goal: long ``[Q]`` the graph, start node and goal node of each query.
        distances: ``[E, N, N]`` output of :func:`all_pairs_distances` on
            ``weights`` if already computed.

    Returns:
        :class:`Paths`; a query without a path gets ``found=False``, its start as the path.

    Examples:
        >>> import math, torch
        >>> w = torch.full((1, 3, 3), math.inf)
        >>> w[0, 0, 1] = w[0, 1, 0] = w[0, 1, 2] = w[0, 2, 1] = 1.0
        >>> w[0, 0, 2] = w[0, 2, 0] = 3.0
        >>> one = torch.zeros(1, dtype=torch.long)
        >>> p = shortest_paths(w, one, one, one + 2)
        >>> p.nodes.tolist(), p.cost.tolist()
        ([[0, 1, 2]], [2.0])
    """
    _check_graph(weights, episode, start, goal)
    D = all_pairs_distances(weights) if distances is None else distances
    to_goal = D[episode, :, goal]  # [Q, N]
    reachable = torch.isfinite(D[episode, start, goal])
    # unreachable queries are parked on their goal so the walk ignores them
    nodes = _walk_down(weights, episode, torch.where(reachable, start, goal), goal, to_goal, weights.shape[1])
    nodes = torch.where(reachable.unsqueeze(-1), nodes, start.unsqueeze(-1))
    return _finish(nodes, _edge_costs(weights, episode, nodes), start, goal)


def astar_paths(
    weights: torch.Tensor,
    positions: torch.Tensor,
    episode: torch.Tensor,
    start: torch.Tensor,
    goal: torch.Tensor,
) -> Paths:
    """Exact shortest paths by batched A*, heuristic = Euclidean distance of ``positions``.

    All queries expand one node per iteration in lock-step, until every query
    has closed its goal or has nothing left open. Exact when edge costs are
    the Euclidean distances of ``positions`` (the heuristic is then consistent),
    as on an :class:`~torchrl_silp.planning.roadmap.ExperienceRoadmap`.

    Args:
        weights: ``[E, N, N]`` edge costs, ``inf`` where there is no edge.
        positions: ``[E, N, D]`` node positions (TCP xyz).
        episode, start, goal: long ``[Q]``.

    Returns:
        :class:`Paths`.

    Examples:
        >>> import torch
        >>> pos = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]])
        >>> w = torch.cdist(pos, pos)
        >>> w[0, 0, 2] = w[0, 2, 0] = float("inf")
        >>> one = torch.zeros(1, dtype=torch.long)
        >>> astar_paths(w, pos, one, one, one + 2).nodes.tolist()
        [[0, 1, 2]]
    """
    _check_graph(weights, episode, start, goal)
    E, N, _ = weights.shape
    Q = episode.numel()
    pos = positions[episode]  # [Q, N, D]
    h = (pos - pos[torch.arange(Q, device=pos.device), goal].unsqueeze(1)).norm(dim=-1)
    g = torch.full((Q, N), math.inf, dtype=weights.dtype, device=weights.device)
    g.scatter_(1, start.unsqueeze(-1), 0.0)
    closed = torch.zeros_like(g)  # 0 open, inf closed: added to f, no masks
    inf_col = torch.full((Q, 1), math.inf, dtype=weights.dtype, device=weights.device)
    goal1 = goal.unsqueeze(-1)
    for _ in range(N):
        fu, u = (g + h + closed).min(-1, keepdim=True)
        if not bool((torch.isfinite(fu) & (closed.gather(1, goal1) == 0)).any()):
            break
        closed.scatter_(1, u, inf_col)
        torch.minimum(g, g.gather(1, u) + _rows(weights, episode, u.squeeze(-1)), out=g)
    # read the path backwards: the predecessor p of node v minimises g[p] + w(p, v)
    wt = weights.transpose(1, 2)
    reachable = torch.isfinite(g.gather(1, goal1).squeeze(-1))
    cur = torch.where(reachable, goal, start)
    back = [cur]
    for _ in range(N - 1):
        if bool((cur == start).all()):
            break
        prev = (_rows(wt, episode, cur) + g).argmin(-1)
        cur = torch.where(cur == start, cur, prev)
        back.append(cur)
    nodes = torch.stack(back[::-1], -1)
    # left-align: paths of different lengths start at column 0, padded with the goal
    nodes = _left_align(nodes, start)
    return _finish(nodes, _edge_costs(weights, episode, nodes), start, goal)


def _left_align(nodes: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    # rows look like [s, s, s, a, b, g]: drop the leading repeats of s
    L = nodes.shape[1]
    lead = (nodes == start.unsqueeze(-1)).long().cumprod(-1).sum(-1) - 1  # repeats beyond the first
    idx = (torch.arange(L, device=nodes.device) + lead.unsqueeze(-1)).clamp(max=L - 1)
    return nodes.gather(1, idx)


def greedy_paths(
    weights: torch.Tensor,
    positions: torch.Tensor,
    episode: torch.Tensor,
    start: torch.Tensor,
    goal: torch.Tensor,
    max_steps: int | None = None,
) -> Paths:
    """The paper's greedy best-first walk (sec. 3.2, steps 3-6), batched over queries.

    From the current node, move to the unvisited neighbour ``n`` minimising
    ``g(n) + h(n)``: the edge cost from the current node plus the Euclidean
    distance of ``positions`` from ``n`` to the goal. Stop at the goal, when
    no unvisited neighbour is left (a dead end: not found) or after
    ``max_steps`` moves. Not optimal, and it can fail where a path exists.

    Args:
        weights: ``[E, N, N]`` edge costs, ``inf`` where there is no edge.
        positions: ``[E, N, D]`` node positions.
        episode, start, goal: long ``[Q]``.
        max_steps: move cap; ``N - 1`` by default.

    Returns:
        :class:`Paths` (for failed queries, the partial walk with ``found=False``).

    Examples:
        >>> import torch
        >>> pos = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]])
        >>> w = torch.cdist(pos, pos)
        >>> w[0, 0, 2] = w[0, 2, 0] = float("inf")
        >>> one = torch.zeros(1, dtype=torch.long)
        >>> greedy_paths(w, pos, one, one, one + 2).nodes.tolist()
        [[0, 1, 2]]
    """
    _check_graph(weights, episode, start, goal)
    nodes = _greedy_walk(lambda cur, visited, active: _rows(weights, episode, cur), positions, episode, start, goal, max_steps)
    return _finish(nodes, _edge_costs(weights, episode, nodes), start, goal)


def _greedy_walk(rows_fn, positions, episode, start, goal, max_steps) -> torch.Tensor:
    # rows_fn(cur [Q], visited [Q, N] (0 / inf), active [Q]) -> [Q, N] costs of the edges out of cur
    N = positions.shape[1]
    check_nonnegative_int(max_steps, name="max_steps", optional=True)
    if max_steps is None:
        max_steps = N - 1
    Q = episode.numel()
    pos = positions[episode]
    h = (pos - pos[torch.arange(Q, device=pos.device), goal].unsqueeze(1)).norm(dim=-1)
    visited = torch.zeros_like(h)  # 0 unvisited, inf visited: added to f, no masks
    inf_col = torch.full((Q, 1), math.inf, dtype=h.dtype, device=h.device)
    visited.scatter_(1, start.unsqueeze(-1), inf_col)
    cur = start
    active = cur != goal
    path = [cur]
    for _ in range(max_steps):
        if not bool(active.any()):
            break
        f, nxt = (rows_fn(cur, visited, active) + h + visited).min(-1)
        moved = active & torch.isfinite(f)
        cur = torch.where(moved, nxt, cur)
        visited.scatter_(1, cur.unsqueeze(-1), inf_col)
        path.append(cur)
        active = moved & (cur != goal)
    return torch.stack(path, -1)


def roadmap_paths(
    roadmap,
    episode: torch.Tensor,
    start: torch.Tensor,
    goal: torch.Tensor,
    method: str = "exact",
    max_rounds: int | None = None,
) -> Paths:
    """Search an :class:`~torchrl_silp.planning.roadmap.ExperienceRoadmap`, checking edges lazily.

    ``method="exact"``: shortest paths (Floyd-Warshall, see the module
    docstring). On a lazy roadmap this is Lazy PRM: search the graph of
    candidate edges not known to collide, check the unchecked edges of the
    paths found (one batched call per round), and search again for the
    queries whose path lost an edge, until every path is checked. A path all
    of whose edges pass is the shortest of the collision-free graph too, since
    that graph is a subgraph of the one searched; so the result is the same
    as on the fully checked roadmap.

    ``method="greedy"``: the paper's walk (:func:`greedy_paths`), checking
    the edges from the current node to its unvisited candidates before each
    move (the paper's step 4).

    Args:
        roadmap: the roadmap (lazy or not).
        episode, start, goal: long ``[Q]`` queries, e.g. from :meth:`ExperienceRoadmap.queries`.
        method: ``"exact"`` or ``"greedy"``.
        max_rounds: cap on the Lazy-PRM rounds (None: until done; queries
            still open at the cap are reported not found).

    Returns:
        :class:`Paths` on the collision-free roadmap.

    Examples:
        >>> import torch
        >>> from torchrl_silp import ReachEnv, UR5eReach
        >>> from torchrl_silp.planning import ExperienceRoadmap
        >>> env = ReachEnv(UR5eReach(), num_envs=2, seed=0)
        >>> roadmap = ExperienceRoadmap(env.model, env.rollout(20, break_when_any_done=False), lazy=True)
        >>> ep, s, g = roadmap.queries(4, torch.Generator().manual_seed(0))
        >>> exact = roadmap_paths(roadmap, ep, s, g)
        >>> greedy = roadmap_paths(roadmap, ep, s, g, method="greedy")
        >>> bool((exact.cost[greedy.found] <= greedy.cost[greedy.found] + 1e-6).all())
        True
    """
    check_choice(method, SEARCH_METHODS, name="method")
    check_positive_int(max_rounds, name="max_rounds", optional=True)
    _check_graph(roadmap.distance, episode, start, goal)
    if method == "greedy":
        nodes = _greedy_on_roadmap(roadmap, episode, start, goal)
    else:
        nodes = _lazy_shortest(roadmap, episode, start, goal, max_rounds)
    e, a, b = episode.unsqueeze(-1), nodes[:, :-1], nodes[:, 1:]
    free = roadmap.candidates[e, a, b] & roadmap.checked[e, a, b] & ~roadmap.colliding[e, a, b]
    cost = torch.where(free, roadmap.distance[e, a, b], math.inf)
    return _finish(nodes, cost, start, goal)


def _lazy_shortest(roadmap, episode, start, goal, max_rounds) -> torch.Tensor:
    Q = episode.numel()
    done_rows, done_nodes = [], []
    todo = torch.arange(Q, device=episode.device)
    rounds = 0
    while todo.numel():
        rounds += 1
        # search only the graphs of the queries still open
        eps, local = torch.unique(episode[todo], return_inverse=True)
        nodes = shortest_paths(roadmap.optimistic_weights[eps], local, start[todo], goal[todo]).nodes
        # check the unchecked edges of every path found, in one call
        e = episode[todo].unsqueeze(-1).expand_as(nodes[:, 1:])
        a, b = nodes[:, :-1], nodes[:, 1:]
        if roadmap.check_edges(e.reshape(-1), a.reshape(-1), b.reshape(-1)) == 0:
            ok = torch.ones_like(todo, dtype=torch.bool)
        else:
            ok = ~roadmap.colliding[e, a, b].any(-1)
            if max_rounds is not None and rounds >= max_rounds:
                ok = torch.ones_like(ok)  # give up: _finish marks paths with a bad edge not found
        done_rows.append(todo[ok])
        done_nodes.append(nodes[ok])
        todo = todo[~ok]
    L = max((n.shape[1] for n in done_nodes), default=1)
    out = start.unsqueeze(-1).repeat(1, L)
    for rows, n in zip(done_rows, done_nodes):
        out[rows] = torch.cat([n, n[:, -1:].expand(-1, L - n.shape[1])], dim=1)
    return out


def _greedy_on_roadmap(roadmap, episode, start, goal) -> torch.Tensor:
    def rows_fn(cur, visited, active):
        # check the edges from each walking query's node to its unvisited candidates
        cand = roadmap.candidates[episode, cur] & (visited == 0) & active.unsqueeze(-1)
        qi, j = (cand & ~roadmap.checked[episode, cur]).nonzero(as_tuple=True)
        roadmap.check_edges(episode[qi], cur[qi], j)
        return roadmap.optimistic_weights[episode, cur]

    return _greedy_walk(rows_fn, roadmap.achieved_goal, episode, start, goal, None)
