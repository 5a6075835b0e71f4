"""Planned paths -> MDP demonstrations (paper, sec. 3.3, "Demonstrations Generation in SILP+")."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_silp.choices import INSERT_NODES
from torchrl_silp.models.base import as_model
from torchrl_silp.planning.roadmap import ExperienceRoadmap
from torchrl_silp.planning.search import SEARCH_METHODS, Paths, roadmap_paths
from torchrl_silp.validation import check_bool, check_choice, check_nonnegative_int, check_positive_float

__all__ = ["plan_demonstrations", "paths_to_demonstrations", "demo_start_flags", "check_planner_kwargs"]




def _split_counts(m: torch.Tensor) -> torch.Tensor:
    # InsertNodes, equal pieces: an edge needing actions of max magnitude m
    # becomes P = 2^k equal steps, k the fewest halvings with m / 2^k <= 1;
    # dividing by a power of two is exact in floating point, so the check
    # below is the one the actions meet.
    P = torch.ones_like(m, dtype=torch.long)
    while True:
        over = m / P > 1.0
        if not bool(over.any()):
            return P
        P = torch.where(over, P * 2, P)


def _halving_pieces(m: torch.Tensor) -> torch.Tensor:
    """The paper's InsertNodes (Alg. 2): the pieces of each edge, as fractions of it.

    While the action ``a`` still needed leaves ``[-1, 1]``, halve it until it fits,
    take that step, and recompute the action for the rest of the edge; the rest
    ``<= 1`` is the last step. ``m`` is the edge's largest action magnitude
    (float ``[E]``); returns float ``[E, K]``, each row's pieces in order, 0 past
    its last. The loop runs over piece indices (a handful), never over edges.
    """
    pieces = []
    rest = m.clone()
    while True:
        over = rest > 1.0
        if not bool(over.any()):
            break
        P = _split_counts(torch.where(over, rest, torch.ones_like(rest)))
        piece = torch.where(over, rest / P, torch.zeros_like(rest))
        pieces.append(piece)
        rest = rest - piece
    pieces.append(rest)
    return torch.stack(pieces, -1) / m.clamp(min=torch.finfo(m.dtype).tiny).unsqueeze(-1)


def _edge_pieces(m: torch.Tensor, insert_nodes: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(edge, start, length) of every step along the edges: the edge index, and the
    step's start and length as fractions of its edge, edges in order, steps in order."""
    if insert_nodes == "equal":
        P = _split_counts(m)
        n = int(P.sum())
        edge = torch.repeat_interleave(torch.arange(P.numel(), device=m.device), P, output_size=n)
        first = torch.cumsum(P, 0) - P
        piece = torch.arange(n, device=m.device) - first[edge]
        Pf = P.to(m.dtype)[edge]
        return edge, piece.to(m.dtype) / Pf, 1.0 / Pf
    fractions = _halving_pieces(m)  # [E, K]
    start = torch.cumsum(fractions, -1) - fractions
    # a zero-length edge (m == 0) is one step of length 0, as with equal pieces
    real = fractions > 0
    real[:, -1] |= ~real.any(-1)
    edge, k = real.nonzero(as_tuple=True)
    return edge, start[edge, k], fractions[edge, k]


def _default_observation(model, observation_transform):
    return model.observation_transform() if observation_transform is None else observation_transform


def demo_start_flags(n: int, device) -> dict[str, torch.Tensor]:
    """The flags of the ``n`` states demonstration steps start from: never terminal, colliding or discarded."""
    false = torch.zeros(n, 1, dtype=torch.bool, device=device)
    flags = {key: false.clone() for key in
             ("collision", "swept_collision", "success", "discard", "done", "terminated", "truncated")}
    flags["collision_reason"] = torch.zeros(n, 1, dtype=torch.uint8, device=device)
    flags["is_demo"] = torch.ones(n, 1, dtype=torch.bool, device=device)
    return flags


def paths_to_demonstrations(
    model, roadmap: ExperienceRoadmap, episode: torch.Tensor, paths: Paths, observation_transform=None,
    insert_nodes: str = "equal",
) -> TensorDict:
    """Flat MDP transitions along found paths, with InsertNodes.

    For each found path ``s_0 ... s_n`` each edge ``s_i -> s_{i+1}`` gives the
    action ``a = (q_{i+1} - q_i) / action_scale``; an edge whose action
    leaves ``[-1, 1]`` is cut into steps within bounds at intermediate
    configurations on the segment, which the roadmap's edge check covered:
    ``insert_nodes="equal"`` (ours) halves the whole edge until its action
    fits, giving ``2^k`` equal steps; ``"halving"`` is the paper's Alg. 2:
    halve the action until it fits, take that step, and recompute the action
    for the rest of the edge (unequal steps, sometimes more of them). The demonstrations' desired goal is the achieved goal of
    the path's goal node; next states, rewards, collision and success flags
    come from ``model.step`` (the env's own step, swept collision check
    included). A demonstration ends at its first successful step (the env
    would terminate there): ``terminated = done = success`` on that step.
    Demonstrations with a colliding step are dropped whole.

    The transitions hold the model's named state keys at the root and under
    ``"next"``; ``observation_transform`` (a TorchRL transform or any callable
    ``td -> td``; the model's :class:`~torchrl_silp.transforms.FlatCatTensors` by default)
    then writes what the networks read (``"observation"``, ...), on both, the
    way the env's transforms do for interaction data.

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` (or an env holding one).
        roadmap: the roadmap the paths were found on.
        episode: long ``[Q]`` the episode of each query.
        paths: :class:`~torchrl_silp.planning.search.Paths` ``[Q]``.
        observation_transform: builds the networks' inputs from a named state.
        insert_nodes: ``"equal"`` or ``"halving"`` (the paper's), see above.

    Returns:
        TensorDict ``[N]`` with the keys of an env rollout plus ``"is_demo"``,
        demonstrations one after the other, steps in order.

    Examples:
        >>> import torch
        >>> from torchrl_silp import ReachEnv, UR5eReach
        >>> from torchrl_silp.planning import ExperienceRoadmap, roadmap_paths
        >>> env = ReachEnv(UR5eReach(), num_envs=2, seed=0)
        >>> roadmap = ExperienceRoadmap(env.model, env.rollout(20, break_when_any_done=False))
        >>> ep, s, g = roadmap.queries(4, torch.Generator().manual_seed(0))
        >>> demos = paths_to_demonstrations(env.model, roadmap, ep, roadmap_paths(roadmap, ep, s, g))
        >>> bool((demos["action"].abs() <= 1).all())
        True
    """
    check_choice(insert_nodes, INSERT_NODES, name="insert_nodes")
    model = as_model(model)
    build = _default_observation(model, observation_transform)
    device, dtype = roadmap.device, model.dtype
    q_all, scale = roadmap.config.to(dtype), model.action_scale
    ok = paths.found & (paths.length >= 2)
    nodes, length, episode = paths.nodes[ok], paths.length[ok], episode[ok]
    D = nodes.shape[0]
    L = nodes.shape[1] if D else 1
    # one row per path edge, demos in order, edges in order within a demo
    has_edge = torch.arange(L - 1, device=device) < (length - 1).unsqueeze(-1)
    demo, k = has_edge.nonzero(as_tuple=True)
    e = episode[demo]
    q_from = q_all[e, nodes[demo, k]]
    delta = q_all[e, nodes[demo, k + 1]] - q_from
    action = delta / scale
    # one row per transition: a piece of its edge
    edge, start, length = _edge_pieces(action.abs().amax(-1), insert_nodes)
    q = q_from[edge] + start.unsqueeze(-1) * delta[edge]
    act = action[edge] * length.unsqueeze(-1)
    e_t, demo_t = e[edge], demo[edge]
    goal_node = nodes[:, -1]
    goal = roadmap.achieved_goal.to(dtype)[episode, goal_node][demo_t]
    goal_q = q_all[episode, goal_node][demo_t]
    state = model.state_at(q, roadmap.scene[e_t], goal)
    next_state, reward, collision, success, flags = model.step(state, act)

    # cut each demo after its first success: later steps are past the env's termination
    succ = success.squeeze(-1).long()
    before = torch.cumsum(succ, 0) - succ  # successes strictly before, over the flat layout
    demo_first = torch.zeros(D + 1, dtype=torch.long, device=device)
    demo_first[1:] = torch.bincount(demo_t, minlength=D).cumsum(0)
    keep = (before - before[demo_first[:-1]][demo_t]) == 0
    bad = torch.zeros(D, dtype=torch.long, device=device)
    bad.index_add_(0, demo_t, (collision.squeeze(-1) & keep).long())
    keep &= bad[demo_t] == 0
    idx = keep.nonzero().squeeze(-1)

    N = idx.numel()
    false = torch.zeros(N, 1, dtype=torch.bool, device=device)
    success = success[idx]
    nxt = next_state[idx]
    nxt.update(
        {
            model.goal_config_key: goal_q[idx],
            "reward": reward[idx],
            "collision": collision[idx],
            # a demonstration has no colliding step (those are dropped above)
            "swept_collision": false.clone(),
            "success": success,
            "discard": false.clone(),
            "collision_reason": flags[idx],
            "done": success.clone(),
            "terminated": success.clone(),
            "truncated": false.clone(),
        }
    )
    root = state[idx]
    root.update({"action": act[idx], model.goal_config_key: goal_q[idx], **demo_start_flags(N, device)})
    root = build(root)
    root.set("next", build(nxt))
    return root


PLANNER_OPTIONS = ("d", "n_pairs", "step_size", "method", "generator", "lazy", "goal_node", "own_query",
                   "insert_nodes", "sampled_nodes", "sample_spread")


def check_planner_kwargs(kwargs: dict) -> None:
    """Reject planner options :func:`plan_demonstrations` would refuse, before any episode is planned.

    Examples:
        >>> check_planner_kwargs({"d": 0.15, "method": "greedy"})
        >>> check_planner_kwargs({"d": 0.0})
        Traceback (most recent call last):
        ...
        ValueError: d must be a finite number > 0 (metres), got 0.0
    """
    unknown = sorted(set(kwargs) - set(PLANNER_OPTIONS))
    if unknown:
        raise TypeError(f"planner options {unknown} are unknown; allowed: {PLANNER_OPTIONS}")
    if "d" in kwargs:
        check_positive_float(kwargs["d"], name="d", unit="metres")
    check_positive_float(kwargs.get("step_size"), name="step_size", unit="radians", optional=True)
    check_nonnegative_int(kwargs.get("n_pairs", 0), name="n_pairs")
    check_choice(kwargs.get("method", "exact"), SEARCH_METHODS, name="method")
    check_choice(kwargs.get("insert_nodes", "equal"), INSERT_NODES, name="insert_nodes")
    for name in ("lazy", "goal_node", "own_query"):
        check_bool(kwargs.get(name, False), name=name)
    check_nonnegative_int(kwargs.get("sampled_nodes", 0), name="sampled_nodes")
    check_positive_float(kwargs.get("sample_spread"), name="sample_spread", unit="radians", optional=True)


def plan_demonstrations(
    model,
    episodes: TensorDictBase,
    *,
    d: float = 0.15,
    n_pairs: int = 10,
    step_size: float | None = None,
    method: str = "exact",
    generator: torch.Generator | None = None,
    lazy: bool = True,
    goal_node: bool = False,
    own_query: bool = True,
    insert_nodes: str = "equal",
    observation_transform=None,
    sampled_nodes: int = 0,
    sample_spread: float | None = None,
) -> TensorDict:
    """Demonstrations planned on the experience of a batch of episodes (SILP+).

    Builds an :class:`~torchrl_silp.planning.roadmap.ExperienceRoadmap` per
    episode, plans ``n_pairs`` random start/goal node pairs per episode plus
    the episode's own start to the node nearest its real goal, and turns
    every path found into MDP transitions (:func:`paths_to_demonstrations`):
    every action in ``[-1, 1]``, every step along a collision-checked edge,
    every demonstration ending with a successful, terminating step at its
    goal node.

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` of the episodes' task (or an env holding one).
        episodes: rollout TensorDict ``[..., T]`` (a ``[B, T]`` rollout or collector batch)
            with the model's named state keys.
        d: largest achieved-goal distance of a roadmap edge (m); the paper's 0.15.
        n_pairs: random start/goal pairs per episode (>= 0).
        step_size: resolution of the edge check (rad); the model's ``motion_resolution`` by default.
        method: ``"exact"`` (shortest paths) or ``"greedy"`` (the paper's walk).
        generator: torch generator of the start/goal draw.
        lazy: check only the edges the search needs (Lazy PRM, same paths as
            checking every candidate edge first; see
            :func:`~torchrl_silp.planning.search.roadmap_paths`).
        goal_node: also plan to each episode's real goal configuration (see
            :class:`~torchrl_silp.planning.roadmap.ExperienceRoadmap`).
        own_query: also plan each episode's own start towards its real goal (ours; the
            paper plans the ``n_pairs`` random pairs only).
        insert_nodes: how an edge too long for one action is cut: ``"equal"`` (ours, 2^k
            equal steps) or ``"halving"`` (the paper's Alg. 2); see :func:`paths_to_demonstrations`.
        observation_transform: builds the networks' inputs from a named state (see
            :func:`paths_to_demonstrations`).
        sampled_nodes, sample_spread: free configurations drawn around each episode's
            visited states, made roadmap nodes (ours; see
            :class:`~torchrl_silp.planning.roadmap.ExperienceRoadmap`).

    Returns:
        TensorDict ``[N]`` of transitions with the keys and dtypes of an env
        rollout but its ``"step_count"`` (the named state, ``"observation"``,
        ``"action"``, ``"goal_joint_position"``, ``("next", "reward")``, the done
        flags, ``"collision"``, ``"success"``, ...) plus ``"is_demo"`` (bool
        ``[N, 1]``, True); demonstrations one after the other, each closed by
        ``("next", "done")``.

    Examples:
        >>> import torch
        >>> from torchrl_silp import ReachEnv, UR5eReach
        >>> env = ReachEnv(UR5eReach(), num_envs=4, seed=0)
        >>> episodes = env.rollout(50, break_when_any_done=False)
        >>> demos = plan_demonstrations(env.model, episodes, generator=torch.Generator().manual_seed(0))
        >>> bool(demos["is_demo"].all()), bool((demos["action"].abs() <= 1).all())
        (True, True)
        >>> int(demos["next", "done"].sum()) == int(demos["next", "success"].sum())
        True
    """
    check_choice(method, SEARCH_METHODS, name="method")
    check_nonnegative_int(n_pairs, name="n_pairs")
    check_choice(insert_nodes, INSERT_NODES, name="insert_nodes")
    model = as_model(model)
    roadmap = ExperienceRoadmap(model, episodes, d=d, step_size=step_size, lazy=lazy, goal_node=goal_node,
                                sampled_nodes=sampled_nodes, sample_spread=sample_spread, generator=generator)
    episode, start, goal = roadmap.queries(n_pairs, generator, own_query=own_query)
    paths = roadmap_paths(roadmap, episode, start, goal, method=method)
    return paths_to_demonstrations(model, roadmap, episode, paths, observation_transform, insert_nodes)
