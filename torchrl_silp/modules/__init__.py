"""Policy-side modules: GP-guided exploration."""

from torchrl_silp.modules.gp_exploration import (
    GP_EXPLORATION_MODES,
    GPGuidedExploration,
    fit_gp_hyperparameters,
    gp_negative_log_marginal_likelihood,
    gp_nll_gradient,
    gp_posterior,
    matern52_kernel,
)

__all__ = [
    "GPGuidedExploration",
    "GP_EXPLORATION_MODES",
    "matern52_kernel",
    "gp_posterior",
    "gp_negative_log_marginal_likelihood",
    "gp_nll_gradient",
    "fit_gp_hyperparameters",
]
