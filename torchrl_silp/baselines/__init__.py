"""Baselines of the paper's Table 1 that are not TorchRL training recipes: OMPL's PRM (PRM-0.1, PRM-1).

OMPL is an optional dependency (``pip install "torchrl_silp[planning]"``): this
package imports without it, and its classes and functions raise an
``ImportError`` naming the extra when used.
"""

from torchrl_silp.baselines.prm import (
    PathReplayPolicy,
    PRMPlanner,
    collect_prm_demonstrations,
    evaluate_prm,
    path_to_actions,
    prm_demonstration_batches,
    prm_demonstration_stats,
)

__all__ = [
    "PRMPlanner",
    "PathReplayPolicy",
    "path_to_actions",
    "evaluate_prm",
    "collect_prm_demonstrations",
    "prm_demonstration_batches",
    "prm_demonstration_stats",
]
