"""OMPL's PRM as a closed-loop controller on the twin: replanned from the measured state at every control step."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torchrl_silp.baselines.prm import PRMPlanner
from torchrl_silp.models.base import as_model

__all__ = ["ReplanningPRMPolicy"]


class ReplanningPRMPolicy:
    """A policy ``td -> td`` for :func:`~torchrl_silp.sim.run_transfer`: at each call, for each task, OMPL's PRM
    plans from the measured configuration to the task's goal configuration in the perceived scene within
    ``budget_s``, and the action moves along the path's first segment (at most one action unit per joint).
    Where a plan fails, the task's previous path is followed from its nearest waypoint on; without one, the
    arm holds still.

    The planner runs one task after the other (OMPL plans one problem at a time): a control step costs up to
    ``budget_s`` per task, so at 10 Hz the paper's PRM-0.1 just keeps up with one arm.

    Args:
        model: the task model (or an env holding one).
        goal_config: ``[B, D]`` the tasks' goal configurations (the planner's goal; the policies reach the goal
            position instead).
        budget_s: planning time per task and step (the paper's PRM-0.1: 0.1 s).
        seed: OMPL's seeds (see :class:`~torchrl_silp.baselines.PRMPlanner`).
    """

    def __init__(self, model, goal_config: torch.Tensor, budget_s: float = 0.1, seed: int | None = 0):
        self.model = as_model(model)
        if goal_config.dim() != 2 or goal_config.shape[-1] != self.model.config_dim:
            raise ValueError(f"goal_config must have shape [B, {self.model.config_dim}], got {tuple(goal_config.shape)}")
        self.goal = goal_config
        self.planner = PRMPlanner(self.model, budget_s, seed=seed)
        self.paths: list[torch.Tensor | None] = [None] * len(goal_config)
        self.plans = self.failures = 0

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        model = self.model
        q = td.get(model.config_key)
        if q.shape[0] != len(self.paths):
            raise ValueError(f"the policy was built for {len(self.paths)} tasks, called on {q.shape[0]}")
        scene = td.select(*model.scene_keys)
        low, high = model.config_low, model.config_high
        action = torch.zeros_like(q)
        for b in range(q.shape[0]):
            start = torch.minimum(torch.maximum(q[b], low), high)
            path, _ = self.planner.plan(start, self.goal[b], scene[b])
            self.plans += 1
            if path is None:
                self.failures += 1
                path = self._rest_of(b, start)
            else:
                self.paths[b] = path
            if path is None or len(path) < 2:
                continue
            step = (path[1] - start) / model.action_scale
            action[b] = step / step.abs().amax().clamp(min=1.0)
        td.set("action", action)
        return td

    def _rest_of(self, b: int, q: torch.Tensor) -> torch.Tensor | None:
        """The previous path from the waypoint after the one nearest ``q``, with ``q`` in front."""
        path = self.paths[b]
        if path is None:
            return None
        nearest = int((path - q).abs().amax(-1).argmin())
        return torch.cat([q.unsqueeze(0), path[nearest + 1:]]) if nearest + 1 < len(path) else None
