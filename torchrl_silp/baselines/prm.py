"""OMPL's PRM as the PRM-0.1 / PRM-1 baselines of the paper's Table 1, and as a demonstration source.

For each task, :class:`PRMPlanner` builds a fresh probabilistic roadmap (the
obstacle changes from task to task) in the three active joints, with the
env's collision checker as OMPL's state validity checker and the env's
subdivision edge check, batched in torch, as its motion validator. It stops at
its first solution or at the time budget. :class:`PathReplayPolicy` turns the
planned paths into action-bounded steps, and :func:`evaluate_prm` runs them
through :func:`~torchrl_silp.eval.evaluate` on the fixed test tasks, as the
learned policies are evaluated. :func:`collect_prm_demonstrations` keeps the
transitions of the successful executions on training tasks (BC-PRM).

OMPL is optional: ``pip install "torchrl_silp[planning]"`` (OMPL >= 1.7; the
nanobind bindings of 2.x are the ones exercised here).
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import time
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase

from torchrl_silp.envs.reach import UR5eReachEnv
from torchrl_silp.eval import DEFAULT_TEST_SEED, episode_outcomes, evaluate

_has_ompl = importlib.util.find_spec("ompl") is not None
if _has_ompl:
    import ompl.base as ob
    import ompl.geometric as og
    import ompl.util as ou

__all__ = [
    "PRMPlanner",
    "PathReplayPolicy",
    "path_to_actions",
    "evaluate_prm",
    "collect_prm_demonstrations",
]

# keys of a demonstration transition (recipes/bc.py trains on exactly these)
DEMO_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
             ("next", "terminated"), "episode")
# training tasks planned and executed per batch in collect_prm_demonstrations
_COLLECT_BATCH = 500


def _require_ompl(what: str) -> None:
    if not _has_ompl:
        raise ImportError(
            f"{what} needs OMPL, which is not installed: pip install \"torchrl_silp[planning]\""
        )


def _check_positive(name: str, value, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number of {unit}, got {value!r}")
    return float(value)


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    return value


def _check_bool(name: str, value) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be a bool, got {value!r}")
    return value


def _progress_bar(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError as err:  # tqdm comes with the recipes extra
        raise ImportError('progress=True needs tqdm: pip install "torchrl_silp[recipes]"') from err
    return tqdm(total=total, desc=desc)


@contextlib.contextmanager
def _ompl_log_level(level):
    # OMPL logs every solve() at INFO; a run plans thousands of tasks
    previous = ou.getLogLevel()
    ou.setLogLevel(level)
    try:
        yield
    finally:
        ou.setLogLevel(previous)


if _has_ompl:

    class _TorchMotionValidator(ob.MotionValidator):
        """An OMPL motion validator that checks an edge with one batched torch call.

        PRM's roadmap expansion also calls the ``checkMotion(s1, s2,
        lastValid)`` overload, which the OMPL 2.0.1 bindings do not forward
        to Python. It adds no edge this check would refuse: every edge of a
        1.5 s roadmap (~16k milestones, ~160k edges) under a validator
        refusing long and crossing edges passed that validator.
        """

        def __init__(self, si, motion_free):
            super().__init__(si)
            self._motion_free = motion_free

        def checkMotion(self, s1, s2):  # noqa: N802 (OMPL's name)
            return self._motion_free(s1, s2)


class PRMPlanner:
    """OMPL's PRM in the three active joints of a :class:`~torchrl_silp.envs.reach.UR5eReachEnv`.

    The configuration space is a 3-D ``RealVectorStateSpace`` bounded by the
    robot's joint limits. A configuration is valid when ``env.collides`` says
    it does not collide; the TCP leaving the workspace counts as a collision
    (as in the env's default ``workspace_exit="collision"``; with ``"block"``
    such a path could not be executed either). An edge is valid when
    ``env.edge_collision_free`` passes it: configurations at most
    ``edge_step`` apart, checked in one batched torch call.

    :meth:`plan` builds a fresh roadmap per task and stops at the first
    solution (OMPL's PRM does) or when ``budget_s`` has passed since the call
    began. Once the budget has passed the checkers refuse every further state
    and edge, so a roadmap step under way when time runs out ends at once
    (OMPL checks its time limit only between roadmap steps): the overrun is
    the one check under way, a millisecond or two, or tens of milliseconds
    when other processes starve this one of CPU. With
    ``simplify=True`` the path is then shortcut greedily (from each kept
    waypoint, straight to the farthest later one the edge check passes, all
    candidates in one batched call) within what is left of the budget.

    Args:
        env: the env whose collision checker and joint limits define the problem
            (its batch size does not matter: only its model functions are used).
        budget_s: planning time per task, seconds (paper: 0.1 and 1).
        seed: seeds OMPL's random generator once per :meth:`plan` call (a seed
            per call drawn from a generator seeded with it), so runs repeat as
            far as a timed, two-threaded planner allows; ``None`` leaves OMPL's
            time-based seed.
        edge_step: largest joint-space gap between the configurations an edge
            check tests (rad); the env's edge check defaults to 0.02.
        simplify: shortcut the roadmap path within the budget.

    Examples:
        >>> import pytest; _ = pytest.importorskip("ompl")  # the planning extra
        >>> from torchrl_silp import UR5eReachEnv
        >>> from torchrl_silp.baselines import PRMPlanner
        >>> env = UR5eReachEnv(seed=0)
        >>> task = env.sample_tasks(8)[6]  # its straight start -> goal segment is free
        >>> planner = PRMPlanner(env, budget_s=1.0, seed=0)
        >>> path, wall_s = planner.plan(task["q"], task["goal_q"], task["obstacle"])
        >>> path.shape, bool((path[0] == task["q"]).all() and (path[-1] == task["goal_q"]).all())
        (torch.Size([2, 3]), True)
    """

    def __init__(
        self,
        env: UR5eReachEnv,
        budget_s: float,
        *,
        seed: int | None = None,
        edge_step: float = 0.02,
        simplify: bool = True,
    ):
        _require_ompl("PRMPlanner")
        if not isinstance(env, UR5eReachEnv):
            raise TypeError(f"env must be a torchrl_silp.UR5eReachEnv, got {type(env).__name__}")
        self.env = env
        self.budget_s = _check_positive("budget_s", budget_s, "seconds")
        self.edge_step = _check_positive("edge_step", edge_step, "radians")
        self.seed = None if seed is None else _check_int("seed", seed, 0)
        self.simplify = _check_bool("simplify", simplify)
        self._seeds = None if seed is None else torch.Generator().manual_seed(seed)
        self._low = env.robot.joint_low.detach().cpu().tolist()
        self._high = env.robot.joint_high.detach().cpu().tolist()
        self._space = ob.RealVectorStateSpace(3)
        bounds = ob.RealVectorBounds(3)
        for j in range(3):
            bounds.setLow(j, self._low[j])
            bounds.setHigh(j, self._high[j])
        self._space.setBounds(bounds)

    def _as_vector(self, name: str, value, size: int) -> torch.Tensor:
        if not isinstance(value, torch.Tensor) or value.shape != (size,):
            raise ValueError(f"{name} must be a tensor of shape ({size},), got {getattr(value, 'shape', type(value))}")
        if not torch.isfinite(value).all():
            raise ValueError(f"{name} must be finite, got {value.tolist()}")
        return value.to(device=self.env.device, dtype=self.env.dtype)

    def _reseed(self) -> None:
        if self._seeds is None:
            return
        seed = int(torch.randint(1, 2**31 - 1, (1,), generator=self._seeds))
        # OMPL complains (without cause here) when the seed changes after its first use:
        # every RNG the new planner creates draws its own seed from the re-seeded generator
        with _ompl_log_level(ou.LogLevel.LOG_NONE):
            ou.RNG.setSeed(seed)

    def plan(
        self, start_q: torch.Tensor, goal_q: torch.Tensor, obstacle: torch.Tensor
    ) -> tuple[torch.Tensor | None, float]:
        """Plan from ``start_q`` to ``goal_q`` (each ``(3,)``) around ``obstacle`` (``(6,)`` AABB).

        Returns:
            ``(path, wall_s)``: the path, a float32 tensor ``(n, 3)`` on the
            env's device whose first row is ``start_q`` and last ``goal_q``, or
            ``None`` when no exact solution was found within the budget (or an
            end collides); and the wall time of the call in seconds.
        """
        t0 = time.perf_counter()
        deadline = t0 + self.budget_s
        env, step = self.env, self.edge_step
        start = self._as_vector("start_q", start_q, 3)
        goal = self._as_vector("goal_q", goal_q, 3)
        box = self._as_vector("obstacle", obstacle, 6)
        for name, q in (("start_q", start), ("goal_q", goal)):
            outside = [j for j in range(3) if not self._low[j] <= float(q[j]) <= self._high[j]]
            if outside:
                raise ValueError(f"{name} is outside the joint limits on joint(s) {outside}: {q.tolist()}")
        if bool(env.collides(torch.stack([start, goal]), box).any()):
            return None, time.perf_counter() - t0
        dtype, device = env.dtype, env.device

        def is_valid(state) -> bool:
            if time.perf_counter() > deadline:
                return False
            q = torch.tensor((state[0], state[1], state[2]), dtype=dtype, device=device)
            return not bool(env.collides(q, box))

        def motion_free(s1, s2) -> bool:
            if time.perf_counter() > deadline:
                return False
            ends = torch.tensor(((s1[0], s1[1], s1[2]), (s2[0], s2[1], s2[2])), dtype=dtype, device=device)
            return bool(env.edge_collision_free(ends[0], ends[1], box, step_size=step))

        path = None
        with _ompl_log_level(ou.LogLevel.LOG_WARN):
            self._reseed()
            setup = og.SimpleSetup(self._space)
            si = setup.getSpaceInformation()
            setup.setStateValidityChecker(is_valid)
            validator = _TorchMotionValidator(si, motion_free)
            si.setMotionValidator(validator)
            ends = [self._space.allocState(), self._space.allocState()]
            for state, q in zip(ends, (start, goal)):
                for j in range(3):
                    state[j] = float(q[j])
            setup.setStartAndGoalStates(ends[0], ends[1])
            setup.setPlanner(og.PRM(si))
            remaining = deadline - time.perf_counter()
            # bool(solve()) is True for an approximate solution too
            if remaining > 0 and setup.solve(remaining) and setup.haveExactSolutionPath():
                states = setup.getSolutionPath().getStates()
                path = torch.tensor([[s[0], s[1], s[2]] for s in states], dtype=dtype, device=device)
                path[0], path[-1] = start, goal
            del setup, si, validator
        if path is not None and self.simplify:
            path = self._shortcut(path, box, deadline)
        return (None if path is None else path.float()), time.perf_counter() - t0

    def _shortcut(self, path: torch.Tensor, box: torch.Tensor, deadline: float) -> torch.Tensor:
        keep, i, last = [0], 0, path.shape[0] - 1
        while i < last:
            if time.perf_counter() > deadline:
                keep.extend(range(i + 1, last + 1))
                break
            ahead = path[i + 1:]
            free = self.env.edge_collision_free(path[i].expand_as(ahead), ahead, box, step_size=self.edge_step)
            hits = free.nonzero()
            # the roadmap edge i -> i+1 passed this check already (up to float32 rounding)
            i += 1 + (int(hits[-1]) if hits.numel() else 0)
            keep.append(i)
        return path[keep]


def path_to_actions(path: torch.Tensor, action_scale: float = UR5eReachEnv.ACTION_SCALE) -> torch.Tensor:
    """Actions ``(k, 3)`` in ``[-1, 1]`` that move the arm along a joint-space path.

    Each segment ``path[i] -> path[i + 1]`` is split into
    ``ceil(max|dq| / action_scale)`` equal steps, so no joint moves more than
    ``action_scale`` rad per step; the action of a step is its joint motion
    divided by ``action_scale``. Repeated waypoints give no step.

    Examples:
        >>> import torch
        >>> from torchrl_silp import UR5eReachEnv
        >>> path = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.1, 0.0], [0.3, -0.1, 0.05]])
        >>> actions = path_to_actions(path)
        >>> actions.shape  # ceil(0.3 / 0.125) = 3 steps, then 1
        torch.Size([4, 3])
        >>> torch.allclose(actions.sum(0) * UR5eReachEnv.ACTION_SCALE, path[-1] - path[0])
        True
    """
    if not isinstance(path, torch.Tensor) or path.ndim != 2 or path.shape[-1] != 3 or path.shape[0] < 1:
        raise ValueError(f"path must be a tensor of shape (n, 3) with n >= 1, got {getattr(path, 'shape', type(path))}")
    _check_positive("action_scale", action_scale, "radians")
    delta = path[1:] - path[:-1]
    n = torch.ceil(delta.abs().amax(-1) / action_scale).long()
    actions = (delta / (n.clamp(min=1).unsqueeze(-1) * action_scale)).clamp(-1.0, 1.0)
    return actions.repeat_interleave(n, dim=0)


class PathReplayPolicy:
    """Replays one joint-space path per env of a batched :class:`~torchrl_silp.envs.reach.UR5eReachEnv`.

    A callable ``td -> td`` writing ``"action"``: at an env's step ``t`` (its
    step counter) it plays the ``t``-th action of :func:`path_to_actions` of
    that env's path, and zeros once the path is done, past ``env.max_steps``
    actions (the episode is truncated there), or for an env without a path
    (``None``: its plan failed).

    Args:
        env: the env the paths run in, batch ``[B]``.
        paths: ``B`` paths ``(n_i, 3)`` starting at the configurations of the
            env's episodes, or ``None``.

    Attributes:
        steps: long ``[B]``: the actions each path needs (0 without a path).

    Examples:
        >>> import torch
        >>> from torchrl_silp import UR5eReachEnv
        >>> env = UR5eReachEnv(num_envs=2, seed=0, collision_type=0)
        >>> td = env.reset()
        >>> straight = [torch.stack([q, g]) for q, g in zip(td["observation"][:, :3], td["goal_q"])]
        >>> policy = PathReplayPolicy(env, [straight[0], None])
        >>> rollout = env.rollout(env.max_steps, policy, auto_reset=False, tensordict=td)
        >>> bool(rollout["action"][1].eq(0).all()), policy.steps[1].item()
        (True, 0)
    """

    def __init__(self, env: UR5eReachEnv, paths: Sequence[torch.Tensor | None]):
        if not isinstance(env, UR5eReachEnv):
            raise TypeError(f"env must be a torchrl_silp.UR5eReachEnv, got {type(env).__name__}")
        if len(env.batch_size) != 1:
            raise ValueError(f"env must have a 1-D batch size, got {tuple(env.batch_size)}")
        n = env.batch_size[0]
        if len(paths) != n:
            raise ValueError(f"paths must hold one path (or None) per env: {n}, got {len(paths)}")
        T = env.max_steps
        self.env = env
        # one zero row past the last step: what an env plays once its path is done
        self._actions = torch.zeros(n, T + 1, 3, dtype=env.dtype, device=env.device)
        self.steps = torch.zeros(n, dtype=torch.long, device=env.device)
        for b, path in enumerate(paths):
            if path is None:
                continue
            actions = path_to_actions(path.to(device=env.device, dtype=env.dtype))
            self.steps[b] = actions.shape[0]
            k = min(T, actions.shape[0])
            self._actions[b, :k] = actions[:k]
        self._rows = torch.arange(n, device=env.device)

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        t = self.env.state["step_count"].reshape(-1).clamp(max=self.env.max_steps)
        return tensordict.set("action", self._actions[self._rows, t])


def _plan_and_execute(env: UR5eReachEnv, planner: PRMPlanner, n_plan: int, bar) -> tuple[dict, TensorDictBase, dict]:
    """Plan the first ``n_plan`` tasks of the env's next reset, then run every path through ``evaluate``."""
    n = env.batch_size[0]
    # the tasks the env's next reset draws: sample_tasks from a copy of its generator
    generator = torch.Generator(device=env.device)
    generator.set_state(env.rng.get_state())
    tasks = env.sample_tasks(n, generator=generator)
    paths: list[torch.Tensor | None] = [None] * n
    times = torch.zeros(n_plan, dtype=torch.float64)
    for i in range(n_plan):
        paths[i], times[i] = planner.plan(tasks["q"][i], tasks["goal_q"][i], tasks["obstacle"][i])
        if bar is not None:
            bar.update(1)
    policy = PathReplayPolicy(env, paths)
    metrics, rollout = evaluate(policy, env=env, return_rollout=True)
    if not torch.equal(rollout[:, 0]["observation"][:, :3], tasks["q"]):
        raise RuntimeError("the env's reset drew other tasks than the ones planned")
    solved = torch.tensor([p is not None for p in paths[:n_plan]], dtype=torch.bool)
    return metrics, rollout, {"planning_time_s": times, "solved": solved, "path_steps": policy.steps[:n_plan].cpu()}


def evaluate_prm(
    budget_s: float,
    n_tasks: int = 1000,
    seed: int = DEFAULT_TEST_SEED,
    *,
    ompl_seed: int = 0,
    max_steps: int = 50,
    workspace_exit: str = "collision",
    task_branch: str = "front",
    device: torch.device | str | None = None,
    progress: bool = False,
    edge_step: float = 0.02,
    simplify: bool = True,
) -> dict:
    """PRM on the fixed test tasks, executed and scored like a learned policy by :func:`~torchrl_silp.eval.evaluate`.

    The test env is the one :func:`~torchrl_silp.eval.evaluate` builds
    (``collision_type=0``: a collision ends the episode as a failure). Each
    task is planned in turn by a :class:`PRMPlanner`, then all paths run as
    one batch through :class:`PathReplayPolicy` (a failed plan: zero
    actions). A path needing more than ``max_steps`` steps is cut there, as
    the episode is.

    Args:
        budget_s: planning time per task, seconds (PRM-0.1: 0.1, PRM-1: 1).
        n_tasks: number of test tasks (paper: 1000).
        seed: seed of the test tasks.
        ompl_seed: seed of OMPL's random generator (see :class:`PRMPlanner`).
        max_steps: episode length (paper: 50).
        workspace_exit: ``"collision"`` or ``"block"`` (see :class:`~torchrl_silp.UR5eReachEnv`).
        task_branch: ``"front"`` or ``"any"`` (see :class:`~torchrl_silp.UR5eReachEnv`).
        device: device of the test env.
        progress: a tqdm bar over the tasks planned.
        edge_step: the planner's edge check resolution (rad).
        simplify: shortcut the paths within the budget (see :class:`PRMPlanner`).

    Returns:
        The keys of :func:`~torchrl_silp.eval.evaluate`, with
        ``time_per_rollout_s`` = mean planning time + execution time per
        task, and ``execution_time_per_rollout_s`` (the latter alone),
        ``planning_time_s`` (mean), ``planning_time_max_s``, ``solved_rate``
        (exact solutions found), ``path_steps_mean`` (env steps of the solved
        tasks' paths) and ``budget_s``.
    """
    _require_ompl("evaluate_prm")
    _check_int("n_tasks", n_tasks, 1)
    _check_int("seed", seed, 0)
    _check_bool("progress", progress)
    env = UR5eReachEnv(
        num_envs=n_tasks, seed=seed, max_steps=max_steps, collision_type=0,
        workspace_exit=workspace_exit, task_branch=task_branch, device=device,
    )
    planner = PRMPlanner(env, budget_s, seed=ompl_seed, edge_step=edge_step, simplify=simplify)
    bar = _progress_bar(n_tasks, f"PRM-{budget_s:g}", progress)
    try:
        metrics, _, info = _plan_and_execute(env, planner, n_tasks, bar)
    finally:
        if bar is not None:
            bar.close()
    times, solved, steps = info["planning_time_s"], info["solved"], info["path_steps"]
    planning = times.mean().item()
    return {
        **metrics,
        "time_per_rollout_s": planning + metrics["time_per_rollout_s"],
        "execution_time_per_rollout_s": metrics["time_per_rollout_s"],
        "planning_time_s": planning,
        "planning_time_max_s": times.max().item(),
        "solved_rate": solved.float().mean().item(),
        "path_steps_mean": steps[solved].float().mean().item() if solved.any() else float("nan"),
        "budget_s": float(budget_s),
    }


def collect_prm_demonstrations(
    n_episodes: int,
    budget_s: float = 1.0,
    *,
    seed: int = 0,
    max_steps: int = 50,
    workspace_exit: str = "collision",
    task_branch: str = "front",
    device: torch.device | str | None = None,
    progress: bool = False,
    edge_step: float = 0.02,
    simplify: bool = True,
) -> tuple[TensorDictBase, dict]:
    """Demonstrations for behaviour cloning (BC-PRM): PRM's successful executions on training tasks.

    ``n_episodes`` tasks of a ``UR5eReachEnv`` seeded with ``seed`` (the
    training distribution, not the test tasks) are planned (OMPL seeded with
    ``seed`` too) and executed as in :func:`evaluate_prm`, in batches of up to
    500; the transitions of the episodes that reach the goal are kept, up to
    and including the successful step.

    Args:
        n_episodes: tasks attempted.
        budget_s: planning time per task, seconds (paper: 1).
        seed: seed of the training tasks and of OMPL.
        max_steps, workspace_exit, task_branch, device, progress, edge_step, simplify:
            as in :func:`evaluate_prm`.

    Returns:
        ``(demos, stats)``: a flat TensorDict ``[N]`` of transitions with
        ``"observation"``, ``"action"``, ``("next", "observation")``,
        ``("next", "reward")``, ``("next", "done")``, ``("next",
        "terminated")`` and ``"episode"`` (long: the attempt's index in
        ``0 .. n_episodes - 1``), episodes one after the other, steps in
        order; ``stats`` holds ``n_attempted``, ``n_kept`` (successful
        episodes), ``n_transitions``, ``success_rate``, ``solved_rate``,
        ``planning_s`` (total), ``planning_time_max_s`` and ``wall_s``.
    """
    _require_ompl("collect_prm_demonstrations")
    start = time.perf_counter()
    _check_int("n_episodes", n_episodes, 1)
    _check_int("seed", seed, 0)
    _check_bool("progress", progress)
    env = UR5eReachEnv(
        num_envs=min(n_episodes, _COLLECT_BATCH), seed=seed, max_steps=max_steps, collision_type=0,
        workspace_exit=workspace_exit, task_branch=task_branch, device=device,
    )
    planner = PRMPlanner(env, budget_s, seed=seed, edge_step=edge_step, simplify=simplify)
    bar = _progress_bar(n_episodes, f"PRM-{budget_s:g} demos", progress)
    kept, times, solved = [], [], []
    attempted = n_kept = 0
    try:
        while attempted < n_episodes:
            take = min(env.batch_size[0], n_episodes - attempted)
            _, rollout, info = _plan_and_execute(env, planner, take, bar)
            alive, success, _ = episode_outcomes(rollout)
            success[take:] = False  # tasks of the last batch that were not wanted (not planned)
            episode = torch.arange(attempted, attempted + rollout.batch_size[0], device=rollout.device)
            rollout.set("episode", episode.unsqueeze(-1).expand(rollout.batch_size))
            kept.append(rollout[alive & success.unsqueeze(-1)].select(*DEMO_KEYS))
            times.append(info["planning_time_s"])
            solved.append(info["solved"])
            attempted += take
            n_kept += int(success.sum())
    finally:
        if bar is not None:
            bar.close()
    demos = torch.cat(kept)
    times, solved = torch.cat(times), torch.cat(solved)
    stats = {
        "n_attempted": attempted,
        "n_kept": n_kept,
        "n_transitions": demos.numel(),
        "success_rate": n_kept / attempted,
        "solved_rate": solved.float().mean().item(),
        "planning_s": times.sum().item(),
        "planning_time_max_s": times.max().item(),
        "wall_s": time.perf_counter() - start,
    }
    return demos, stats
