"""Analytic, batched, differentiable geometry for the reach task.

Boxes are axis-aligned and given the way the observation holds them:
``(xmin, xmax, ymin, ymax, zmin, zmax)`` in the last dim. Every function
broadcasts over leading dims and works on any device.
"""

from __future__ import annotations

import torch

__all__ = [
    "aabb_from_center",
    "aabb_bounds",
    "point_box_signed_distance",
    "sphere_box_distance",
    "in_box",
    "CollisionReason",
]


class CollisionReason:
    """Bit flags of ``("next", "collision_reason")``: why a state counts as a collision."""

    NONE = 0
    OBSTACLE = 1
    TABLE = 2
    SELF = 4
    WORKSPACE = 8

    @classmethod
    def pack(cls, obstacle: torch.Tensor, table: torch.Tensor, self_: torch.Tensor, workspace: torch.Tensor) -> torch.Tensor:
        """The uint8 flags of four bool tensors of one shape (a collision with a box, the table, itself, the workspace)."""
        return (obstacle.to(torch.uint8) * cls.OBSTACLE + table.to(torch.uint8) * cls.TABLE
                + self_.to(torch.uint8) * cls.SELF + workspace.to(torch.uint8) * cls.WORKSPACE)

    @classmethod
    def names(cls, flags: int) -> list[str]:
        return [n.lower() for n in ("OBSTACLE", "TABLE", "SELF", "WORKSPACE") if flags & getattr(cls, n)]


def aabb_from_center(center: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` box ``(xmin, xmax, ymin, ymax, zmin, zmax)`` from centre and full size ``(..., 3)``."""
    if bool((size < 0).any()):
        raise ValueError("size must be >= 0 in every coordinate (a box's full size)")
    half = size / 2
    lo, hi = center - half, center + half
    return torch.stack([lo, hi], dim=-1).flatten(-2)


def aabb_bounds(box: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a ``(..., 6)`` box into its ``(..., 3)`` lower and upper corners."""
    b = box.unflatten(-1, (3, 2))
    return b[..., 0], b[..., 1]


def point_box_signed_distance(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Signed distance from points ``(..., 3)`` to boxes ``(..., 6)``: negative inside."""
    lo, hi = aabb_bounds(box)
    center, half = (lo + hi) / 2, (hi - lo) / 2
    d = (points - center).abs() - half
    outside = d.clamp(min=0).norm(dim=-1)
    inside = d.max(dim=-1).values.clamp(max=0)
    return outside + inside


def sphere_box_distance(centres: torch.Tensor, radii: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Signed distance between sphere surfaces and boxes: ``< 0`` means they intersect.

    Args:
        centres: ``(..., 3)`` sphere centres.
        radii: ``(...)`` radii, broadcastable to ``centres.shape[:-1]``.
        box: ``(..., 6)`` boxes, broadcastable against ``centres``.
    """
    return point_box_signed_distance(centres, box) - radii


def in_box(points: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Whether points ``(..., 3)`` lie in the closed box ``[low, high]``."""
    return ((points >= low) & (points <= high)).all(-1)
