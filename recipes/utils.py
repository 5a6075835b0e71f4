"""The recipe helpers in one namespace: the public names of ``builders``, ``update``, ``checkpointing``,
``metrics`` and ``start``, re-exported.

Importable as ``torchrl_silp.recipes.utils`` and, from the repository root, as ``recipes.utils``;
code of the recipes imports the module that holds a name.

Examples:
    >>> from torchrl_silp.recipes import builders, checkpointing, utils
    >>> utils.make_model is builders.make_model and utils.load_trained_networks is checkpointing.load_trained_networks
    True
"""

from __future__ import annotations

from torchrl_silp.recipes.builders import (
    EXPLORATION_MODES, make_model, observation_keys, make_observation_transform, make_env, make_actor_critic,
    make_exploration, make_policy, make_collector, make_buffers, DEMO_ROWS_CHOICES, demo_rows_of, make_loss,
    rl_loss_of, make_optimizers,
)
from torchrl_silp.recipes.update import (
    check_compile, GradientStep, make_gradient_step, compile_update, compile_kwargs,
)
from torchrl_silp.recipes.checkpointing import (
    RESUME_FIELDS, RESUME_PRESENCE_FIELDS, RESUME_RETIRED_FIELDS, RESUME_MODES, check_resume, save_checkpoint,
    StopRequest, training_state, restore, load_checkpoint, checkpoint_exists, load_trained_networks,
)
from torchrl_silp.recipes.metrics import (
    new_counters, log_metrics, batch_metrics, plot_learning_curve, summarize, write_json, write_results,
    truncate_logs,
)
from torchrl_silp.recipes.start import (
    check_device, resolve_device, start_run,
)

__all__ = [
    "EXPLORATION_MODES", "make_model", "observation_keys", "make_observation_transform", "make_env",
    "make_actor_critic", "make_exploration", "make_policy", "make_collector", "make_buffers", "DEMO_ROWS_CHOICES",
    "demo_rows_of", "make_loss", "rl_loss_of", "make_optimizers", "check_compile", "GradientStep",
    "make_gradient_step", "compile_update", "compile_kwargs", "RESUME_FIELDS", "RESUME_PRESENCE_FIELDS",
    "RESUME_RETIRED_FIELDS", "RESUME_MODES", "check_resume", "save_checkpoint", "StopRequest", "training_state",
    "restore", "load_checkpoint", "checkpoint_exists", "load_trained_networks", "new_counters", "log_metrics",
    "batch_metrics", "plot_learning_curve", "summarize", "write_json", "write_results", "truncate_logs",
    "check_device", "resolve_device", "start_run",
]
