"""OMPL's PRM as the PRM-0.1 / PRM-1 baselines of the paper's Table 1, and as a demonstration source.

For each task, :class:`PRMPlanner` builds a fresh probabilistic roadmap (the
scene changes from task to task) in the configuration space of a
:class:`~torchrl_silp.models.TaskModel`, whatever its ``config_dim``: the
model's collision test is OMPL's state validity checker, and the model's motion
check (:meth:`~torchrl_silp.models.TaskModel.segment_collision_free`, the test
the env judges its steps with) is its motion validator. It stops at its first
solution or at the time budget. :class:`PathReplayPolicy` turns the planned
paths into action-bounded steps, and :func:`evaluate_prm` runs them through
:func:`~torchrl_silp.eval.evaluate` on the fixed test tasks, as the learned
policies are evaluated. :func:`collect_prm_demonstrations` turns the
successful executions on training tasks into demonstration transitions
(BC-PRM), built with the model as :func:`~torchrl_silp.planning.plan_demonstrations`
builds its own.

OMPL is optional: ``pip install "torchrl_silp[planning]"`` (OMPL >= 1.7; the
nanobind bindings of 2.x are the ones exercised here).
"""

from __future__ import annotations

import contextlib
import importlib.util
import time
from collections.abc import Iterator, Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_silp.data.demo_buffer import transition_keys
from torchrl_silp.eval import DEFAULT_TEST_SEED, evaluate
from torchrl_silp.models.base import TaskModel, as_model
from torchrl_silp.planning.demos import demo_start_flags
from torchrl_silp.validation import check_bool, check_nonnegative_int, check_positive_float, check_positive_int

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
    "prm_demonstration_batches",
    "prm_demonstration_stats",
]

# training tasks planned and executed per batch in collect_prm_demonstrations
_COLLECT_BATCH = 500


def _require_ompl(what: str) -> None:
    if not _has_ompl:
        raise ImportError(
            f"{what} needs OMPL, which is not installed: pip install \"torchrl_silp[planning]\""
        )


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
    """OMPL's PRM in the configuration space of a :class:`~torchrl_silp.models.TaskModel`.

    The configuration space is a ``RealVectorStateSpace(model.config_dim)``
    bounded by the model's joint limits (``model.config_low`` /
    ``model.config_high``). A configuration is valid when ``model.collides``
    says it does not collide in the task's scene (every collision reason of
    the model counts: for :class:`~torchrl_silp.models.UR5eReach` the TCP
    leaving the workspace too, which the env could not execute under either
    ``workspace_exit``). An edge is valid when
    :meth:`~torchrl_silp.models.TaskModel.segment_collision_free` passes it:
    configurations at most ``edge_step`` apart, each with the model's
    Lipschitz margin (the test the env judges its steps with), in one batched
    torch call.

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

    The planner checks on the model's device, with the model's dtype (one
    configuration at a time: the CPU is faster).

    Args:
        model: the task model whose collision test and joint limits define the
            problem (or an env holding one as ``.model``).
        budget_s: planning time per task, seconds (paper: 0.1 and 1).
        seed: seeds OMPL's random generator once per :meth:`plan` call (a seed
            per call drawn from a generator seeded with it), so runs repeat as
            far as a timed, two-threaded planner allows; ``None`` leaves OMPL's
            time-based seed.
        edge_step: largest joint-space gap between the configurations an edge
            check tests (rad); ``None``: the model's ``motion_resolution``, the
            resolution the env's step check uses.
        simplify: shortcut the roadmap path within the budget.

    Examples:
        >>> import pytest; _ = pytest.importorskip("ompl")  # the planning extra
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> from torchrl_silp.baselines import PRMPlanner
        >>> model = UR5eReach()
        >>> task = model.sample_tasks(8, torch.Generator().manual_seed(0))[0]  # a free start -> goal segment
        >>> planner = PRMPlanner(model, budget_s=1.0, seed=0)
        >>> start, goal = task["joint_position"], task["goal_joint_position"]
        >>> path, wall_s = planner.plan(start, goal, task.select(*model.scene_keys))
        >>> path.shape, bool((path[0] == start).all() and (path[-1] == goal).all())
        (torch.Size([2, 3]), True)
    """

    def __init__(
        self,
        model: TaskModel,
        budget_s: float,
        *,
        seed: int | None = None,
        edge_step: float | None = None,
        simplify: bool = True,
    ):
        _require_ompl("PRMPlanner")
        self.model = model = as_model(model)
        self.budget_s = check_positive_float(budget_s, name="budget_s", unit="seconds")
        self.edge_step = model.motion_resolution if edge_step is None else check_positive_float(
            edge_step, name="edge_step", unit="radians")
        self.seed = check_nonnegative_int(seed, name="seed", optional=True)
        self.simplify = check_bool(simplify, name="simplify")
        self._seeds = None if seed is None else torch.Generator().manual_seed(seed)
        self.dim = D = int(model.config_dim)
        self._low = model.config_low.detach().double().cpu().reshape(D).tolist()
        self._high = model.config_high.detach().double().cpu().reshape(D).tolist()
        self._space = ob.RealVectorStateSpace(D)
        bounds = ob.RealVectorBounds(D)
        for j in range(D):
            bounds.setLow(j, self._low[j])
            bounds.setHigh(j, self._high[j])
        self._space.setBounds(bounds)
        # the edge check's margin rests on a Lipschitz bound a model estimates once, on first
        # use (0.1-1 s): paid here, not out of the first task's budget
        model.motion_margin(self.edge_step)

    def _as_vector(self, name: str, value) -> torch.Tensor:
        D = self.dim
        if not isinstance(value, torch.Tensor) or value.shape != (D,):
            raise ValueError(f"{name} must be a tensor of shape ({D},), got {getattr(value, 'shape', type(value))}")
        if not torch.isfinite(value).all():
            raise ValueError(f"{name} must be finite, got {value.tolist()}")
        return value.to(device=self.model.device, dtype=self.model.dtype)

    def _as_scene(self, scene) -> TensorDictBase:
        model = self.model
        if not isinstance(scene, TensorDictBase) or scene.batch_dims != 0:
            raise ValueError(
                f"scene must be a TensorDict with batch size [] holding the scene keys {model.scene_keys}, "
                f"got {type(scene).__name__}" + (f" of batch size {list(scene.batch_size)}" if isinstance(scene, TensorDictBase) else "")
            )
        for key, shape in model.scene_shapes.items():
            value = scene.get(key, None)
            if not isinstance(value, torch.Tensor) or value.shape != tuple(shape):
                raise ValueError(f"scene[{key!r}] must be a tensor of shape {tuple(shape)}, got {getattr(value, 'shape', None)}")
            if value.is_floating_point() and not torch.isfinite(value).all():
                raise ValueError(f"scene[{key!r}] must be finite, got {value.tolist()}")
        out = scene.select(*model.scene_keys)
        return out.apply(lambda x: x.to(device=model.device, dtype=model.dtype) if x.is_floating_point() else x.to(model.device))

    def skip(self, n_calls: int) -> None:
        """Move the per-call seeds on as ``n_calls`` :meth:`plan` calls would, without planning.

        A collection resumed at task ``n`` plans each later task with the seed
        that the uninterrupted one would have used.
        """
        check_nonnegative_int(n_calls, name="n_calls")
        if self._seeds is not None:
            for _ in range(n_calls):
                self._next_seed()

    def _next_seed(self) -> int:
        return int(torch.randint(1, 2**31 - 1, (1,), generator=self._seeds))

    def _reseed(self) -> None:
        if self._seeds is None:
            return
        seed = self._next_seed()
        # OMPL complains (without cause here) when the seed changes after its first use:
        # every RNG the new planner creates draws its own seed from the re-seeded generator
        with _ompl_log_level(ou.LogLevel.LOG_NONE):
            ou.RNG.setSeed(seed)

    def plan(
        self, start: torch.Tensor, goal: torch.Tensor, scene: TensorDictBase
    ) -> tuple[torch.Tensor | None, float]:
        """Plan from ``start`` to ``goal`` (each ``(config_dim,)``) in ``scene``.

        Args:
            start, goal: configurations within the model's joint limits.
            scene: a TensorDict of batch size ``[]`` with the model's scene keys
                (e.g. ``task.select(*model.scene_keys)``; further keys are ignored).

        Returns:
            ``(path, wall_s)``: the path, a float32 tensor ``(n, config_dim)``
            on the model's device whose first row is ``start`` and last
            ``goal``, or ``None`` when no exact solution was found within the
            budget (or an end collides); and the wall time of the call in seconds.
        """
        t0 = time.perf_counter()
        deadline = t0 + self.budget_s
        model, step, D = self.model, self.edge_step, self.dim
        start = self._as_vector("start", start)
        goal = self._as_vector("goal", goal)
        scene = self._as_scene(scene)
        for name, q in (("start", start), ("goal", goal)):
            outside = [j for j in range(D) if not self._low[j] <= float(q[j]) <= self._high[j]]
            if outside:
                raise ValueError(f"{name} is outside the joint limits on joint(s) {outside}: {q.tolist()}")
        if bool(model.collides(torch.stack([start, goal]), scene.expand(2)).any()):
            return None, time.perf_counter() - t0
        dtype, device = model.dtype, model.device
        scene1 = scene.expand(1)

        def is_valid(state) -> bool:
            if time.perf_counter() > deadline:
                return False
            q = torch.tensor([state[j] for j in range(D)], dtype=dtype, device=device)
            return not bool(model.collides(q, scene))

        def motion_free(s1, s2) -> bool:
            if time.perf_counter() > deadline:
                return False
            ends = torch.tensor([[s1[j] for j in range(D)], [s2[j] for j in range(D)]], dtype=dtype, device=device)
            return bool(model.segment_collision_free(ends[:1], ends[1:], scene1, step))

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
                for j in range(D):
                    state[j] = float(q[j])
            setup.setStartAndGoalStates(ends[0], ends[1])
            setup.setPlanner(og.PRM(si))
            remaining = deadline - time.perf_counter()
            # bool(solve()) is True for an approximate solution too
            if remaining > 0 and setup.solve(remaining) and setup.haveExactSolutionPath():
                states = setup.getSolutionPath().getStates()
                path = torch.tensor([[s[j] for j in range(D)] for s in states], dtype=dtype, device=device)
                path[0], path[-1] = start, goal
            del setup, si, validator
        if path is not None and self.simplify:
            path = self._shortcut(path, scene, deadline)
        return (None if path is None else path.float()), time.perf_counter() - t0

    def _shortcut(self, path: torch.Tensor, scene: TensorDictBase, deadline: float) -> torch.Tensor:
        keep, i, last = [0], 0, path.shape[0] - 1
        while i < last:
            if time.perf_counter() > deadline:
                keep.extend(range(i + 1, last + 1))
                break
            ahead = path[i + 1:]
            free = self.model.segment_collision_free(
                path[i].expand_as(ahead), ahead, scene.expand(ahead.shape[0]), self.edge_step
            )
            hits = free.nonzero()
            # the roadmap edge i -> i+1 passed this check already (up to float32 rounding)
            i += 1 + (int(hits[-1]) if hits.numel() else 0)
            keep.append(i)
        return path[keep]


def path_to_actions(path: torch.Tensor, action_scale: float) -> torch.Tensor:
    """Actions ``(k, D)`` in ``[-1, 1]`` that move a configuration along a joint-space path ``(n, D)``.

    Each segment ``path[i] -> path[i + 1]`` is split into
    ``ceil(max|dq| / action_scale)`` equal steps, so no joint moves more than
    ``action_scale`` rad per step (a task model's ``action_scale``); the action
    of a step is its joint motion divided by ``action_scale``. Repeated
    waypoints give no step.

    Examples:
        >>> import torch
        >>> path = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.1, 0.0], [0.3, -0.1, 0.05]])
        >>> actions = path_to_actions(path, 0.125)
        >>> actions.shape  # ceil(0.3 / 0.125) = 3 steps, then 1
        torch.Size([4, 3])
        >>> torch.allclose(actions.sum(0) * 0.125, path[-1] - path[0])
        True
    """
    if not isinstance(path, torch.Tensor) or path.ndim != 2 or path.shape[-1] < 1 or path.shape[0] < 1:
        raise ValueError(f"path must be a tensor of shape (n, D) with n, D >= 1, got {getattr(path, 'shape', type(path))}")
    if not path.is_floating_point() or not bool(torch.isfinite(path).all()):
        raise ValueError("path must be a finite floating tensor")
    check_positive_float(action_scale, name="action_scale", unit="radians")
    delta = path[1:] - path[:-1]
    n = torch.ceil(delta.abs().amax(-1) / action_scale).long()
    actions = (delta / (n.clamp(min=1).unsqueeze(-1) * action_scale)).clamp(-1.0, 1.0)
    return actions.repeat_interleave(n, dim=0)


class PathReplayPolicy:
    """Replays one joint-space path per row of a batched env over a :class:`~torchrl_silp.models.TaskModel`.

    A callable ``td -> td`` writing ``"action"``: at a row's step ``t`` (its
    ``"step_count"`` in the TensorDict it is called with, as a
    :class:`~torchrl_silp.envs.ReachEnv` keeps it) it plays the ``t``-th
    action of :func:`path_to_actions` of that row's path, and zeros once the
    path is done or for a row without a path (``None``: its plan failed). The
    env truncates a path longer than its episode.

    Args:
        model: the task model (its ``action_scale`` and ``config_dim``; or an env holding one).
        paths: one path ``(n_i, config_dim)`` per row of the batch ``[B]`` the policy is
            called on, starting at that row's configuration, or ``None``.

    Attributes:
        steps: long ``[B]``: the actions each path needs (0 without a path).

    Examples:
        >>> import torch
        >>> from torchrl_silp.envs import ReachEnv
        >>> from torchrl_silp.models import UR5eReach
        >>> env = ReachEnv(UR5eReach(), num_envs=2, seed=0)
        >>> td = env.reset()
        >>> straight = torch.stack([td["joint_position"][0], td["goal_joint_position"][0]])
        >>> policy = PathReplayPolicy(env.model, [straight, None])
        >>> rollout = env.rollout(env.max_steps, policy, auto_reset=False, tensordict=td)
        >>> bool(rollout["action"][1].eq(0).all()), policy.steps[1].item()
        (True, 0)
    """

    def __init__(self, model: TaskModel, paths: Sequence[torch.Tensor | None]):
        model = as_model(model)
        if isinstance(paths, torch.Tensor) or not isinstance(paths, Sequence) or len(paths) < 1:
            raise ValueError(f"paths must be a non-empty sequence of paths (or None), got {type(paths).__name__}")
        D, n = model.config_dim, len(paths)
        device, dtype = model.device, model.dtype
        actions = []
        for b, path in enumerate(paths):
            if path is None:
                actions.append(None)
                continue
            if not isinstance(path, torch.Tensor) or path.ndim != 2 or path.shape[-1] != D:
                raise ValueError(f"paths[{b}] must be None or a tensor of shape (n, {D}), got {getattr(path, 'shape', type(path))}")
            actions.append(path_to_actions(path.to(device=device, dtype=dtype), model.action_scale))
        self.steps = torch.tensor([0 if a is None else a.shape[0] for a in actions], dtype=torch.long, device=device)
        # one zero row past the longest path: what a row plays once its path is done
        self._actions = torch.zeros(n, int(self.steps.max()) + 1, D, dtype=dtype, device=device)
        for b, a in enumerate(actions):
            if a is not None:
                self._actions[b, : a.shape[0]] = a
        self._rows = torch.arange(n, device=device)
        self.action_dim = D

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        n = self._rows.numel()
        if tuple(tensordict.batch_size) != (n,):
            raise ValueError(f"the paths hold one path per row of a batch [{n}], called on a batch {list(tensordict.batch_size)}")
        count = tensordict.get("step_count", None)
        if count is None:
            raise KeyError("PathReplayPolicy reads the step counter \"step_count\" of the TensorDict it is called with")
        t = count.reshape(n).to(self._actions.device).clamp(0, self._actions.shape[1] - 1)
        return tensordict.set("action", self._actions[self._rows, t].to(tensordict.device or self._actions.device))


def _plan_tasks(planner: PRMPlanner, tasks: TensorDictBase, n_plan: int, bar) -> tuple[list, torch.Tensor]:
    """Plan the first ``n_plan`` tasks; the rest get no path."""
    model = planner.model
    paths: list[torch.Tensor | None] = [None] * tasks.batch_size[0]
    times = torch.zeros(n_plan, dtype=torch.float64)
    scenes = tasks.select(*model.scene_keys)
    starts, goals = tasks.get(model.config_key), tasks.get(model.goal_config_key)
    for i in range(n_plan):
        paths[i], times[i] = planner.plan(starts[i], goals[i], scenes[i])
        if bar is not None:
            bar.update(1)
    return paths, times


def _device(model: TaskModel, device) -> torch.device:
    device = model.device if device is None else torch.device(device)
    if model.device != device:
        model.to(device)  # as ReachEnv(model, device=device) does
    return device


def evaluate_prm(
    model: TaskModel,
    budget_s: float,
    n_tasks: int = 1000,
    seed: int = DEFAULT_TEST_SEED,
    *,
    ompl_seed: int = 0,
    max_steps: int = 50,
    device: torch.device | str | None = None,
    progress: bool = False,
    edge_step: float | None = None,
    simplify: bool = True,
) -> dict:
    """PRM on the fixed test tasks, executed and scored like a learned policy by :func:`~torchrl_silp.eval.evaluate`.

    The test tasks and env are the ones :func:`~torchrl_silp.eval.evaluate`
    builds from the model (``collision_type=0``: a collision ends the episode
    as a failure). Each task is planned in turn by a :class:`PRMPlanner`,
    then all paths run as one batch through :class:`PathReplayPolicy` (a
    failed plan: zero actions). A path needing more than ``max_steps`` steps
    is cut there, as the episode is.

    Args:
        model: the task model (or an env holding one); moved to ``device``, as the env does.
        budget_s: planning time per task, seconds (PRM-0.1: 0.1, PRM-1: 1).
        n_tasks: number of test tasks (paper: 1000).
        seed: seed of the test tasks.
        ompl_seed: seed of OMPL's random generator (see :class:`PRMPlanner`).
        max_steps: episode length (50 in our tables; the paper does not state it).
        device: device of the test env and of the planner's checks; the model's by default.
        progress: a tqdm bar over the tasks planned.
        edge_step: the planner's edge check resolution (rad); the model's ``motion_resolution`` by default.
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
    model = as_model(model)
    check_positive_int(n_tasks, name="n_tasks")
    check_nonnegative_int(seed, name="seed")
    check_positive_int(max_steps, name="max_steps")
    check_bool(progress, name="progress")
    planner = PRMPlanner(model, budget_s, seed=ompl_seed, edge_step=edge_step, simplify=simplify)
    device = _device(model, device)
    # the tasks of evaluate's env: ReachEnv(model, num_envs=n_tasks, seed=seed)'s first reset
    tasks = model.sample_tasks(n_tasks, torch.Generator(device=device).manual_seed(seed))
    bar = _progress_bar(n_tasks, f"PRM-{budget_s:g}", progress)
    try:
        paths, times = _plan_tasks(planner, tasks, n_tasks, bar)
    finally:
        if bar is not None:
            bar.close()
    policy = PathReplayPolicy(model, paths)
    metrics, rollout = evaluate(
        policy, n_tasks, seed, model=model, max_steps=max_steps, collision_type=0, device=device, return_rollout=True
    )
    if not torch.equal(rollout[:, 0][model.config_key], tasks[model.config_key].to(rollout.device)):
        raise RuntimeError("the test env's reset drew other tasks than the ones planned")
    solved = torch.tensor([p is not None for p in paths], dtype=torch.bool)
    steps = policy.steps.cpu()
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


def _execute(model: TaskModel, tasks: TensorDictBase, actions: torch.Tensor, max_steps: int):
    """Run ``actions`` ``[B, T, D]`` from the tasks' starts with ``model.step``, as an env with collision type 0 would.

    Returns ``(state, next_state, reward, collision, success, flags)``, each ``[B, T, ...]``.
    """
    state = tasks.select(*model.state_keys)
    states, nexts, out = [], [], []
    for t in range(max_steps):
        nxt, reward, collision, success, flags = model.step(state, actions[:, t])
        states.append(state)
        nexts.append(nxt)
        out.append((reward, collision, success, flags))
        state = nxt
    stack = lambda xs: torch.stack(xs, 1)  # noqa: E731
    return (stack(states), stack(nexts), *(torch.stack([o[k] for o in out], 1) for k in range(4)))


def _demonstrations(
    model: TaskModel, tasks: TensorDictBase, policy: PathReplayPolicy, first_episode: int, max_steps: int, build
) -> tuple[TensorDict, torch.Tensor]:
    """The transitions of the tasks' executions that reach the goal, up to and including the successful step,
    and which tasks' executions did (bool ``[B]``)."""
    B, D, device = tasks.batch_size[0], model.config_dim, model.device
    T = max_steps
    actions = torch.zeros(B, T, D, dtype=model.dtype, device=device)
    k = min(T, policy._actions.shape[1])
    actions[:, :k] = policy._actions[:, :k].to(device)
    state, nxt, reward, collision, success, flags = _execute(model, tasks, actions, T)
    collision, success = collision.squeeze(-1), success.squeeze(-1)
    ended = collision | success
    # alive: steps up to and including the first collision or success (an env with collision type 0 ends there)
    alive = torch.ones_like(ended)
    alive[:, 1:] = ~ended[:, :-1].cumsum(-1).bool()
    ok = (success & alive).any(-1)
    keep = alive & ok.unsqueeze(-1)
    b, t = keep.nonzero(as_tuple=True)
    N = b.numel()
    false = torch.zeros(N, 1, dtype=torch.bool, device=device)
    goal_q = tasks.get(model.goal_config_key)[b]
    succ = success[b, t].unsqueeze(-1)
    next_td = nxt[b, t]
    next_td.update(
        {
            model.goal_config_key: goal_q,
            "reward": reward[b, t],
            "collision": collision[b, t].unsqueeze(-1),
            "swept_collision": false.clone(),  # kept episodes succeeded, and a collision ends one
            "success": succ,
            "discard": false.clone(),
            "collision_reason": flags[b, t],
            "done": succ.clone(),
            "terminated": succ.clone(),
            "truncated": false.clone(),
        }
    )
    root = state[b, t]
    root.update({"action": actions[b, t], model.goal_config_key: goal_q.clone(), **demo_start_flags(N, device),
                 "episode": b + first_episode})
    root = build(root)
    root.set("next", build(next_td))
    return root, ok


def collect_prm_demonstrations(
    model: TaskModel,
    n_episodes: int,
    budget_s: float = 1.0,
    *,
    seed: int = 0,
    max_steps: int = 50,
    device: torch.device | str | None = None,
    progress: bool = False,
    edge_step: float | None = None,
    simplify: bool = True,
    observation_transform=None,
    observation_keys: Sequence[NestedKey] = ("observation",),
) -> tuple[TensorDict, dict]:
    """Demonstrations for behaviour cloning (BC-PRM): PRM's successful executions on training tasks.

    ``n_episodes`` training tasks (not the test tasks: those that a
    ``ReachEnv(model, num_envs=min(n_episodes, 500), seed=seed)`` draws on its
    successive resets) are planned (OMPL seeded with ``seed`` too) in batches
    of up to 500, and each path is executed from its task's start with
    ``model.step``, :class:`PathReplayPolicy`'s actions step by step, as the
    env of :func:`evaluate_prm` would run it (a collision ends the episode, the
    episode is ``max_steps`` long). The transitions of the episodes that reach
    the goal are kept, up to and including the successful step, built the way
    :func:`~torchrl_silp.planning.paths_to_demonstrations` builds the planner's
    demonstrations: the model's named state at the root and under ``"next"``,
    and what ``observation_transform`` writes from it on both.

    :func:`prm_demonstration_batches` gives the same batches one at a time (to
    save each as it comes, and resume a collection at its next batch).

    Args:
        model: the task model (or an env holding one); moved to ``device``.
        n_episodes: tasks attempted.
        budget_s: planning time per task, seconds (paper: 1).
        seed: seed of the training tasks and of OMPL.
        max_steps, device, progress, edge_step, simplify: as in :func:`evaluate_prm`.
        observation_transform: builds the networks' inputs from a named state (a TorchRL
            transform or any callable ``td -> td``); the model's
            :class:`~torchrl_silp.transforms.FlatCatTensors` (``"observation"``) by default.
        observation_keys: the keys ``observation_transform`` writes that the transitions keep.

    Returns:
        ``(demos, stats)``: a flat TensorDict ``[N]`` of transitions with the keys
        of :func:`~torchrl_silp.data.transition_keys` (model, ``observation_keys``),
        ``"is_demo"`` (bool ``[N, 1]``, True) and ``"episode"`` (long ``[N]``: the
        attempt's index in ``0 .. n_episodes - 1``), episodes one after the
        other, steps in order, each closed by its successful, terminating step;
        ``stats`` (:func:`prm_demonstration_stats`) holds ``n_attempted``,
        ``n_kept`` (successful episodes), ``n_transitions``, ``success_rate``,
        ``solved_rate``, ``planning_s`` (total), ``planning_time_max_s`` and ``wall_s``.
    """
    start = time.perf_counter()
    batches = list(prm_demonstration_batches(
        model, n_episodes, budget_s, seed=seed, max_steps=max_steps, device=device, progress=progress,
        edge_step=edge_step, simplify=simplify, observation_transform=observation_transform,
        observation_keys=observation_keys,
    ))
    demos = torch.cat([d for d, _ in batches])
    return demos, prm_demonstration_stats([b for _, b in batches], demos.numel(), time.perf_counter() - start)


def prm_demonstration_batches(
    model: TaskModel,
    n_episodes: int,
    budget_s: float = 1.0,
    *,
    start_episode: int = 0,
    seed: int = 0,
    max_steps: int = 50,
    device: torch.device | str | None = None,
    progress: bool = False,
    edge_step: float | None = None,
    simplify: bool = True,
    observation_transform=None,
    observation_keys: Sequence[NestedKey] = ("observation",),
) -> Iterator[tuple[TensorDict, dict]]:
    """:func:`collect_prm_demonstrations` one batch of up to 500 tasks at a time, from ``start_episode`` on.

    The arguments are checked (and the model moved) when this is called, before
    any planning; the planning happens as the iterator is consumed.

    Args:
        start_episode: the first task attempted, a multiple of the batch size
            (``min(n_episodes, 500)``) below ``n_episodes``. The tasks before it
            are drawn and skipped, and OMPL's per-task seeds moved on past them,
            so task ``e`` is the one a collection from 0 attempts as its
            ``e``-th: a collection cut after a batch resumes at the next.
        the others: as in :func:`collect_prm_demonstrations`.

    Yields:
        ``(demos, batch_stats)`` per batch: the batch's kept transitions (as
        :func:`collect_prm_demonstrations` returns them: ``"episode"`` is the
        task's index in the whole collection) and ``batch_stats``: ``n_attempted``,
        ``n_kept``, ``planning_times`` (float64 ``[n_attempted]``, seconds) and
        ``solved`` (bool ``[n_attempted]``: PRM found a path), the input of
        :func:`prm_demonstration_stats`.
    """
    _require_ompl("prm_demonstration_batches")
    model = as_model(model)
    check_positive_int(n_episodes, name="n_episodes")
    check_nonnegative_int(seed, name="seed")
    check_positive_int(max_steps, name="max_steps")
    check_bool(progress, name="progress")
    batch = min(n_episodes, _COLLECT_BATCH)
    check_nonnegative_int(start_episode, name="start_episode")
    if start_episode >= n_episodes or start_episode % batch:
        raise ValueError(f"start_episode must be a multiple of the batch size {batch} below n_episodes={n_episodes}, "
                         f"got {start_episode}")
    planner = PRMPlanner(model, budget_s, seed=seed, edge_step=edge_step, simplify=simplify)
    device = _device(model, device)
    build = model.observation_transform() if observation_transform is None else observation_transform
    keys = (*transition_keys(model, observation_keys), "is_demo", "episode")

    def batches() -> Iterator[tuple[TensorDict, dict]]:
        generator = torch.Generator(device=device).manual_seed(seed)
        for _ in range(start_episode // batch):
            model.sample_tasks(batch, generator)
        planner.skip(start_episode)
        bar = _progress_bar(n_episodes, f"PRM-{budget_s:g} demos", progress)
        if bar is not None:
            bar.update(start_episode)
        attempted = start_episode
        try:
            while attempted < n_episodes:
                take = min(batch, n_episodes - attempted)
                tasks = model.sample_tasks(batch, generator)[:take]  # what the env's next reset draws
                paths, times = _plan_tasks(planner, tasks, take, bar)
                demos, ok = _demonstrations(model, tasks, PathReplayPolicy(model, paths), attempted, max_steps, build)
                solved = torch.tensor([p is not None for p in paths], dtype=torch.bool)
                attempted += take
                yield demos.select(*keys), {"n_attempted": take, "n_kept": int(ok.sum()),
                                            "planning_times": times, "solved": solved}
        finally:
            if bar is not None:
                bar.close()

    return batches()


def prm_demonstration_stats(batch_stats: Sequence[dict], n_transitions: int, wall_s: float) -> dict:
    """The stats of :func:`collect_prm_demonstrations` from its batches' (:func:`prm_demonstration_batches`).

    Args:
        batch_stats: the ``batch_stats`` of every batch of the collection.
        n_transitions: transitions kept in all.
        wall_s: the collection's wall time, seconds.
    """
    if not batch_stats:
        raise ValueError("batch_stats must hold at least one batch's stats, got none")
    attempted = sum(b["n_attempted"] for b in batch_stats)
    kept = sum(b["n_kept"] for b in batch_stats)
    times = torch.cat([b["planning_times"] for b in batch_stats])
    solved = torch.cat([b["solved"] for b in batch_stats])
    return {
        "n_attempted": attempted,
        "n_kept": kept,
        "n_transitions": int(n_transitions),
        "success_rate": kept / attempted,
        "solved_rate": solved.float().mean().item(),
        "planning_s": times.sum().item(),
        "planning_time_max_s": times.max().item(),
        "wall_s": float(wall_s),
    }
