"""Experience-based planner: planning time, success rate and demo length (paper, appendix A, Table A.1).

Measures :func:`~torchrl_silp.planning.plan_demonstrations` as the demo
buffer calls it: a lazy :class:`~torchrl_silp.planning.ExperienceRoadmap`
over each episode's collision-free states, the episode's own query (first
state -> node nearest its goal) plus ``--n-pairs`` random node pairs, exact
search (:func:`~torchrl_silp.planning.roadmap_paths`, Lazy PRM) and the
conversion to MDP demonstrations with InsertNodes. Roadmaps come from batches
of ``B`` rollouts of 50 steps of two kinds:

* ``random``: the env's random action, ``env.rollout(50, break_when_any_done=False)``;
* ``scripted``: a noisy joint-space controller towards each episode's goal
  configuration (``"goal_joint_position"``), so that most episodes reach or nearly
  reach their goal (the roadmaps of a policy that has learnt something).

A row that reaches its goal before step 50 is reset by the env and goes on
with a new episode (as in a collector's batch); the planner plans those too.
``ms/rollout`` divides a batch's time by its ``B`` 50-step rows, ``ms/episode``
by the ``E`` episodes they hold (``E >= B``); the goal check uses the
larger, ``ms/rollout``.

Tables:

1. time per batch, per rollout / episode and per plan (query) for
   ``B`` in {1, 16, 64} at ``d = 0.15``, split into roadmap, search and demos;
2. the ``d`` sweep of Table A.1 at ``B = 64``: planning success rate over all
   queries, over the random pairs and over the episodes' own queries, path
   edges and demo steps (after InsertNodes), time per plan and per rollout,
   the paper's figures beside;
3. exact search vs the paper's greedy walk on the same roadmaps and queries:
   violations (greedy found a path and exact found none or a longer one;
   must be 0) and the mean exact / greedy cost ratio;
4. the project's goal: <= 2 ms per rollout at ``B = 64`` and >= 100x faster
   than the paper's 0.218 s per plan.

``--search`` times the search algorithms alone on fully checked roadmaps
(``B = 64`` rollouts, ``d = 0.15``): Floyd-Warshall (``all_pairs_distances``
+ ``shortest_paths``), batched A* (``astar_paths``), Dijkstra (A* with a zero
heuristic), the greedy walk, and ``scipy.sparse.csgraph.dijkstra`` on the
block-diagonal graph when scipy is installed: the figures quoted in
:mod:`torchrl_silp.planning.search`.

Run::

    python benchmarks/planner.py                         # tables 1-4
    python benchmarks/planner.py --quick                 # fewer repeats, d in {0.10, 0.15, 0.40}
    python benchmarks/planner.py --search                # the search algorithms alone
    python benchmarks/planner.py --search --threads 1
    python benchmarks/planner.py --markdown planner.md   # also write the tables as markdown
    python benchmarks/planner.py --device cuda

On a machine busy with other work (load average above half the CPU count,
which the script warns about), torch's default intra-op threads spin-wait on
each other and the times come out several times too high; ``--threads 1``
suffers least.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass, field

import torch

from torchrl_silp import UR5eReachEnv
from torchrl_silp.models import TaskModel
from torchrl_silp.planning import (
    ExperienceRoadmap,
    Paths,
    all_pairs_distances,
    astar_paths,
    greedy_paths,
    paths_to_demonstrations,
    plan_demonstrations,
    roadmap_paths,
    shortest_paths,
)

_has_scipy = importlib.util.find_spec("scipy") is not None

STEPS = 50  # the env's episode length (max_steps; ours, the paper does not state it)
D_VALUES = (0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40)
# Table A.1 of the paper: d -> (planning SR, avg steps, planning time s per successful path)
PAPER = {
    0.10: (0.8, 6.39, 0.242),
    0.15: (0.8786, 5.614, 0.218),
    0.20: (0.9028, 5.064, 0.202),
    0.25: (0.9144, 4.676, 0.191),
    0.30: (0.9214, 4.402, 0.184),
    0.35: (0.9238, 4.152, 0.177),
    0.40: (0.924, 3.920, 0.171),
}
PAPER_S_PER_PLAN = PAPER[0.15][2]
GOAL_MS_PER_ROLLOUT = 2.0
GOAL_SPEEDUP = 100.0


# ---------------------------------------------------------------- rollouts
def near_goal_policy(model: TaskModel, noise: float, generator: torch.Generator):
    """Drive every env's joints towards its goal configuration at full speed, plus Gaussian noise.

    The straight joint-space line often runs into the box (start, obstacle and
    goal are drawn so that the box lies between them); the noise lets the arm
    slide off it, so episodes end near the goal by varied routes.
    """

    def policy(td):
        q = td[model.config_key]
        towards = ((td[model.goal_config_key] - q) / model.action_scale).clamp(-1, 1)
        jitter = torch.randn(q.shape, generator=generator, device=generator.device, dtype=q.dtype)
        td["action"] = (towards + noise * jitter.to(q.device)).clamp(-1, 1)
        return td

    return policy


def make_rollouts(kind: str, batch: int, seed: int, device: str, noise: float):
    """The task model and a ``[B, 50]`` rollout of the ``kind`` policy, deterministic in ``seed``."""
    env = UR5eReachEnv(num_envs=batch, seed=seed, device=device)
    model = env.model
    torch.manual_seed(seed)  # the env's random action draws from the global generator
    if kind == "random":
        episodes = env.rollout(STEPS, break_when_any_done=False)
    elif kind == "scripted":
        gen = torch.Generator(device=device).manual_seed(seed)
        episodes = env.rollout(STEPS, policy=near_goal_policy(model, noise, gen), break_when_any_done=False)
    else:
        raise ValueError(f"unknown rollout kind {kind!r}")
    return model, episodes


# ----------------------------------------------------------------- timing
def _sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def median_s(fn, reps: int, device: str) -> float:
    """Median seconds per call of ``fn`` after one warm-up call."""
    fn()
    _sync(device)
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


@dataclass
class Planned:
    """One planning pass of a batch, stage by stage, with what it produced."""

    roadmap: ExperienceRoadmap
    episode: torch.Tensor
    start: torch.Tensor
    goal: torch.Tensor
    paths: Paths
    demos: object
    stage_s: dict = field(default_factory=dict)


def plan_staged(model, episodes, d: float, n_pairs: int, seed: int, method: str, device: str) -> Planned:
    """``plan_demonstrations``' body, with the time of each stage.

    Kept step for step with :func:`plan_demonstrations` (same defaults, same
    generator use), so the stages add up to the timed call.
    """
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    roadmap = ExperienceRoadmap(model, episodes, d=d, lazy=True)
    _sync(device)
    t1 = time.perf_counter()
    episode, start, goal = roadmap.queries(n_pairs, gen)
    paths = roadmap_paths(roadmap, episode, start, goal, method=method)
    _sync(device)
    t2 = time.perf_counter()
    demos = paths_to_demonstrations(model, roadmap, episode, paths)
    _sync(device)
    t3 = time.perf_counter()
    stage_s = {"roadmap": t1 - t0, "search": t2 - t1, "demos": t3 - t2}
    return Planned(roadmap, episode, start, goal, paths, demos, stage_s)


def measure(model, episodes, d: float, n_pairs: int, seed: int, method: str, reps: int, device: str, stages: bool):
    """Median time of ``plan_demonstrations``, of its stages (``stages=True``), and one pass's plans.

    Every repeat builds a fresh roadmap with the same query draw: a lazy
    roadmap caches its edge checks, so reusing one would time a warm cache.
    """

    def call():
        gen = torch.Generator().manual_seed(seed)
        plan_demonstrations(model, episodes, d=d, n_pairs=n_pairs, method=method, generator=gen)

    total = median_s(call, reps, device)
    # already warm from the calls above
    passes = [plan_staged(model, episodes, d, n_pairs, seed, method, device) for _ in range(reps if stages else 1)]
    stage_s = {k: statistics.median(p.stage_s[k] for p in passes) for k in passes[0].stage_s}
    return total, stage_s, passes[-1]


# ------------------------------------------------------------- statistics
def own_queries(p: Planned) -> torch.Tensor:
    """bool ``[Q]``: the episodes' own queries (first state -> node nearest the goal).

    ``queries`` puts an episode's own query first in its group, dropping it
    when the first state is itself the nearest node; a random pair can never
    be (0, nearest) in that case, since its start and goal differ.
    """
    first = torch.ones_like(p.episode, dtype=torch.bool)
    first[1:] = p.episode[1:] != p.episode[:-1]
    nearest = p.roadmap.nearest_goal_node()[p.episode]
    return first & (p.start == 0) & (p.goal == nearest)


def _mean(x: torch.Tensor) -> float:
    return float(x.float().mean()) if x.numel() else math.nan


def plan_stats(p: Planned) -> dict:
    found = p.paths.found
    own = own_queries(p)
    moved = found & (p.paths.length >= 2)
    done = p.demos["next", "done"]
    n_demos = int(done.sum())
    return {
        "E": p.roadmap.num_episodes,
        "Q": found.numel(),
        "found": int(found.sum()),
        "nodes": _mean(p.roadmap.num_nodes),
        "reached": _mean(p.roadmap.reached),
        "sr": _mean(found),
        "sr_pairs": _mean(found[~own]),
        "sr_own": _mean(found[own]),
        "edges": _mean(p.paths.length[moved] - 1),
        "steps": p.demos.numel() / n_demos if n_demos else math.nan,
    }


def compare_exact_greedy(model, episodes, d: float, n_pairs: int, seed: int) -> dict:
    """Exact vs greedy on one roadmap and one query set.

    Both searches run on the same lazy roadmap: the exact search returns the
    shortest path of the fully checked roadmap and the greedy walk checks
    every edge it looks at, so neither sees an unchecked edge as free.
    """
    roadmap = ExperienceRoadmap(model, episodes, d=d, lazy=True)
    episode, start, goal = roadmap.queries(n_pairs, torch.Generator().manual_seed(seed))
    exact = roadmap_paths(roadmap, episode, start, goal, method="exact")
    greedy = roadmap_paths(roadmap, episode, start, goal, method="greedy")
    both = exact.found & greedy.found
    # tolerance: equal-cost paths (or one path summed in another order) differ by float32 rounding
    longer = both & (exact.cost > greedy.cost * (1 + 1e-5) + 1e-6)
    missed = greedy.found & ~exact.found
    ratio = exact.cost[both] / greedy.cost[both].clamp(min=1e-12)
    return {
        "Q": episode.numel(),
        "sr_exact": _mean(exact.found),
        "sr_greedy": _mean(greedy.found),
        "violations": int(longer.sum() + missed.sum()),
        "ratio": _mean(ratio),
        "shorter": _mean(exact.cost[both] < greedy.cost[both] * (1 - 1e-5)),
    }


# ------------------------------------------------------------------ output
class Report:
    """Tables printed as they are made, optionally written out as markdown."""

    def __init__(self):
        self.parts: list[str] = []

    def line(self, text: str = "") -> None:
        print(text, flush=True)
        self.parts.append(text)

    def table(self, title: str, header: list[str], rows: list[list[str]], notes: list[str] = ()) -> None:
        # Pipe tables padded to aligned columns: markdown that still reads as
        # plain text. The first column names a row (left), the others hold figures (right).
        widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]

        def fmt(cells):
            padded = [c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths))]
            return "| " + " | ".join(padded) + " |"

        rule = [":" + "-" * (w + 1) if i == 0 else "-" * (w + 1) + ":" for i, w in enumerate(widths)]
        self.line(f"\n### {title}\n")
        self.line(fmt(header))
        self.line("|" + "|".join(rule) + "|")
        for r in rows:
            self.line(fmt(r))
        if notes:
            self.line()
            for n in notes:
                self.line(n)

    def write(self, path: str) -> None:
        with open(path, "w") as f:
            f.write("\n".join(self.parts) + "\n")


def f(x: float, spec: str) -> str:
    return "-" if isinstance(x, float) and math.isnan(x) else format(x, spec)


# ----------------------------------------------------------- benchmarks
def bench_batches(args, report: Report) -> dict:
    """Table 1; returns the rows at the largest B for the goal check."""
    rows, at_max = [], {}
    for kind in args.rollouts:
        for b in args.batch_sizes:
            model, episodes = make_rollouts(kind, b, args.seed, args.device, args.noise)
            total, stages, p = measure(
                model, episodes, args.d, args.n_pairs, args.seed, "exact", args.reps, args.device, stages=True
            )
            s = plan_stats(p)
            ms = 1e3 * total
            rows.append([
                kind, str(b), str(s["E"]), f(s["reached"], ".2f"), f(s["nodes"], ".1f"), str(s["Q"]),
                f(s["sr"], ".3f"), f(ms, ".2f"),
                f(1e3 * stages["roadmap"], ".2f"), f(1e3 * stages["search"], ".2f"), f(1e3 * stages["demos"], ".2f"),
                f(ms / b, ".3f"), f(ms / s["E"], ".3f"), f(ms / s["Q"], ".4f"), f(ms / max(s["found"], 1), ".4f"),
                f(PAPER_S_PER_PLAN / (total / s["Q"]), ",.0f") + "x",
            ])
            if b == max(args.batch_sizes):
                at_max[kind] = (total, b, s)
    report.table(
        f"Planning time per batch of B rollouts of {STEPS} steps (d = {args.d}, exact, "
        f"n_pairs = {args.n_pairs}, median of {args.reps})",
        ["rollouts", "B", "E", "reached", "nodes/ep", "Q", "SR", "ms/batch", "roadmap", "search", "demos",
         "ms/rollout", "ms/episode", "ms/plan", "ms/found", "vs 0.218 s"],
        rows,
        [
            "E: episodes in the batch (a row that reached its goal early holds a second one); reached: fraction of",
            "episodes that reached their goal; Q: queries (own + random pairs); roadmap / search / demos: median ms",
            "of each stage; ms/plan: ms/batch / Q; ms/found: per path found (the paper times successful paths);",
            f"vs 0.218 s: the paper's {PAPER_S_PER_PLAN} s per plan at d = 0.15 over ms/plan.",
        ],
    )
    return at_max


def bench_distances(args, report: Report) -> None:
    """Tables 2 and 3: the d sweep and exact vs greedy, on one batch of each kind."""
    sweep, versus = [], []
    b = args.sweep_batch
    for kind in args.rollouts:
        model, episodes = make_rollouts(kind, b, args.seed, args.device, args.noise)
        for d in args.d_values:
            total, _, p = measure(model, episodes, d, args.n_pairs, args.seed, "exact", args.reps, args.device, False)
            t_greedy = median_s(
                lambda: plan_demonstrations(
                    model, episodes, d=d, n_pairs=args.n_pairs, method="greedy",
                    generator=torch.Generator().manual_seed(args.seed),
                ),
                args.reps, args.device,
            )
            s = plan_stats(p)
            paper = PAPER.get(round(d, 2), (math.nan,) * 3)
            sweep.append([
                kind, f"{d:.2f}", f(s["nodes"], ".1f"), str(s["Q"]), f(s["sr"], ".3f"), f(s["sr_pairs"], ".3f"),
                f(s["sr_own"], ".3f"), f(s["edges"], ".2f"), f(s["steps"], ".2f"),
                f(1e3 * total / s["Q"], ".4f"), f(1e3 * total / b, ".3f"),
                f(paper[0], ".3f"), f(paper[1], ".2f"), f(paper[2], ".3f"),
            ])
            c = compare_exact_greedy(model, episodes, d, args.n_pairs, args.seed)
            versus.append([
                kind, f"{d:.2f}", str(c["Q"]), f(c["sr_exact"], ".3f"), f(c["sr_greedy"], ".3f"),
                str(c["violations"]), f(c["ratio"], ".4f"), f(c["shorter"], ".3f"),
                f(1e3 * total / c["Q"], ".4f"), f(1e3 * t_greedy / c["Q"], ".4f"),
            ])
    report.table(
        f"Planning vs the roadmap distance d (Table A.1), B = {b} rollouts of {STEPS} steps, exact search",
        ["rollouts", "d (m)", "nodes/ep", "Q", "SR", "SR pairs", "SR own", "path edges", "demo steps",
         "ms/plan", "ms/rollout", "paper SR", "paper steps", "paper s/plan"],
        sweep,
        [
            "SR: fraction of queries with a path; SR pairs: over the random node pairs (the paper's queries);",
            "SR own: over the episodes' own queries (first state -> node nearest the goal); path edges: mean",
            "roadmap edges per path found; demo steps: mean transitions per demonstration after InsertNodes",
            "(cut at the first success); paper: Table A.1 (time per successful path, their hardware).",
        ],
    )
    report.table(
        f"Exact search vs the paper's greedy walk, same roadmaps and queries (B = {b})",
        ["rollouts", "d (m)", "Q", "SR exact", "SR greedy", "violations", "cost exact/greedy", "exact shorter",
         "exact ms/plan", "greedy ms/plan"],
        versus,
        [
            "violations: queries where greedy found a path and exact found none or a longer one (must be 0);",
            "cost exact/greedy: mean ratio of Paths.cost over queries both found; exact shorter: fraction of",
            "those where the exact path is strictly shorter; ms/plan: plan_demonstrations(method=...) / Q.",
        ],
    )
    bad = sum(int(r[5]) for r in versus)
    report.line(f"\nexact never longer than greedy: {'yes' if bad == 0 else 'NO'} ({bad} violations in all)")


def report_goal(at_max: dict, report: Report) -> None:
    rows = []
    for kind, (total, b, s) in at_max.items():
        per_rollout = 1e3 * total / b
        per_plan = total / s["Q"]
        speedup = PAPER_S_PER_PLAN / per_plan
        speedup_found = PAPER_S_PER_PLAN / (total / max(s["found"], 1))
        rows.append([
            kind, str(b), f(per_rollout, ".3f"), "yes" if per_rollout <= GOAL_MS_PER_ROLLOUT else "NO",
            f(1e3 * per_plan, ".4f"), f(speedup, ",.0f") + "x", "yes" if speedup >= GOAL_SPEEDUP else "NO",
            f(speedup_found, ",.0f") + "x",
        ])
    report.table(
        f"Goal: <= {GOAL_MS_PER_ROLLOUT:g} ms per rollout at the largest B, >= {GOAL_SPEEDUP:g}x the paper's "
        f"{PAPER_S_PER_PLAN} s per plan",
        ["rollouts", "B", "ms/rollout", "<= 2 ms", "ms/plan", "speed-up", ">= 100x", "speed-up per found path"],
        rows,
    )


# ------------------------------------------------------------ --search
def scipy_dijkstra(weights: torch.Tensor, episode, start, goal) -> torch.Tensor:
    """Path costs by ``scipy.sparse.csgraph.dijkstra`` on the block-diagonal graph of all episodes.

    Timed from the padded tensor (the CSR build is part of the cost) to the
    distances and predecessors of every distinct start; the path read-out, a
    Python loop over the predecessors, is left out (in scipy's favour).
    """
    import numpy as np
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    E, N, _ = weights.shape
    w = weights.cpu().numpy()
    e, i, j = np.nonzero(np.isfinite(w))
    graph = csr_matrix((w[e, i, j].astype(np.float64), (e * N + i, e * N + j)), shape=(E * N, E * N))
    src = (episode * N + start).cpu().numpy()
    sources, row = np.unique(src, return_inverse=True)
    dist, _ = dijkstra(graph, directed=True, indices=sources, return_predecessors=True)
    return torch.from_numpy(dist[row, (episode * N + goal).cpu().numpy()])


def bench_search(args, report: Report) -> None:
    b = args.sweep_batch
    for kind in args.rollouts:
        model, episodes = make_rollouts(kind, b, args.seed, args.device, args.noise)
        # fully checked: the algorithms alone, not the lazy edge checks between rounds
        roadmap = ExperienceRoadmap(model, episodes, d=args.d, lazy=False)
        episode, start, goal = roadmap.queries(args.n_pairs, torch.Generator().manual_seed(args.seed))
        w, tcp = roadmap.weights, roadmap.achieved_goal
        ref = shortest_paths(w, episode, start, goal)

        def agrees(cost: torch.Tensor) -> str:
            cost = cost.to(ref.cost.dtype).to(ref.cost.device)
            same_found = torch.equal(torch.isfinite(cost), ref.found)
            close = torch.allclose(cost[ref.found], ref.cost[ref.found], rtol=1e-5, atol=1e-6)
            return "yes" if same_found and close else "NO"

        zeros = torch.zeros_like(tcp)
        methods = [
            ("Floyd-Warshall + path read-out (shortest_paths)", lambda: shortest_paths(w, episode, start, goal), True),
            ("Floyd-Warshall distances only (all_pairs_distances)", lambda: all_pairs_distances(w), None),
            ("A*, TCP heuristic (astar_paths)", lambda: astar_paths(w, tcp, episode, start, goal), True),
            ("Dijkstra (astar_paths, zero heuristic)", lambda: astar_paths(w, zeros, episode, start, goal), True),
            ("greedy walk, not exact (greedy_paths)", lambda: greedy_paths(w, tcp, episode, start, goal), False),
        ]
        if _has_scipy:
            name = "scipy csgraph.dijkstra, CSR build + search"
            methods.append((name, lambda: scipy_dijkstra(w, episode, start, goal), True))
        rows, t_fw = [], None
        for name, fn, exact in methods:
            t = median_s(fn, args.reps, args.device)
            t_fw = t if t_fw is None else t_fw
            out = fn()
            if exact is None:
                check = "-"
            elif exact:
                check = agrees(out.cost if isinstance(out, Paths) else out)
            else:
                longer = out.found & (out.cost > ref.cost * (1 + 1e-5) + 1e-6)
                check = f"SR {_mean(out.found):.3f} vs {_mean(ref.found):.3f}, {_mean(longer[out.found]):.2f} longer"
            rows.append([name, f(1e3 * t, ".2f"), f(t / t_fw, ".2f") + "x", check])
        if not _has_scipy:
            rows.append(["scipy csgraph.dijkstra", "-", "-", "scipy not installed"])
        E, N = roadmap.mask.shape
        edges = int(roadmap.adjacency.sum()) // 2
        report.table(
            f"Search alone, {kind} rollouts: B = {b}, d = {args.d}, E = {E} graphs of <= {N} nodes "
            f"({_mean(roadmap.num_nodes):.1f} on average, {edges} free edges), Q = {episode.numel()} queries, "
            f"median of {args.reps}",
            ["method", "ms", "vs Floyd-Warshall", "same costs as Floyd-Warshall"],
            rows,
        )


# ------------------------------------------------------------------ main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="3 repeats, d in {0.10, 0.15, 0.40}")
    parser.add_argument("--search", action="store_true", help="time the search algorithms alone")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--sweep-batch", type=int, default=64, help="B of the d sweep and of --search")
    parser.add_argument("--d", type=float, default=0.15, help="roadmap distance of table 1 and --search (m)")
    parser.add_argument("--d-values", type=float, nargs="+", default=None, help=f"d sweep (default {D_VALUES})")
    parser.add_argument("--n-pairs", type=int, default=10, help="random start/goal pairs per episode")
    parser.add_argument("--rollouts", nargs="+", choices=["random", "scripted"], default=["random", "scripted"])
    parser.add_argument("--noise", type=float, default=0.4, help="action noise of the scripted policy")
    parser.add_argument("--reps", type=int, default=None, help="timed repeats (median); 10, or 3 with --quick")
    parser.add_argument("--markdown", metavar="PATH", help="also write the tables to PATH as markdown")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if args.reps is None:
        args.reps = 3 if args.quick else 10
    if args.d_values is None:
        args.d_values = (0.10, 0.15, 0.40) if args.quick else D_VALUES

    report = Report()
    dev = torch.device(args.device)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else (platform.processor() or platform.machine())
    report.line(
        f"torch {torch.__version__}, {args.device} ({where}), {torch.get_num_threads()} thread(s), "
        f"{os.cpu_count()} CPUs; seed {args.seed}"
    )
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    if load > 0.5 * (os.cpu_count() or 1):
        # oversubscribed intra-op threads spin-wait on each other: several times slower, not a bit
        report.line(
            f"WARNING: load average {load:.1f} on {os.cpu_count()} CPUs: other work competes for the cores, "
            "times are inflated (--threads 1 suffers least)"
        )
    if args.search:
        bench_search(args, report)
    else:
        at_max = bench_batches(args, report)
        bench_distances(args, report)
        report_goal(at_max, report)
    if args.markdown:
        report.write(args.markdown)
        print(f"\nwrote {args.markdown}")


if __name__ == "__main__":
    main()
