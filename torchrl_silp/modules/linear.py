"""A linear layer whose float32 CPU products run through oneDNN."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["Linear", "onednn_linear_available", "with_onednn_linear"]


def onednn_linear_available() -> bool:
    """Whether this torch build has oneDNN's float32 linear (``torch.ops.mkldnn._linear_pointwise``)."""
    try:
        x = torch.ones(2, 3)
        out = torch.ops.mkldnn._linear_pointwise(x, torch.ones(4, 3), None, "none", [], "")
    except (AttributeError, RuntimeError):
        return False
    return bool((out == 3).all())


# defined through torch.library directly rather than torch.library.custom_op, whose per-call
# checks (input aliasing, keysets) cost more than a 256 x 256 product's gain over MKL
_LIBRARY = torch.library.Library("torchrl_silp", "FRAGMENT")
_LIBRARY.define("linear(Tensor x, Tensor weight, Tensor? bias) -> Tensor")


try:
    _POINTWISE = torch.ops.mkldnn._linear_pointwise.default
except (AttributeError, RuntimeError):  # a torch build without oneDNN: Linear keeps torch's path
    _POINTWISE = None


@torch.library.impl(_LIBRARY, "linear", "CPU")
def _linear_cpu(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    # oneDNN's linear flattens and packs the input itself. A weight laid out by rows or by columns (the
    # backward's W^T and x^T) goes in as it is: oneDNN reorders the weight into its own layout on every
    # call anyway, reading either order, so a transposing copy first would only add a pass over it.
    # This body runs on every layer call, so it does nothing else.
    if weight.stride(1) != 1 and weight.stride(0) != 1:
        weight = weight.contiguous()
    return _POINTWISE(x, weight, bias, "none", [], "")


@torch.library.register_fake("torchrl_silp::linear")
def _(x, weight, bias):
    return x.new_empty(*x.shape[:-1], weight.shape[0])


_linear = torch.ops.torchrl_silp.linear.default

# below this many rows a oneDNN call's fixed cost outweighs its faster arithmetic: on an AMD EPYC,
# an MLP of the recipes' shape runs its forward faster through oneDNN from ~96 rows on one thread
# and ~256 on two (benchmarks/linear_layers.py); a collector's 32-row policy call stays on torch's
MIN_ROWS = 128


def _product(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    if x.numel() >= MIN_ROWS * x.shape[-1]:
        return _linear(x, weight, bias)
    return F.linear(x, weight, bias)


def _setup_context(ctx, inputs, output):
    x, weight, bias = inputs
    ctx.save_for_backward(x, weight)
    ctx.has_bias = bias is not None


def _backward(ctx, grad):
    x, weight = ctx.saved_tensors
    rows, grad_rows = x.reshape(-1, x.shape[-1]), grad.reshape(-1, grad.shape[-1])
    grad_x = grad_w = grad_b = None
    if ctx.needs_input_grad[0]:
        grad_x = _product(grad, weight.t(), None)
    if ctx.needs_input_grad[1]:
        # dL/dW = grad^T x: the same product with the batch as the summed dimension
        grad_w = _product(grad_rows.t(), rows.t(), None)
    if ctx.has_bias and ctx.needs_input_grad[2]:
        grad_b = grad_rows.sum(0)
    return grad_x, grad_w, grad_b


torch.library.register_autograd("torchrl_silp::linear", _backward, setup_context=_setup_context)


@torch.library.register_vmap("torchrl_silp::linear")
def _(info, in_dims, x, weight, bias):
    x_dim, weight_dim, bias_dim = in_dims
    if weight_dim is None and bias_dim is None:
        # one layer for every member: the members' rows are rows of one product
        return _product(x, weight, bias), x_dim
    # an ensemble's own layers: one product per member (a handful, not the batch)
    size = info.batch_size
    xs = x.movedim(x_dim, 0) if x_dim is not None else x.expand(size, *x.shape)
    weights = weight.movedim(weight_dim, 0) if weight_dim is not None else weight.expand(size, *weight.shape)
    if bias is None:
        biases = [None] * size
    else:
        biases = bias.movedim(bias_dim, 0) if bias_dim is not None else bias.expand(size, *bias.shape)
    return torch.stack([_product(xs[i], weights[i], biases[i]) for i in range(size)]), 0


_ONEDNN = onednn_linear_available()  # once, at import: a compiled forward reads a constant


class Linear(nn.Linear):
    """:class:`torch.nn.Linear` whose float32 CPU products run through oneDNN.

    torch's CPU matrix product calls MKL, whose float32 kernels on AMD CPUs are
    its AVX2 ones; oneDNN, part of torch's CPU build, uses the AVX-512 units
    where the CPU has them. The forward and both backward products (input and
    weight gradients) go through oneDNN's float32 linear, as the
    ``torchrl_silp::linear`` operator, which ``torch.compile`` calls as it is
    and ``torch.func.vmap`` runs once per member of a vmapped ensemble.
    Float32 throughout: outputs and gradients equal ``nn.Linear``'s up to the
    order of the sums. A product of fewer than :data:`MIN_ROWS` rows (one
    task's policy step, a collector's step over 32 envs) takes torch's path:
    there oneDNN's fixed cost per call outweighs its rate. So do other dtypes
    and devices, and a torch build without oneDNN. Same parameters and state
    dict as ``nn.Linear``.

    It pays where the products dominate: a compiled update of a few hundred
    rows on one thread. An eager backward pays the operator's Python autograd
    per layer, and on two threads torch's products close most of the gap, so
    there ``nn.Linear`` is as fast or faster; ``benchmarks/linear_layers.py``
    measures the crossover on a given machine.

    Examples:
        >>> import torch
        >>> from torchrl.modules import MLP
        >>> from torchrl_silp.modules import Linear
        >>> net = MLP(in_features=24, num_cells=[256, 256], out_features=1, layer_class=Linear)
        >>> net(torch.zeros(8, 24)).shape
        torch.Size([8, 1])
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (
            x.device.type == "cpu" and x.dtype == torch.float32 and self.weight.dtype == torch.float32
            and x.shape[-1] == self.in_features and _ONEDNN
        ):
            return _product(x, self.weight, self.bias)
        return super().forward(x)


def with_onednn_linear(module: nn.Module) -> nn.Module:
    """Make every ``nn.Linear`` of ``module`` a :class:`Linear`, in place (and return ``module``).

    A lazy layer (``nn.LazyLinear``, what TorchRL's ``MLP`` builds without
    ``in_features``) becomes one when it materialises. Parameters, state dict and
    outputs stay those of the ``nn.Linear``.

    Examples:
        >>> import torch
        >>> from torchrl.modules import MLP
        >>> from torchrl_silp.modules import Linear, with_onednn_linear
        >>> net = with_onednn_linear(MLP(num_cells=[32], out_features=1))
        >>> _ = net(torch.zeros(4, 7))
        >>> [type(m).__name__ for m in net if isinstance(m, torch.nn.Linear)]
        ['Linear', 'Linear']
    """
    for layer in module.modules():
        if isinstance(layer, nn.LazyLinear):
            layer.cls_to_become = Linear
        elif type(layer) is nn.Linear:
            layer.__class__ = Linear
    return module
