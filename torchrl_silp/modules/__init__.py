"""Policy- and network-side modules: GP-guided exploration, the next-goal Q-network input, actor averaging.

The networks themselves are TorchRL's ``MLP`` of stock ``nn.Linear`` and ``nn.ReLU`` layers.
"""

from torchrl_silp.modules.averaging import make_averaged_actor
from torchrl_silp.modules.gp_exploration import (
    GP_EXPLORATION_MODES,
    GP_STATE_KEYS,
    GPGuidedExploration,
    fit_gp_hyperparameters,
    gp_negative_log_marginal_likelihood,
    gp_nll_gradient,
    gp_posterior,
    matern52_kernel,
)
from torchrl_silp.modules.networks import NextGoalOffsetQ

__all__ = [
    "GPGuidedExploration",
    "GP_EXPLORATION_MODES",
    "GP_STATE_KEYS",
    "NextGoalOffsetQ",
    "make_averaged_actor",
    "matern52_kernel",
    "gp_posterior",
    "gp_negative_log_marginal_likelihood",
    "gp_nll_gradient",
    "fit_gp_hyperparameters",
]
