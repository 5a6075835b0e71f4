"""Planned paths -> MDP demonstrations (paper, sec. 3.3, "Demonstrations Generation in SILP+")."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_silp.models.base import as_model
from torchrl_silp.planning.edges import _check_positive
from torchrl_silp.planning.roadmap import ExperienceRoadmap
from torchrl_silp.planning.search import SEARCH_METHODS, Paths, roadmap_paths

__all__ = ["plan_demonstrations", "paths_to_demonstrations", "demo_start_flags", "check_planner_kwargs"]


def _split_counts(m: torch.Tensor) -> torch.Tensor:
    # InsertNodes: halve the step until every action is within [-1, 1]. A path
    # edge needing actions of max magnitude m becomes P = 2^k equal steps,
    # k the fewest halvings with m / 2^k <= 1; dividing by a power of two is
    # exact in floating point, so the check below is the one the actions meet.
    P = torch.ones_like(m, dtype=torch.long)
    while True:
        over = m / P > 1.0
        if not bool(over.any()):
            return P
        P = torch.where(over, P * 2, P)


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
    model, roadmap: ExperienceRoadmap, episode: torch.Tensor, paths: Paths, observation_transform=None
) -> TensorDict:
    """Flat MDP transitions along found paths, with InsertNodes.

    For each found path ``s_0 ... s_n`` each edge ``s_i -> s_{i+1}`` gives the
    action ``a = (q_{i+1} - q_i) / action_scale``; an edge whose action
    leaves ``[-1, 1]`` is halved (intermediate configurations on the
    segment, which the roadmap's edge check covered) until every action is
    within bounds. The demonstrations' desired goal is the achieved goal of
    the path's goal node; next states, rewards, collision and success flags
    come from ``model.step`` (the env's own step, swept collision check
    included). A demonstration ends at its first successful step (the env
    would terminate there): ``terminated = done = success`` on that step.
    Demonstrations with a colliding step are dropped whole.

    The transitions hold the model's named state keys at the root and under
    ``"next"``; ``observation_transform`` (a TorchRL transform or any callable
    ``td -> td``; the model's :class:`~torchrl.envs.CatTensors` by default)
    then writes what the networks read (``"observation"``, ...), on both, the
    way the env's transforms do for interaction data.

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` (or an env holding one).
        roadmap: the roadmap the paths were found on.
        episode: long ``[Q]`` the episode of each query.
        paths: :class:`~torchrl_silp.planning.search.Paths` ``[Q]``.
        observation_transform: builds the networks' inputs from a named state.

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
    P = _split_counts(action.abs().amax(-1))
    # one row per transition: piece i of P along the edge
    n = int(P.sum())
    edge = torch.repeat_interleave(torch.arange(P.numel(), device=device), P, output_size=n)
    first = torch.cumsum(P, 0) - P
    piece = torch.arange(n, device=device) - first[edge]
    Pf = P.to(dtype)[edge].unsqueeze(-1)
    q = q_from[edge] + (piece.to(dtype).unsqueeze(-1) / Pf) * delta[edge]
    act = action[edge] / Pf
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


PLANNER_OPTIONS = ("d", "n_pairs", "step_size", "method", "generator", "lazy", "goal_node", "own_query")


def check_planner_kwargs(kwargs: dict) -> None:
    """Reject planner options :func:`plan_demonstrations` would refuse, before any episode is planned.

    Examples:
        >>> check_planner_kwargs({"d": 0.15, "method": "greedy"})
        >>> check_planner_kwargs({"d": 0.0})
        Traceback (most recent call last):
        ...
        ValueError: d must be a positive finite number of metres, got 0.0
    """
    unknown = sorted(set(kwargs) - set(PLANNER_OPTIONS))
    if unknown:
        raise TypeError(f"planner options {unknown} are unknown; allowed: {PLANNER_OPTIONS}")
    if "d" in kwargs:
        _check_positive("d", kwargs["d"], "metres")
    if kwargs.get("step_size") is not None:
        _check_positive("step_size", kwargs["step_size"], "radians")
    n_pairs = kwargs.get("n_pairs", 0)
    if isinstance(n_pairs, bool) or not isinstance(n_pairs, int) or n_pairs < 0:
        raise ValueError(f"n_pairs must be an int >= 0, got {n_pairs!r}")
    if kwargs.get("method", "exact") not in SEARCH_METHODS:
        raise ValueError(f"method must be one of {SEARCH_METHODS}, got {kwargs['method']!r}")
    for name in ("lazy", "goal_node", "own_query"):
        if not isinstance(kwargs.get(name, False), bool):
            raise TypeError(f"{name} must be a bool, got {kwargs[name]!r}")


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
    observation_transform=None,
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
        observation_transform: builds the networks' inputs from a named state (see
            :func:`paths_to_demonstrations`).

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
    if method not in SEARCH_METHODS:
        raise ValueError(f"method must be one of {SEARCH_METHODS}, got {method!r}")
    if isinstance(n_pairs, bool) or not isinstance(n_pairs, int) or n_pairs < 0:
        raise ValueError(f"n_pairs must be an int >= 0, got {n_pairs!r}")
    model = as_model(model)
    roadmap = ExperienceRoadmap(model, episodes, d=d, step_size=step_size, lazy=lazy, goal_node=goal_node)
    episode, start, goal = roadmap.queries(n_pairs, generator, own_query=own_query)
    paths = roadmap_paths(roadmap, episode, start, goal, method=method)
    return paths_to_demonstrations(model, roadmap, episode, paths, observation_transform)
