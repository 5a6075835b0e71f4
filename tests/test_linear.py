"""torchrl_silp.modules.Linear: nn.Linear's outputs and gradients, its products through oneDNN."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn
from torch.func import functional_call, stack_module_state, vmap
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.modules import MLP

from torchrl_silp.modules import Linear, onednn_linear_available, with_onednn_linear
from torchrl_silp.modules.linear import MIN_ROWS

pytestmark = pytest.mark.skipif(not onednn_linear_available(), reason="this torch build has no oneDNN linear")


class Calls(TorchDispatchMode):
    """The operators a block of code dispatches, by name."""

    def __init__(self):
        super().__init__()
        self.names = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names.append(str(func._overloadpacket))
        return func(*args, **(kwargs or {}))


def pair(in_features: int, out_features: int, seed: int = 0) -> tuple[nn.Linear, Linear]:
    torch.manual_seed(seed)
    reference = nn.Linear(in_features, out_features)
    layer = Linear(in_features, out_features)
    layer.load_state_dict(reference.state_dict())
    return reference, layer


def float64_grads(reference: nn.Linear, x: torch.Tensor, weight_of_output: torch.Tensor):
    """Output and gradients of sum(weight_of_output * (x W^T + b)), in float64: the independent figure."""
    w = reference.weight.detach().double().requires_grad_()
    b = reference.bias.detach().double().requires_grad_()
    x64 = x.detach().double().requires_grad_()
    out = x64 @ w.T + b
    (out * weight_of_output.double()).sum().backward()
    return out, x64.grad, w.grad, b.grad


@settings(max_examples=25, deadline=None)
@given(rows=st.integers(1, 300), lead=st.sampled_from([(), (3,)]), in_features=st.integers(1, 40),
       out_features=st.integers(1, 40))
def test_outputs_and_gradients_are_those_of_the_float64_product(rows, lead, in_features, out_features):
    reference, layer = pair(in_features, out_features)
    x = torch.randn(*lead, rows, in_features, requires_grad=True)
    g = torch.randn(*lead, rows, out_features)
    out = layer(x)
    (out * g).sum().backward()
    exact, gx, gw, gb = float64_grads(reference, x, g)
    # float32 sums of up to 900 products of size ~1
    tol = dict(atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out.double(), exact, **tol)
    torch.testing.assert_close(x.grad.double(), gx, **tol)
    torch.testing.assert_close(layer.weight.grad.double(), gw, **tol)
    torch.testing.assert_close(layer.bias.grad.double(), gb, **tol)


def test_batches_of_many_rows_go_through_onednn_and_single_rows_through_torch():
    _, layer = pair(256, 256)
    for rows, through_onednn in ((MIN_ROWS, True), (MIN_ROWS - 1, False), (1, False), (256, True)):
        with Calls() as calls:
            layer(torch.randn(rows, 256))
        assert ("torchrl_silp.linear" in calls.names) == through_onednn, (rows, calls.names)
    with Calls() as calls:  # float64 is not oneDNN's
        layer.double()(torch.randn(256, 256, dtype=torch.float64))
    assert "torchrl_silp.linear" not in calls.names


@pytest.mark.parametrize("layout", ["contiguous", "transposed", "padded rows", "every other column"])
def test_the_operator_multiplies_by_the_weights_values_whatever_its_strides(layout):
    # the backward hands the operator transposed views (W^T, x^T) without copying them first
    torch.manual_seed(0)
    x, dense = torch.randn(200, 48), torch.randn(160, 48)
    weight = {"contiguous": dense,
              "transposed": dense.t().contiguous().t(),
              "padded rows": torch.cat([dense, torch.randn(160, 7)], dim=1)[:, :48],
              "every other column": torch.stack([dense, torch.randn_like(dense)], dim=-1)[..., 0]}[layout]
    assert torch.equal(weight, dense)
    out = torch.ops.torchrl_silp.linear(x, weight, None)
    torch.testing.assert_close(out.double(), x.double() @ dense.double().T, atol=1e-4, rtol=1e-4)


def test_the_backward_products_go_through_onednn_copying_only_the_gradients_transpose():
    from torch.profiler import ProfilerActivity, profile

    _, layer = pair(256, 256)
    x = torch.randn(256, 256, requires_grad=True)
    out = layer(x)
    grad = torch.randn_like(out)
    with Calls() as calls:
        out.backward(grad, retain_graph=True)
    assert calls.names.count("torchrl_silp.linear") == 2, calls.names  # the input's and the weight's gradients
    with profile(activities=[ProfilerActivity.CPU]) as prof:  # it sees the operator's own calls too
        out.backward(grad)
    copies = [e.name for e in prof.events() if e.name in ("aten::clone", "aten::copy_")]
    # grad^T, the weight gradient's left operand, which oneDNN packs into rows itself; not W^T nor x^T
    assert copies == ["aten::clone", "aten::copy_"], copies


@pytest.mark.parametrize("x_batched", [False, True])
def test_a_vmapped_ensemble_computes_each_members_product_and_gradients(x_batched):
    members = [pair(24, 64, seed=k)[0] for k in range(3)]
    fast = [Linear(24, 64) for _ in members]
    for f, m in zip(fast, members):
        f.load_state_dict(m.state_dict())
    params, buffers = stack_module_state(fast)
    params = {k: v.detach().requires_grad_() for k, v in params.items()}
    shell = Linear(24, 64).to("meta")
    x = torch.randn(3, 100, 24) if x_batched else torch.randn(100, 24)
    out = vmap(lambda p, b, x: functional_call(shell, (p, b), (x,)), in_dims=(0, 0, 0 if x_batched else None))(
        params, buffers, x)
    (out ** 2).sum().backward()
    for k, member in enumerate(members):
        xk = x[k] if x_batched else x
        expected = member(xk)
        (expected ** 2).sum().backward()
        torch.testing.assert_close(out[k], expected, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(params["weight"].grad[k], member.weight.grad, atol=1e-3, rtol=1e-4)
        torch.testing.assert_close(params["bias"].grad[k], member.bias.grad, atol=1e-3, rtol=1e-4)


def test_a_compiled_network_learns_as_the_eager_torch_one():
    torch.manual_seed(0)
    reference = MLP(in_features=12, num_cells=[64, 64], out_features=3)
    fast = with_onednn_linear(MLP(in_features=12, num_cells=[64, 64], out_features=3))
    fast.load_state_dict(reference.state_dict())
    step = torch.compile(lambda net, x, y: ((net(x) - y) ** 2).mean())
    x, y = torch.randn(128, 12), torch.randn(128, 3)
    opt_ref, opt_fast = (torch.optim.SGD(n.parameters(), lr=0.1) for n in (reference, fast))
    for _ in range(5):
        for net, opt, loss_of in ((reference, opt_ref, lambda n: ((n(x) - y) ** 2).mean()), (fast, opt_fast, lambda n: step(n, x, y))):
            opt.zero_grad()
            loss_of(net).backward()
            opt.step()
    for a, b in zip(reference.parameters(), fast.parameters()):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    with Calls() as calls:
        fast(x)
    assert "torchrl_silp.linear" in calls.names


def test_with_onednn_linear_converts_plain_and_lazy_layers_keeping_their_state():
    torch.manual_seed(0)
    built = MLP(in_features=5, num_cells=[16], out_features=2)
    state = {k: v.clone() for k, v in built.state_dict().items()}
    assert with_onednn_linear(built) is built
    assert [type(m) for m in built if isinstance(m, nn.Linear)] == [Linear, Linear]
    assert all(torch.equal(v, state[k]) for k, v in built.state_dict().items())
    lazy = with_onednn_linear(MLP(num_cells=[16], out_features=2))
    lazy(torch.randn(40, 5))
    assert [type(m) for m in lazy if isinstance(m, nn.Linear)] == [Linear, Linear]
