"""Closed-loop execution of a policy on the MuJoCo twin: noisy encoders, a perceived obstacle, a moving box.

The paper's real-robot scenarios (sec. 4.5): *Free* (the straight path from start to
goal is clear of the box), *Block* (the box stands in that path) and *Change* (the
path starts clear and the box moves into it during the motion); and the reaching test of
its Table 5, ten fixed scenarios run ten times each (:func:`reaching_trials`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_silp.sim.twin import MujocoTwin
from torchrl_silp.validation import check_choice, check_nonnegative_float, check_nonnegative_int, check_positive_float, check_positive_int

__all__ = ["Perception", "NOISE_LEVELS", "SCENARIOS", "scenario_tasks", "reaching_trials", "run_transfer"]

SCENARIOS = ("free", "block", "change")


@dataclass(frozen=True)
class Perception:
    """What the policy sees of the world.

    Args:
        obstacle_noise: std (m) of the perceived box centre, per axis, drawn afresh each control step.
        latency_steps: control steps between a box pose and the policy's view of it.
        joint_noise: std (rad) of the joint encoders.
    """

    obstacle_noise: float = 0.0
    latency_steps: int = 0
    joint_noise: float = 0.0

    def __post_init__(self):
        check_nonnegative_float(self.obstacle_noise, name="obstacle_noise", unit="metres")
        check_nonnegative_float(self.joint_noise, name="joint_noise", unit="radians")
        check_nonnegative_int(self.latency_steps, name="latency_steps")


# The paper localises the box with ArUco markers and a camera and gives no error figure. ArUco
# poses at 0.5-1.5 m are typically off by a few millimetres to about 2 cm: "paper" takes 1 cm
# per axis and one control step (0.1 s) of latency (a 10-30 Hz camera plus detection); "double"
# doubles both. The encoders' noise (1e-4 rad) is the order of a UR joint's repeatability.
NOISE_LEVELS = {
    "none": Perception(),
    "paper": Perception(obstacle_noise=0.01, latency_steps=1, joint_noise=1e-4),
    "double": Perception(obstacle_noise=0.02, latency_steps=2, joint_noise=2e-4),
}


def _path_obstacle_clearance(model, start, goal, obstacle, resolution: float = 0.01) -> torch.Tensor:
    """The box's smallest clearance (m) along each straight joint-space path ``[N]`` (negative: it meets the
    box), sampled every ``resolution`` rad of the largest joint's motion."""
    reason = model.collision_reasons.index("obstacle")
    samples = max(2, int(math.ceil(float((goal - start).abs().amax()) / resolution)) + 1)
    s = torch.linspace(0.0, 1.0, samples, dtype=start.dtype, device=start.device).view(1, -1, 1)
    configs = start.unsqueeze(1) + s * (goal - start).unsqueeze(1)  # [N, S, D]
    scene = TensorDict({"obstacle": obstacle.unsqueeze(1).expand(-1, samples, -1)}, batch_size=configs.shape[:2])
    return model.clearance(configs, scene)[..., reason].amin(-1)


def _free_of_all_but_box(model, start, goal, obstacle) -> torch.Tensor:
    """The straight path is clear of the table, the arm itself and the workspace bounds (the box set aside)."""
    far = obstacle.clone()
    far[:, 0::2] += 10.0  # the box moved 10 m along x
    far[:, 1::2] += 10.0
    return model.segment_collision_free(start, goal, TensorDict({"obstacle": far}, batch_size=[start.shape[0]]))


def scenario_tasks(model, scenario: str, n: int, seed: int, *, margin: float = 0.03, speed: float = 0.5,
                   move_at_s: float = 0.2) -> TensorDict:
    """``n`` seeded tasks of a scenario, drawn from the model's task distribution.

    *free*: the straight joint-space path from start to goal keeps at least ``margin`` (m) from the
    box; *block*: it passes at least ``margin`` into the box. *change*: a free task whose box,
    from ``move_at_s`` seconds on, slides at ``speed`` m/s to a second place from which it blocks
    the path by ``margin`` and leaves start and goal free. In all three the path is clear of the
    table, the arm itself and the workspace bounds, so the box alone makes the difference.

    Returns a TensorDict ``[n]`` with the task's keys (``joint_position``, ``goal_joint_position``,
    ``obstacle``, ``desired_goal``, ...) and, for *change*, ``obstacle_end`` (the box's second
    place), ``move_at_s`` and ``speed``.
    """
    check_choice(scenario, SCENARIOS, name="scenario")
    check_positive_int(n, name="n")
    for name, value in (("margin", margin), ("speed", speed), ("move_at_s", move_at_s)):
        check_nonnegative_float(value, name=name)
    if scenario == "change" and speed <= 0:
        raise ValueError(f"speed must be positive for the change scenario, got {speed!r}")
    gen = torch.Generator().manual_seed(seed)
    picked, total = [], 0
    for _ in range(200):
        draw = model.sample_tasks(max(4 * n, 256), gen)
        start, goal, box = draw["joint_position"], draw["goal_joint_position"], draw["obstacle"]
        clear = _free_of_all_but_box(model, start, goal, box)
        clearance = _path_obstacle_clearance(model, start, goal, box)
        if scenario == "block":
            keep = clear & (clearance <= -margin)
        else:
            keep = clear & (clearance >= margin)
        draw = draw[keep]
        if scenario == "change" and len(draw):
            # the box's second place: another draw of the model's box distribution that blocks this path
            # and leaves the start and goal configurations free
            other = model.sample_tasks(len(draw), gen)["obstacle"]
            start, goal = draw["joint_position"], draw["goal_joint_position"]
            blocks = _path_obstacle_clearance(model, start, goal, other) <= -margin
            ends = TensorDict({"obstacle": other}, batch_size=[len(draw)])
            ends_free = ~model.collides(start, ends) & ~model.collides(goal, ends)
            keep = blocks & ends_free
            draw = draw[keep]
            draw.set("obstacle_end", other[keep])
            draw.set("move_at_s", torch.full((len(draw), 1), float(move_at_s)))
            draw.set("speed", torch.full((len(draw), 1), float(speed)))
        picked.append(draw)
        total += len(draw)
        if total >= n:
            break
    else:
        raise RuntimeError(f"could not draw {n} {scenario} tasks with margin {margin} (got {total})")
    return torch.cat(picked)[:n]


def reaching_trials(model, *, n_free: int = 5, n_block: int = 5, trials: int = 10, seed: int = 0,
                    margin: float = 0.03) -> TensorDict:
    """The reaching test of the paper's Table 5: fixed scenarios (a box, a goal and a start pose each), each
    run ``trials`` times.

    The paper runs its two policies "for ten trials in each scenario" of "10 different scenarios with
    different obstacles, goals, and initial robot poses" and does not list them; here they are ``n_free``
    *free* and ``n_block`` *block* tasks of :func:`scenario_tasks` (seeds ``seed`` and ``seed + 1``). The
    trials of one scenario are the same task: they differ in what perception draws (:class:`Perception`)
    when :func:`run_transfer` runs them.

    Returns a TensorDict ``[(n_free + n_block) * trials]``, scenario-major, with the tasks' keys and
    ``"scenario"`` (long, the scenario's index: the free ones first).
    """
    for name, value in (("n_free", n_free), ("n_block", n_block)):
        check_nonnegative_int(value, name=name)
    check_positive_int(trials, name="trials")
    if n_free + n_block == 0:
        raise ValueError("n_free + n_block must be positive: no scenario to run")
    parts = [scenario_tasks(model, kind, n, seed=seed + i, margin=margin)
             for i, (kind, n) in enumerate((("free", n_free), ("block", n_block))) if n > 0]
    scenarios = torch.cat(parts) if len(parts) > 1 else parts[0]
    index = torch.arange(len(scenarios)).repeat_interleave(trials)
    out = scenarios[index]
    out.set("scenario", index)
    return out


def _box_at(tasks: TensorDict, t: float) -> torch.Tensor:
    """Each task's true box bounds at time ``t`` (s): a change task's box slides at its speed."""
    box = tasks["obstacle"].double()
    if "obstacle_end" not in tasks.keys():
        return box
    end = tasks["obstacle_end"].double()
    dist = (end - box).view(len(box), -1, 3, 2)[..., 0].norm(dim=-1).amax(-1, keepdim=True)  # [N, 1]
    moved = ((t - tasks["move_at_s"].double()) * tasks["speed"].double()).clamp(min=0)
    frac = torch.where(dist > 0, (moved / dist.clamp(min=1e-12)).clamp(max=1.0), torch.ones_like(dist))
    return box + frac * (end - box)


def run_transfer(policy, model, tasks: TensorDict, *, observation_transform=None,
                 perception: Perception = Perception(), control_dt: float = 0.1, max_steps: int = 50,
                 twin: MujocoTwin | None = None, seed: int = 0, updates_per_step: int = 10, on_step=None) -> dict:
    """Run ``policy`` closed-loop on the twin, one world per task, all tasks in lockstep.

    Each control step: read the encoders (plus noise), perceive the box (its pose
    ``perception.latency_steps`` steps ago, plus noise), build the named state through
    the task model (``model.state_at``) and the networks' inputs (``observation_transform``),
    ask the policy for an action (all tasks in one batch) and integrate ``control_dt`` seconds of
    physics while the servos' targets ramp from the measured configuration to its
    ``model.next_config`` in ``updates_per_step`` equal steps (the way a robot controller
    interpolates a position command), a *change* task's box moving on the same ticks. A task ends
    at its first collision contact (a failure, never a success), at success (MuJoCo's TCP within
    the model's ``success_distance`` of the goal after a control step) or after ``max_steps``.

    Returns a dict of per-task tensors (``success``, ``collision``, ``steps``, ``time_s``: simulated
    seconds to success or to the end, ``box_track``: MuJoCo's box centres ``[steps + 1, n, boxes, 3]``
    at the start and after each control step) and ``policy_ms_per_step`` (wall time of one batched
    policy call). ``on_step(twin, k)``, if given, is called at the start and after each control step
    (e.g. to render frames).
    """
    if not isinstance(perception, Perception):
        raise TypeError(f"perception must be a Perception, got {type(perception).__name__}")
    check_positive_float(control_dt, name="control_dt", unit="seconds")
    check_positive_int(max_steps, name="max_steps")
    n = len(tasks)
    twin = MujocoTwin(model, n_envs=n) if twin is None else twin
    if twin.n_envs != n:
        raise ValueError(f"twin has {twin.n_envs} worlds for {n} tasks")
    substeps = max(1, round(control_dt / twin.mj_model.opt.timestep))
    check_positive_int(updates_per_step, name="updates_per_step")
    chunks = min(updates_per_step, substeps)
    build = model.observation_transform() if observation_transform is None else observation_transform
    gen = torch.Generator().manual_seed(seed)
    dtype = model.dtype

    twin.reset(tasks["joint_position"], _box_at(tasks, 0.0))
    goal = tasks["desired_goal"].to(dtype)
    success = torch.zeros(n, dtype=torch.bool)
    collision = twin.colliding()
    steps = torch.zeros(n, dtype=torch.long)
    seen = [_box_at(tasks, 0.0)] * (perception.latency_steps + 1)  # the true poses of the last steps
    track = [twin.obstacle_centres()]
    if on_step is not None:
        on_step(twin, 0)
    policy_s = 0.0
    for k in range(max_steps):
        active = ~(success | collision)
        if not bool(active.any()):
            break
        t = k * control_dt
        q = twin.config().to(dtype)
        q_seen = q + perception.joint_noise * torch.randn(q.shape, generator=gen, dtype=dtype)
        seen = seen[1:] + [_box_at(tasks, t)]
        box = seen[0].to(dtype)
        if perception.obstacle_noise:
            shift = perception.obstacle_noise * torch.randn(n, box.shape[-1] // 6, 3, generator=gen, dtype=dtype)
            box = (box.view(n, -1, 3, 2) + shift.unsqueeze(-1)).view(n, -1)
        state = model.state_at(q_seen, TensorDict({"obstacle": box}, batch_size=[n]), goal)
        tick = time.perf_counter()
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            action = policy(build(state))["action"]
        policy_s += time.perf_counter() - tick
        target = model.next_config(q_seen, action.to(dtype))
        hit = torch.zeros(n, dtype=torch.bool)
        for c in range(chunks):
            twin.set_targets(q_seen + (c + 1) / chunks * (target - q_seen))
            if "obstacle_end" in tasks.keys():
                twin.set_obstacle(_box_at(tasks, t + control_dt * c / chunks))
            part = substeps // chunks + (1 if c < substeps % chunks else 0)
            hit |= twin.step(part, active & ~hit)
        steps += active.long()
        collision |= hit & active
        reached = (twin.tcp().to(dtype) - goal).norm(dim=-1) <= model.success_distance
        success |= reached & active & ~collision
        track.append(twin.obstacle_centres())
        if on_step is not None:
            on_step(twin, k + 1)
    return {
        "success": success, "collision": collision, "steps": steps, "time_s": steps.double() * control_dt,
        "box_track": torch.stack(track), "policy_ms_per_step": 1e3 * policy_s / max(int(steps.max()), 1),
    }
