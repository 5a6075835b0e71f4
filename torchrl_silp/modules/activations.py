"""A ReLU for networks whose update is compiled on CPU."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["ReLU"]


@torch.library.custom_op("torchrl_silp::relu", mutates_args=())
def _relu(x: torch.Tensor) -> torch.Tensor:
    return torch.relu(x)


@_relu.register_fake
def _(x):
    return torch.empty_like(x)


@torch.library.custom_op("torchrl_silp::relu_backward", mutates_args=())
def _relu_backward(grad: torch.Tensor, output: torch.Tensor) -> torch.Tensor:
    return torch.ops.aten.threshold_backward(grad, output, 0.0)


@_relu_backward.register_fake
def _(grad, output):
    return torch.empty_like(grad)


def _setup_context(ctx, inputs, output):
    ctx.save_for_backward(output)


def _backward(ctx, grad):
    (output,) = ctx.saved_tensors
    # an operator too: written in plain ops, inductor moves the comparison into the
    # forward and saves its bool result again
    return _relu_backward(grad, output)


_relu.register_autograd(_backward, setup_context=_setup_context)


def _batched(x: torch.Tensor, dim: int | None, size: int) -> torch.Tensor:
    if dim is None:
        return x.expand(size, *x.shape)
    return x.movedim(dim, 0)


@_relu.register_vmap
def _(info, in_dims, x):
    return _relu(x), in_dims[0]


@_relu_backward.register_vmap
def _(info, in_dims, grad, output):
    grad_dim, output_dim = in_dims
    grad = _batched(grad, grad_dim, info.batch_size).contiguous()
    output = _batched(output, output_dim, info.batch_size).contiguous()
    return _relu_backward(grad, output), 0


class ReLU(nn.Module):
    """:class:`torch.nn.ReLU`, computed the same way, that a CPU ``torch.compile`` leaves to ATen's own kernels.

    Traced by ``torch.compile`` on a CPU tensor with gradient enabled, it is an
    opaque operator (the ``torchrl_silp::relu`` custom op: ATen's ``relu``, and
    ``threshold_backward`` for its backward) that saves its float output for the
    backward. With ``nn.ReLU`` inductor fuses the activation into its neighbours
    and saves a bool mask of the active units instead, and inductor's CPU code
    stores bool tensors an order of magnitude slower than ATen does, which made
    a compiled, vmapped Q-ensemble's forward and backward twice as slow as the
    eager ones. Eager code, code traced without gradient (nothing is saved
    then) and CUDA tensors call ``torch.relu``. Outputs and gradients are those
    of ``nn.ReLU`` exactly, and the module has no state, so it swaps in for
    ``nn.ReLU`` in a trained network.

    Examples:
        >>> from torchrl.modules import MLP
        >>> from torchrl_silp.modules import ReLU
        >>> net = MLP(num_cells=[256, 256], out_features=1, activation_class=ReLU)
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # (grad mode rather than x.requires_grad: inside torch.func.vmap a traced input reports False)
        if torch.compiler.is_compiling() and torch.is_grad_enabled() and x.device.type == "cpu":
            return _relu(x)
        return torch.relu(x)
