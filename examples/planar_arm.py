"""A task of your own: a planar 3-link arm reaching among randomised discs, with self collisions.

None of the package's robots: written against :class:`torchrl_silp.models.TaskModel` alone, as a
user would. The arm's base sits at the origin of the plane; its links (0.4, 0.3, 0.2 m) are
segments of half-width 0.025 m; each episode draws ``n_discs`` discs and a start and goal pose.
A configuration collides when a link meets a disc, or the last link meets the first (self).

The discs lie in the ring the outer links sweep (0.5 to 0.8 m from the base), and the base joint
turns through two full turns (starts and goals are drawn within one), so the arm can always swing
round either way: nearly every task can be solved within the 50 steps of an episode (the share a
search of the whole joint space solves: :func:`solvable`), and few without a detour
(:func:`torchrl_silp.eval.straight_path_free`, re-exported here).

Train SILP+ on it with the main job, no file of the repository changed (run from the repo root,
where ``examples`` is importable)::

    PYTHONPATH=. python recipes/sac_silp.py env=custom env.model._target_=examples.planar_arm.PlanarArmReach env.model.n_discs=3

Examples:
    >>> import torch
    >>> from torchrl_silp.models import check_task_model
    >>> model = PlanarArmReach(n_discs=3)
    >>> check_task_model(model)
    >>> tasks = model.sample_tasks(4, torch.Generator().manual_seed(0))
    >>> tasks["discs"].shape, tasks["achieved_goal"].shape
    (torch.Size([4, 3, 3]), torch.Size([4, 2]))
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_silp.eval import straight_path_free
from torchrl_silp.models import TaskModel

__all__ = ["PlanarArmReach", "solvable", "straight_path_free", "task_shares"]

LINKS = (0.4, 0.3, 0.2)
HALF_WIDTH = 0.025


def _point_segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance ``(...)`` from points ``p`` to segments ``a -> b`` (all ``(..., 2)``)."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / ab.square().sum(-1).clamp(min=1e-12)
    closest = a + t.clamp(0, 1).unsqueeze(-1) * ab
    return (p - closest).norm(dim=-1)


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _segment_distance(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Distance ``(...)`` between segments ``a -> b`` and ``c -> d``: 0 where they cross."""
    ends = torch.stack([_point_segment_distance(a, c, d), _point_segment_distance(b, c, d),
                        _point_segment_distance(c, a, b), _point_segment_distance(d, a, b)], -1).amin(-1)
    d1, d2 = _cross(b - a, c - a), _cross(b - a, d - a)
    d3, d4 = _cross(d - c, a - c), _cross(d - c, b - c)
    crossing = (d1 * d2 < 0) & (d3 * d4 < 0)
    return torch.where(crossing, torch.zeros_like(ends), ends)


class PlanarArmReach(TaskModel):
    """A planar 3-link arm reaching a goal point among ``n_discs`` random discs.

    The configuration is the three joint angles (the first about the base, within ``[-2 pi, 2 pi]``
    so that it turns either way from any start drawn within ``[-pi, pi]``; the others within
    ``[-2.5, 2.5]`` rad); the achieved goal is the tip of the last link; the scene is ``"discs"``
    ``(n_discs, 3)``: centre x, y and radius, the centres 0.5 to 0.8 m from the base. Tasks keep the
    paper's rule with the first disc (start-goal > start-disc > disc-goal), so that it tends to lie
    between start and goal.

    Args:
        n_discs: discs per episode.
        success_distance: reach accuracy (m).
        motion_resolution: the swept check's joint-space resolution (rad).
        device, dtype: of the model's tensors.
    """

    config_dim, goal_dim = 3, 2
    collision_reasons = ("obstacle", "self")
    action_scale = 0.1

    def __init__(self, n_discs: int = 3, *, success_distance: float = 0.05, motion_resolution: float = 0.01,
                 device=None, dtype=torch.float32):
        super().__init__(success_distance=success_distance, motion_resolution=motion_resolution,
                         device=device, dtype=dtype)
        if isinstance(n_discs, bool) or not isinstance(n_discs, int) or n_discs < 1:
            raise ValueError(f"n_discs must be a positive int, got {n_discs!r}")
        self.n_discs = n_discs
        self.scene_shapes = {"discs": (n_discs, 3)}
        self._make_tensors()

    def _make_tensors(self) -> None:
        f = dict(device=self.device, dtype=self.dtype)
        self.config_low = torch.tensor([-2 * math.pi, -2.5, -2.5], **f)
        self.config_high = torch.tensor([2 * math.pi, 2.5, 2.5], **f)
        # where starts and goals are drawn: one turn of the base
        self.task_low = torch.tensor([-math.pi, -2.5, -2.5], **f)
        self.task_high = torch.tensor([math.pi, 2.5, 2.5], **f)
        self.links = torch.tensor(LINKS, **f)

    def to(self, device) -> "PlanarArmReach":
        super().to(device)
        self._make_tensors()
        return self

    # ---------------------------------------------------------------- kinematics
    def joints(self, config: torch.Tensor) -> torch.Tensor:
        """Base, elbow, wrist and tip positions ``(..., 4, 2)``."""
        angle = torch.cumsum(config, -1)
        steps = self.links.to(config.dtype).unsqueeze(-1) * torch.stack([angle.cos(), angle.sin()], -1)
        points = torch.cumsum(steps, -2)
        return torch.cat([torch.zeros_like(points[..., :1, :]), points], -2)

    def draw_scene(self, ax, state: TensorDictBase) -> None:
        """The discs and the arm at ``state`` on a matplotlib axes (what the rollout picture calls)."""
        from matplotlib.patches import Circle

        for x, y, r in state.get("discs").tolist():
            ax.add_patch(Circle((x, y), r, facecolor=(0.85, 0.25, 0.2, 0.45), edgecolor=(0.55, 0.1, 0.08, 0.9)))
        joints = self.joints(state.get(self.config_key)).tolist()
        ax.plot(*zip(*joints), color="#5f7f9f", linewidth=3, solid_capstyle="round", label="arm (last state)")

    def achieved_goal(self, config: torch.Tensor) -> torch.Tensor:
        return self.joints(config)[..., -1, :]

    # ---------------------------------------------------------------- collisions
    def clearance(self, config: torch.Tensor, scene) -> torch.Tensor:
        discs = scene.get("discs") if isinstance(scene, TensorDictBase) else scene
        p = self.joints(config)  # (..., 4, 2)
        a, b = p[..., :-1, :], p[..., 1:, :]  # the links (..., 3, 2)
        centre, radius = discs[..., :2], discs[..., 2]  # (..., K, 2), (..., K)
        to_disc = _point_segment_distance(centre.unsqueeze(-2), a.unsqueeze(-3), b.unsqueeze(-3))  # (..., K, 3)
        obstacle = (to_disc - radius.unsqueeze(-1) - HALF_WIDTH).flatten(-2).amin(-1)
        self_gap = _segment_distance(p[..., 0, :], p[..., 1, :], p[..., 2, :], p[..., 3, :]) - 2 * HALF_WIDTH
        return torch.stack([obstacle, self_gap], -1)

    def collision_flags(self, config: torch.Tensor, scene, margin=None):
        margin = margin or {}
        c = self.clearance(config, scene)
        hit = (c[..., 0] < margin.get("obstacle", 0.0)).to(torch.uint8)
        own = (c[..., 1] < margin.get("self", 0.0)).to(torch.uint8)
        return (hit + 2 * own).unsqueeze(-1), self.achieved_goal(config)

    def lipschitz(self) -> dict[str, float]:
        # a joint step of max-norm 1 rad moves a point of the arm by at most the sum of its distances to
        # the joints before it (<= 0.9 + 0.5 + 0.2); the first joint turns the whole arm rigidly, so the
        # distance of the last link to the first changes only by joints 2 and 3 (<= 0.5 + 0.2)
        return {"obstacle": sum(LINKS) + LINKS[1] + 2 * LINKS[2], "self": LINKS[1] + 2 * LINKS[2]}

    # ---------------------------------------------------------------- tasks
    def sample_tasks(self, n: int, generator: torch.Generator | None = None) -> TensorDict:
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be a positive int, got {n!r}")
        f = dict(device=self.device, dtype=self.dtype)
        margin = self.motion_margin()
        out, have = [], 0
        while have < n:
            m = 8 * (n - have) + 64
            u = torch.rand(2, m, 3, generator=generator, **f)
            q = self.task_low + u * (self.task_high - self.task_low)
            r = 0.5 + 0.3 * torch.rand(m, self.n_discs, generator=generator, **f)
            phi = 2 * math.pi * torch.rand(m, self.n_discs, generator=generator, **f)
            radius = 0.06 + 0.06 * torch.rand(m, self.n_discs, generator=generator, **f)
            discs = torch.stack([r * phi.cos(), r * phi.sin(), radius], -1)
            tip = self.achieved_goal(q)  # (2, m, 2)
            d1 = (tip[0] - discs[:, 0, :2]).norm(dim=-1)
            d2 = (tip[0] - tip[1]).norm(dim=-1)
            d3 = (discs[:, 0, :2] - tip[1]).norm(dim=-1)
            free = (self.collision_flags(q, discs.unsqueeze(0).expand(2, m, self.n_discs, 3), margin)[0] == 0).squeeze(-1)
            keep = (free.all(0) & (d2 > d1) & (d1 > d3) & (d2 > 0.3)).nonzero().squeeze(-1)[: n - have]
            if keep.numel():
                out.append(TensorDict({
                    self.config_key: q[0, keep], self.achieved_goal_key: tip[0, keep], "discs": discs[keep],
                    self.desired_goal_key: tip[1, keep], self.goal_config_key: q[1, keep],
                }, batch_size=[keep.numel()]))
                have += keep.numel()
        return torch.cat(out) if len(out) > 1 else out[0]


def solvable(model: PlanarArmReach, tasks: TensorDictBase, max_steps: int = 50) -> torch.Tensor:
    """Which tasks ``[n]`` a search of the whole joint space solves within ``max_steps`` steps (bool ``[n]``).

    The joint box is a grid of ``model.action_scale`` spacing, on which one step reaches the 26
    neighbouring cells (every joint moves by at most one action); a breadth-first search from the
    start's nearest cell through the collision-free cells, by ``max_steps`` dilations, looks for a
    cell whose tip lies within ``success_distance`` of the goal. Motions between neighbouring cells
    are not checked (a cell is 0.1 rad across), so this is the share an ideal policy could reach,
    not a bound a trained one is held to.
    """
    h = model.action_scale
    low, high = model.config_low, model.config_high
    axes = [torch.arange(float(lo), float(hi) + 1e-6, h, dtype=model.dtype) for lo, hi in zip(low, high)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
    shape, cells = grid.shape[:3], grid.reshape(-1, 3)
    tips = model.achieved_goal(cells)
    out = torch.zeros(len(tasks), dtype=torch.bool)
    for i in range(len(tasks)):  # one task's grid at a time: 300k cells
        task = tasks[i]
        discs = task.get("discs").unsqueeze(0).expand(cells.shape[0], -1, -1)
        free = (model.collision_flags(cells, discs)[0].squeeze(-1) == 0).reshape(shape)
        goal = ((tips - task.get(model.desired_goal_key)).norm(dim=-1) <= model.success_distance).reshape(shape) & free
        start = ((task.get(model.config_key) - low) / h).round().long().tolist()
        front = torch.zeros(shape, dtype=model.dtype)
        front[tuple(start)] = 1.0
        for _ in range(max_steps):
            front = torch.nn.functional.max_pool3d(front[None, None], 3, stride=1, padding=1)[0, 0] * free
            if bool((front.bool() & goal).any()):
                out[i] = True
                break
    return out


def task_shares(n_tasks: int = 1000, seed: int = 20231101, max_steps: int = 50, n_discs: int = 3) -> dict:
    """Of the main job's test tasks (``eval.test_seed``'s, as ``ReachEnv`` draws them): the share
    :func:`solvable` solves and the share :func:`straight_path_free` solves."""
    from torchrl_silp.envs import ReachEnv

    model = PlanarArmReach(n_discs=n_discs)
    tasks = ReachEnv(model, num_envs=n_tasks, seed=seed).reset()
    return {"solvable_share": solvable(model, tasks, max_steps).float().mean().item(),
            "straight_path_share": straight_path_free(model, tasks, max_steps).float().mean().item()}


if __name__ == "__main__":  # python examples/planar_arm.py [n_tasks]: what share of the test tasks can be solved at all
    import json
    import sys

    torch.set_num_threads(1)
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
    print(json.dumps({"n_tasks": n, "seed": 20231101, "max_steps": 50, **task_shares(n)}))
