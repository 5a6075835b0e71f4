"""An exponential moving average of the actor's parameters, with :class:`torch.optim.swa_utils.AveragedModel`.

The policy that is evaluated (and deployed) can be an average of the actor's
parameters over the updates rather than the last ones: it evens out the
swings of the online actor between evaluations. PyTorch's
:class:`~torch.optim.swa_utils.AveragedModel` with
:func:`~torch.optim.swa_utils.get_ema_multi_avg_fn` keeps it; this module only
starts it where the EMA of the training loop starts, from the actor's
parameters at construction.

Use::

    averaged = make_averaged_actor(actor, decay=0.995)   # after the actor's lazy layers are initialized
    ...                                                  # every update:
    optimizer.step()
    averaged.update_parameters(actor)
    ...                                                  # evaluate the average:
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        env.rollout(max_steps, averaged.module)          # a TensorDict module like the actor
    ...                                                  # checkpoint:
    state = averaged.state_dict()                        # "n_averaged" and "module.*"
    make_averaged_actor(new_actor, decay).load_state_dict(state)
    new_actor.load_state_dict(averaged.module.state_dict())  # or the average into an actor

``averaged`` itself is an ``nn.Module`` whose ``forward`` calls the copy, but
it is no TensorDict module (it has no ``in_keys`` / ``out_keys``): give TorchRL
(collectors, ``env.rollout``, evaluation helpers) ``averaged.module``.
"""

from __future__ import annotations

from torch import nn
from torch.nn.parameter import UninitializedParameter
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from torchrl_silp.validation import check_probability

__all__ = ["make_averaged_actor"]


def make_averaged_actor(actor: nn.Module, decay: float) -> AveragedModel:
    """An :class:`~torch.optim.swa_utils.AveragedModel` keeping the EMA of ``actor``'s parameters.

    The average starts at the actor's current parameters θ₀ (the first
    ``update_parameters`` of an ``AveragedModel`` would copy instead of
    averaging, so it is called here once). After ``k`` calls of
    ``averaged.update_parameters(actor)`` following parameter updates θ₁..θₖ,
    the average is ``decay^k θ₀ + (1 - decay) Σᵢ decay^(k-i) θᵢ``. Buffers are
    not averaged: they are copied from the actor at each update (the actors of
    the recipes hold only constant ones, such as the action bounds of
    :class:`~torchrl.modules.TanhModule`).

    The copy (``averaged.module``) is a deep copy of the actor, the same
    TensorDict module (a :class:`~torchrl.modules.ProbabilisticActor` stays one),
    on the actor's device; its parameters do not require gradients.

    Args:
        actor: the online actor; its lazy layers must be initialized (run it once).
        decay: the EMA decay in ``(0, 1)``; the average spans about ``1 / (1 - decay)`` updates.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_silp.modules.averaging import make_averaged_actor
        >>> actor = TensorDictModule(torch.nn.Linear(2, 1), in_keys=["observation"], out_keys=["action"])
        >>> averaged = make_averaged_actor(actor, decay=0.5)
        >>> w0 = actor.module.weight.detach().clone()
        >>> with torch.no_grad():
        ...     _ = actor.module.weight.add_(1.0)
        >>> averaged.update_parameters(actor)
        >>> torch.allclose(averaged.module.module.weight, w0 + 0.5)
        True
        >>> averaged.module(TensorDict(observation=torch.zeros(3, 2), batch_size=[3]))["action"].shape
        torch.Size([3, 1])
    """
    check_probability(decay, name="decay")
    if not isinstance(actor, nn.Module):
        raise TypeError(f"actor must be an nn.Module, got {type(actor).__name__}")
    if any(isinstance(p, UninitializedParameter) for p in actor.parameters()):
        raise RuntimeError("the actor has uninitialized (lazy) parameters: run it once on a batch before averaging it")
    averaged = AveragedModel(actor, multi_avg_fn=get_ema_multi_avg_fn(float(decay)), use_buffers=False)
    averaged.module.requires_grad_(False)
    averaged.update_parameters(actor)  # n_averaged 0 -> 1: the average starts at the actor's parameters
    return averaged
