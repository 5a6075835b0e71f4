"""Collision checks of joint-space segments (roadmap edges), through the task model.

The check itself is the model's
(:meth:`~torchrl_silp.models.TaskModel.segment_collision_free`): samples no more
than ``step_size`` apart, each checked with a margin of ``L * step_size / 2``
(``L`` from :meth:`~torchrl_silp.models.TaskModel.lipschitz`), so that every
point of a passing segment is free; with ``model.conservative = False`` the
samples are checked exactly (the paper's subdivision check). The env judges its
steps with the same test, so a demonstration planned along an edge is a motion
the env lets pass.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from torchrl_silp.models.base import as_model

__all__ = ["segment_collision_free", "clearance_radius", "lipschitz_bounds"]


def _check_positive(name: str, value, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 or not math.isfinite(value):
        raise ValueError(f"{name} must be a positive finite number of {unit}, got {value!r}")
    return float(value)


def lipschitz_bounds(model) -> dict[str, float]:
    """How far (m) the model's checked geometry can move per radian of joint motion, per collision reason.

    Examples:
        >>> from torchrl_silp.models import UR5eReach
        >>> b = lipschitz_bounds(UR5eReach())
        >>> sorted(b)
        ['obstacle', 'self', 'table', 'workspace']
    """
    return as_model(model).lipschitz()


def clearance_radius(model, config: torch.Tensor, scene: TensorDictBase) -> torch.Tensor:
    """A joint-space radius (rad, max-norm) around each configuration inside which nothing collides.

    Each reason's clearance (metres) divided by its Lipschitz bound; negative exactly
    where the configuration collides.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> task = model.sample_tasks(4, torch.Generator().manual_seed(0))
        >>> bool((clearance_radius(model, task["joint_position"], task.select("obstacle")) >= 0).all())
        True
    """
    model = as_model(model)
    bounds = model.lipschitz()
    lip = torch.tensor([bounds[r] for r in model.collision_reasons], dtype=config.dtype, device=config.device)
    return (model.clearance(config, scene) / lip).amin(-1)


def segment_collision_free(
    model, q_from: torch.Tensor, q_to: torch.Tensor, scene: TensorDictBase, step_size: float | None = None
) -> torch.Tensor:
    """The model's motion check of a flat batch of segments ``(P, D)``: bool ``(P,)``.

    Examples:
        >>> import torch
        >>> from torchrl_silp.models import UR5eReach
        >>> model = UR5eReach()
        >>> task = model.sample_tasks(2, torch.Generator().manual_seed(0))
        >>> q = task["joint_position"]
        >>> segment_collision_free(model, q, q + 0.05, task.select("obstacle")).shape
        torch.Size([2])
    """
    model = as_model(model)
    if step_size is not None:
        step_size = _check_positive("step_size", step_size, "radians")
    if q_from.shape != q_to.shape or q_from.dim() != 2 or q_from.shape[-1] != model.config_dim:
        raise ValueError(
            f"q_from and q_to must have one shape (P, {model.config_dim}), got {tuple(q_from.shape)} and {tuple(q_to.shape)}"
        )
    return model.segment_collision_free(q_from, q_to, scene, step_size)
