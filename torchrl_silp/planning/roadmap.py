"""The experience roadmap: a PRM over the collision-free states an episode visited.

Paper, sec. 3.2: the nodes of episode ``e`` are its visited collision-free
states ``S_f``; an edge joins two nodes whose TCPs are at most ``d`` apart and
whose joint-space segment passes the subdivision collision check. Every
episode of a batch becomes one padded graph, so a batch of ``E`` episodes is
held as ``[E, N]`` node tensors and ``[E, N, N]`` edge tensors with masks, and
all of them are built with a handful of batched tensor operations.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from torchrl_silp.models.base import as_model
from torchrl_silp.validation import check_bool, check_nonnegative_int, check_positive_float

__all__ = ["ExperienceRoadmap", "split_episodes"]

def split_episodes(episodes: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """Episode boundaries of a rollout batch.

    A row of a ``[B, T]`` batch from an auto-resetting env may hold several
    episodes, and a collector's batch may start in the middle of one. A new
    episode starts at ``t = 0`` of every row, where ``("collector",
    "traj_ids")`` changes (when present) and after every ``("next", "done")``.

    Args:
        episodes: TensorDict with batch dims ``[..., T]`` (at least one dim).

    Returns:
        ``starts``: bool ``[R, T]`` (``R`` the flattened leading dims), True on
        the first step of an episode; ``episode``: long ``[R, T]``, the index of
        the episode of each step, counted row-major from 0.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([[False, True, False, False]]).unsqueeze(-1)
        >>> td = TensorDict({("next", "done"): done}, batch_size=[1, 4])
        >>> starts, episode = split_episodes(td)
        >>> episode.tolist()
        [[0, 0, 1, 1]]
    """
    if not isinstance(episodes, TensorDictBase):
        raise TypeError(f"episodes must be a TensorDict with batch dims [..., T], got {type(episodes).__name__}")
    if episodes.batch_dims < 1 or episodes.batch_size.numel() == 0:
        raise ValueError(f"episodes must have batch dims [..., T] with T >= 1, got {tuple(episodes.batch_size)}")
    T = episodes.batch_size[-1]
    done = episodes.get(("next", "done"), None)
    if done is None:
        raise ValueError('episodes must hold ("next", "done") to find the episode boundaries')
    done = done.reshape(-1, T)
    starts = torch.zeros_like(done)
    starts[:, 0] = True
    starts[:, 1:] = done[:, :-1]
    traj = episodes.get(("collector", "traj_ids"), None)
    if traj is not None:
        traj = traj.reshape(-1, T)
        starts[:, 1:] |= traj[:, 1:] != traj[:, :-1]
    episode = starts.reshape(-1).cumsum(0).reshape(starts.shape) - 1
    return starts, episode


class ExperienceRoadmap:
    """Padded roadmaps over the collision-free states of a batch of episodes.

    Nodes of an episode: its first state and every next state whose
    ``("next", "collision")`` flag is False, in visiting order, exact repeats
    dropped (a type-1/2 collision puts the arm back on the previous state).
    Node 0 of every episode is its first state. Candidate edges join two
    nodes of one episode whose achieved goals (e.g. TCPs) are at most ``d``
    apart; an edge is kept when its joint segment passes the task model's
    motion check (:meth:`~torchrl_silp.models.TaskModel.segment_collision_free`,
    the test the env judges its steps with). Edges are undirected and
    weighted by the achieved-goal distance.

    The roadmap reads the model's named keys (configuration, achieved goal,
    scene, desired goal), never the flat observation, so transforms that
    rescale ``"observation"`` leave it unchanged.

    Episodes are split with ``("collector", "traj_ids")`` when present and with
    the done flags (see :func:`split_episodes`), so a ``[B, T]`` batch of an
    auto-resetting env or a flat ``[N]`` slice of a replay buffer both work.

    With ``lazy=False`` every candidate edge is checked at construction, in one
    batched call over all candidate pairs of all episodes. With ``lazy=True``
    none is; :meth:`check_edges` checks the ones a search asks for (the
    Lazy-PRM scheme :func:`~torchrl_silp.planning.search.roadmap_paths` uses).

    Args:
        model: the :class:`~torchrl_silp.models.TaskModel` (or an env holding one as ``.model``).
        episodes: rollout TensorDict ``[..., T]`` with the model's state keys at the root,
            its configuration and achieved goal under ``"next"``, ``("next", "collision")``
            and ``("next", "done")`` (optionally ``("collector", "traj_ids")``,
            ``("next", "success")`` and the goal configuration).
        d: largest achieved-goal distance of an edge (m); the paper's 0.15.
        step_size: resolution of the edge check (rad); the model's ``motion_resolution`` by default.
        lazy: defer the edge checks to :meth:`check_edges`.
        goal_node: also make each episode's real goal configuration
            (``model.goal_config_key``, free by the task's construction) a node, the
            last of its episode, so that an episode that came within ``d`` of
            its goal yields a demonstration that reaches the goal itself rather
            than the visited state nearest it. An extension of the paper, whose
            nodes are visited states only.
        sampled_nodes: also make up to this many collision-free configurations per
            episode nodes (ours; the paper's nodes are visited states only), so that a
            path may leave the states the policy visited: each is a visited node of the
            episode (or, with ``goal_node``, its goal configuration), drawn uniformly,
            moved by a uniform offset of at most
            ``sample_spread`` per joint and clipped to the joint limits, and kept
            when it is free in the episode's scene (:meth:`~torchrl_silp.models.TaskModel.collision_flags`);
            the drawn ones that collide are dropped. Their edges are checked as every
            other edge. They are waypoints: a path may pass through them and end at
            the one nearest the goal, but :meth:`queries` draws its random pairs among the
            visited nodes only, so that every demonstration starts from a state the
            policy was in (a start drawn among the sampled nodes, most of the nodes with
            a wide spread, fills the demonstrations with states the policy never visits).
        sample_spread: the largest offset of a sampled node per joint, in the
            configuration's units (rad); ``None``: two actions' reach
            (``2 * model.action_scale``). A spread as wide as the joint ranges draws
            nodes all over the joint box, as a PRM's.
        generator: torch generator of the sampled nodes.

    Attributes:
        config: ``[E, N, D]`` configurations of the nodes (zero padding).
        achieved_goal: ``[E, N, G]`` achieved goals of the nodes.
        mask: bool ``[E, N]``, True on real nodes (the first ``num_nodes[e]``).
        num_nodes: long ``[E]``.
        scene: TensorDict ``[E]`` of the scene keys, and ``goal`` ``[E, G]``: each episode's desired goal.
        reached: bool ``[E]``, whether the episode reached its goal.
        is_goal_node: bool ``[E, N]``, True on the goal node of each episode
            (all False without ``goal_node``).
        is_sampled_node: bool ``[E, N]``, True on the sampled nodes (all False without ``sampled_nodes``).
        num_visited: long ``[E]``: the visited nodes, the first of each episode.
        distance: ``[E, N, N]`` achieved-goal distances between nodes.
        candidates: bool ``[E, N, N]``, symmetric: node pairs within ``d``.
        checked: bool ``[E, N, N]``: candidate edges whose check has run.
        colliding: bool ``[E, N, N]``: checked edges that failed it.

    Examples:
        >>> from torchrl_silp import ReachEnv, UR5eReach
        >>> env = ReachEnv(UR5eReach(), num_envs=2, seed=0)
        >>> episodes = env.rollout(20, break_when_any_done=False)
        >>> roadmap = ExperienceRoadmap(env.model, episodes, d=0.15)
        >>> roadmap.config.shape[0], roadmap.adjacency.shape == roadmap.distance.shape
        (2, True)
        >>> bool((roadmap.weights[roadmap.adjacency] <= 0.15).all())
        True
    """

    def __init__(
        self,
        model,
        episodes: TensorDictBase,
        *,
        d: float = 0.15,
        step_size: float | None = None,
        lazy: bool = False,
        goal_node: bool = False,
        sampled_nodes: int = 0,
        sample_spread: float | None = None,
        generator: torch.Generator | None = None,
    ):
        model = as_model(model)
        self.model = model
        self.d = check_positive_float(d, name="d", unit="metres")
        self.step_size = model.motion_resolution if step_size is None else check_positive_float(
            step_size, name="step_size", unit="radians")
        check_bool(lazy, name="lazy")
        check_bool(goal_node, name="goal_node")
        check_nonnegative_int(sampled_nodes, name="sampled_nodes")
        check_positive_float(sample_spread, name="sample_spread", unit="radians", optional=True)
        starts, episode = split_episodes(episodes)
        cfg_key, goal_key = model.config_key, model.achieved_goal_key
        needed = [*model.state_keys, ("next", cfg_key), ("next", goal_key), ("next", "collision")]
        if goal_node:
            needed.append(model.goal_config_key)
        missing = [k for k in needed if episodes.get(k, None) is None]
        if missing:
            raise ValueError(f"episodes must hold the keys {missing} (the task model's named state)")
        T = episodes.batch_size[-1]
        D, G = model.config_dim, model.goal_dim

        def rows(key, width):
            return episodes.get(key).reshape(-1, T, width)

        config, next_config = rows(cfg_key, D), rows(("next", cfg_key), D)
        achieved, next_achieved = rows(goal_key, G), rows(("next", goal_key), G)
        collision = episodes.get(("next", "collision")).reshape(-1, T)
        success = episodes.get(("next", "success"), None)
        device = config.device
        E = int(episode[-1, -1]) + 1

        # Two candidate slots per step, in visiting order: the state an episode
        # starts from, and the next state unless it collided.
        slot_config = torch.stack([config, next_config], dim=2).reshape(-1, D)
        slot_goal = torch.stack([achieved, next_achieved], dim=2).reshape(-1, G)
        slot_valid = torch.stack([starts, ~collision], dim=2).reshape(-1)
        slot_episode = episode.unsqueeze(-1).expand(-1, -1, 2).reshape(-1)
        keep = slot_valid.nonzero().squeeze(-1)
        node_config, node_goal, node_episode = slot_config[keep], slot_goal[keep], slot_episode[keep]
        first_step = starts.reshape(-1).nonzero().squeeze(-1)
        flat = episodes.reshape(-1)
        self.scene = flat.select(*model.scene_keys)[first_step].clone()
        self.goal = flat.get(model.desired_goal_key)[first_step].contiguous()
        reached = torch.zeros(E, dtype=torch.long, device=device)
        if success is not None:
            reached.index_add_(0, episode.reshape(-1), success.reshape(-1).long())
        self.reached = reached > 0

        # a last column tells the nodes apart through the padding and the de-duplication:
        # 0 visited, 1 the goal node, 2 sampled
        rows_ = torch.cat([node_config, node_goal.to(node_config.dtype), torch.zeros_like(node_config[:, :1])], dim=-1)
        goal_rows = goal_episode = None
        if goal_node:
            goal_q = flat.get(model.goal_config_key)[first_step].to(rows_.dtype)
            goal_rows = torch.cat([goal_q, self.goal.to(rows_.dtype), torch.ones_like(goal_q[:, :1])], dim=-1)
            goal_episode = torch.arange(E, device=device)
        if sampled_nodes:
            # drawn around the visited states and, with goal nodes, the goal configuration too
            around = node_config if goal_rows is None else torch.cat([node_config, goal_rows[:, :D].to(node_config.dtype)])
            around_episode = node_episode if goal_rows is None else torch.cat([node_episode, goal_episode])
            sampled, sampled_episode = self._sample_nodes(around, around_episode, E, sampled_nodes, sample_spread,
                                                          generator)
            rows_ = torch.cat([rows_, sampled.to(rows_.dtype)])
            node_episode = torch.cat([node_episode, sampled_episode])
        if goal_rows is not None:
            rows_ = torch.cat([rows_, goal_rows])
            node_episode = torch.cat([node_episode, goal_episode])
        appended = sampled_nodes > 0 or goal_node
        if appended:
            # stable: visiting order kept, then the sampled nodes, each goal node last in its episode
            node_episode, order = torch.sort(node_episode, stable=True)
            rows_ = rows_[order]
        qt, mask = self._pad(rows_, node_episode, E)
        # exact repeats: a node equal to an earlier node of its episode
        q = qt[..., :D]
        same = (q.unsqueeze(2) == q.unsqueeze(1)).all(-1) & mask.unsqueeze(1) & mask.unsqueeze(2)
        repeat = torch.tril(same, diagonal=-1).any(-1)
        if bool(repeat.any()):
            keep_nodes = mask & ~repeat
            ep = torch.arange(E, device=device).unsqueeze(-1).expand_as(keep_nodes)[keep_nodes]
            qt, mask = self._pad(qt[keep_nodes], ep, E)
        self.config = qt[..., :D].contiguous()
        self.achieved_goal = qt[..., D : D + G].contiguous()
        self.mask = mask
        kind = qt[..., -1].round()
        self.is_goal_node = (kind == 1) & mask
        self.is_sampled_node = (kind == 2) & mask
        self.num_nodes = mask.sum(-1)
        self.num_visited = self.num_nodes - (self.is_goal_node | self.is_sampled_node).sum(-1)

        self.distance = torch.cdist(self.achieved_goal, self.achieved_goal)
        pair = mask.unsqueeze(1) & mask.unsqueeze(2)
        eye = torch.eye(self.config.shape[1], dtype=torch.bool, device=device)
        self.candidates = pair & ~eye & (self.distance <= self.d)
        self.checked = torch.zeros_like(self.candidates)
        self.colliding = torch.zeros_like(self.candidates)
        # candidate costs with the edges known to collide at inf, updated in
        # place by check_edges (a where over [E, N, N] is too slow to redo per search)
        self._optimistic = torch.where(self.candidates, self.distance, math.inf)
        if not lazy:
            self.check_edges()

    def _sample_nodes(self, node_config, node_episode, E: int, k: int, spread: float | None, generator):
        # k draws per episode around its visited nodes (or in the joint box); the free ones as node rows
        model, device = self.model, node_config.device
        gdev = generator.device if generator is not None else device
        low, high = model.config_low.to(device, node_config.dtype), model.config_high.to(device, node_config.dtype)
        episode = torch.arange(E, device=device).repeat_interleave(k)
        u = torch.rand(E * k, model.config_dim, generator=generator, device=gdev, dtype=node_config.dtype).to(device)
        spread = 2 * float(model.action_scale) if spread is None else spread
        order = torch.argsort(node_episode, stable=True)
        counts = torch.bincount(node_episode, minlength=E)  # every episode has its first state
        first = torch.cumsum(counts, 0) - counts
        pick = torch.rand(E * k, generator=generator, device=gdev, dtype=node_config.dtype).to(device)
        offset = (pick * counts[episode]).long().clamp(max=(counts[episode] - 1).clamp(min=0))
        base = node_config[order][first[episode] + offset]
        q = torch.minimum(torch.maximum(base + spread * (2 * u - 1), low), high)
        flags, _ = model.collision_flags(q, self.scene[episode])
        free = (flags.squeeze(-1) == 0).nonzero().squeeze(-1)
        q, episode = q[free], episode[free]
        goal = model.achieved_goal(q).to(q.dtype)
        return torch.cat([q, goal, torch.full_like(q[:, :1], 2.0)], dim=-1), episode

    # names of the UR5e days: the configuration and the TCP (the achieved goal)
    @property
    def q(self) -> torch.Tensor:
        return self.config

    @property
    def tcp(self) -> torch.Tensor:
        return self.achieved_goal

    @staticmethod
    def _pad(values: torch.Tensor, episode: torch.Tensor, E: int) -> tuple[torch.Tensor, torch.Tensor]:
        # flat rows sorted by episode -> [E, N, ...] padded, and the mask
        counts = torch.bincount(episode, minlength=E)
        N = max(int(counts.max()), 1) if counts.numel() else 1
        first = torch.cumsum(counts, 0) - counts
        pos = torch.arange(values.shape[0], device=values.device) - first[episode]
        out = values.new_zeros(E, N, *values.shape[1:])
        out[episode, pos] = values
        mask = torch.zeros(E, N, dtype=torch.bool, device=values.device)
        mask[episode, pos] = True
        return out, mask

    # ------------------------------------------------------------------ edges
    def check_edges(
        self, episode: torch.Tensor | None = None, i: torch.Tensor | None = None, j: torch.Tensor | None = None
    ) -> int:
        """Run the model's motion check on unchecked candidate edges, all in one batch.

        Args:
            episode, i, j: long ``[K]`` edges ``(episode, i, j)`` to check, in
                either direction, repeats allowed; pairs that are no candidate
                or already checked are skipped. All unchecked candidates when None.

        Returns:
            the number of (undirected) edges checked.
        """
        N = self.config.shape[1]
        if episode is None:
            episode, i, j = torch.triu(self.candidates & ~self.checked, diagonal=1).nonzero(as_tuple=True)
        else:
            if i is None or j is None or not (episode.shape == i.shape == j.shape):
                raise ValueError("episode, i and j must be long tensors of one shape [K]")
            keep = self.candidates[episode, i, j] & ~self.checked[episode, i, j]
            lo, hi = torch.minimum(i, j)[keep], torch.maximum(i, j)[keep]
            key = torch.unique((episode[keep] * N + lo) * N + hi)
            episode, i, j = key // (N * N), (key // N) % N, key % N
        if episode.numel() == 0:
            return 0
        free = self.model.segment_collision_free(
            self.config[episode, i], self.config[episode, j], self.scene[episode], self.step_size
        )
        e2, a, b = torch.cat([episode, episode]), torch.cat([i, j]), torch.cat([j, i])
        self.checked[e2, a, b] = True
        hit = ~torch.cat([free, free])
        self.colliding[e2, a, b] = hit
        self._optimistic[e2[hit], a[hit], b[hit]] = math.inf
        return int(episode.numel())

    @property
    def adjacency(self) -> torch.Tensor:
        """bool ``[E, N, N]``: candidate edges checked and collision-free."""
        return self.candidates & self.checked & ~self.colliding

    @property
    def weights(self) -> torch.Tensor:
        """``[E, N, N]`` edge costs (TCP distance) of :attr:`adjacency`, ``inf`` elsewhere."""
        return torch.where(self.adjacency, self.distance, math.inf)

    @property
    def optimistic_weights(self) -> torch.Tensor:
        """``[E, N, N]`` edge costs of the candidates not known to collide (unchecked ones count as free).

        The tensor is the roadmap's own, updated by :meth:`check_edges`: read, don't write.
        """
        return self._optimistic

    @property
    def num_episodes(self) -> int:
        return self.config.shape[0]

    @property
    def device(self) -> torch.device:
        return self.config.device

    # ---------------------------------------------------------------- queries
    def nearest_goal_node(self) -> torch.Tensor:
        """long ``[E]``: the node of each episode (visited or sampled, not the goal node) whose achieved goal is
        nearest its desired goal."""
        dist = (self.achieved_goal - self.goal.unsqueeze(1).to(self.achieved_goal.dtype)).norm(dim=-1)
        return dist.masked_fill(~self.mask | self.is_goal_node, math.inf).argmin(-1)

    def queries(
        self, n_pairs: int = 10, generator: torch.Generator | None = None, own_query: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Start/goal queries: each episode's own, then ``n_pairs`` random node pairs.

        Random pairs draw the start uniformly among an episode's visited nodes
        and the goal uniformly among its other visited nodes (episodes with one
        visited node get none); sampled nodes are waypoints only. Each episode's
        own query goes from its first state to the node nearest its real goal
        (:meth:`nearest_goal_node`; it *is* the goal when the episode reached
        it), unless the two coincide; with goal nodes, a second one goes from
        the first state to the goal node.

        Args:
            n_pairs: random pairs per episode (>= 0).
            generator: torch generator of the draw (on any device).
            own_query: plan the episode's own queries (ours); ``False`` keeps the random
                pairs only, as the paper does (the same draws).

        Returns:
            ``(episode, start, goal)``, each long ``[Q]``, on the roadmap's device,
            grouped by episode, each episode's own query first.
        """
        check_nonnegative_int(n_pairs, name="n_pairs")
        E, device = self.num_episodes, self.device
        has_goal_node = self.is_goal_node.any(-1)
        n = self.num_visited.unsqueeze(-1)  # visited nodes come first
        start = torch.zeros(E, n_pairs + 1, dtype=torch.long, device=device)
        goal = self.nearest_goal_node().unsqueeze(-1).repeat(1, n_pairs + 1)
        if bool(has_goal_node.any()):
            # the goal node's query right after the own one; a start equal to it drops it below
            to_goal = torch.where(has_goal_node, self.num_nodes - 1, 0).unsqueeze(-1)
            start = torch.cat([start[:, :1], torch.zeros_like(to_goal), start[:, 1:]], dim=1)
            goal = torch.cat([goal[:, :1], to_goal, goal[:, 1:]], dim=1)
        if n_pairs:
            gdev = generator.device if generator is not None else device
            u = torch.rand(2, E, n_pairs, generator=generator, device=gdev).to(device)
            s = (u[0] * n).long().clamp(max=n - 1)
            # goal = start + an offset in 1..n-1, so that it differs from the start
            offset = 1 + (u[1] * (n - 1)).long().clamp(max=(n - 2).clamp(min=0))
            start[:, -n_pairs:] = s
            goal[:, -n_pairs:] = (s + offset) % n.clamp(min=1)
        if not own_query:
            start, goal = start[:, start.shape[1] - n_pairs:], goal[:, goal.shape[1] - n_pairs:]
        episode = torch.arange(E, device=device).unsqueeze(-1).expand_as(start)
        ok = start != goal
        return episode[ok], start[ok], goal[ok]
