"""modules.ReLU: nn.ReLU's values and gradients, eager, compiled and inside a vmapped ensemble, and what the compiled graph runs."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

from torchrl_silp.modules import ReLU


def relu_by_hand(x):
    return torch.where(x > 0, x, torch.zeros_like(x))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-5, 5, width=32), min_size=1, max_size=40))
def test_values_and_gradient_are_relus(values):
    x = torch.tensor(values, requires_grad=True)
    y = ReLU()(x)
    assert torch.equal(y, relu_by_hand(x.detach()))
    (y * torch.arange(1.0, len(values) + 1)).sum().backward()
    # d/dx relu(x) is 1 above 0 and 0 at and below it (PyTorch's convention at 0)
    assert torch.equal(x.grad, torch.where(x.detach() > 0, torch.arange(1.0, len(values) + 1), 0.0))


def ensemble_step(act, compiled: bool):
    """Outputs and parameter gradients of a two-member MLP ensemble called through torch.vmap, as SAC's critic is."""
    torch.manual_seed(0)
    nets = [MLP(in_features=7, num_cells=[32, 32], out_features=1, activation_class=act) for _ in range(2)]
    params = TensorDict.from_modules(*nets, as_module=True)
    x = torch.randn(64, 7)
    x[:8] = -10.0  # rows whose first layer is inactive in places

    def call(data, p):
        with p.to_module(nets[0]):
            return nets[0](data)

    def step():
        y = torch.vmap(call, (None, 0))(x, params)
        y.square().sum().backward()
        return y

    fn = torch.compile(step) if compiled else step  # (backward breaks the graph)
    y = fn()
    return y.detach(), [p.grad.clone() for p in params.values(True, True)]


@pytest.mark.parametrize("compiled", [False, True])
def test_a_vmapped_ensemble_learns_exactly_as_with_nn_relu(compiled):
    y_ref, grads_ref = ensemble_step(nn.ReLU, compiled=False)
    y, grads = ensemble_step(ReLU, compiled=compiled)
    torch.testing.assert_close(y, y_ref, rtol=1e-5, atol=1e-6)
    assert len(grads) == len(grads_ref) == 6  # 3 layers x (weight, bias), each stacked over the 2 members
    assert all(g.shape[0] == 2 for g in grads)
    for g, g_ref in zip(grads, grads_ref):
        torch.testing.assert_close(g, g_ref, rtol=1e-4, atol=1e-5)


def test_compiled_on_cpu_with_gradient_it_is_the_custom_operator_and_saves_no_mask():
    net = nn.Sequential(nn.Linear(5, 16), ReLU(), nn.Linear(16, 1))
    x = torch.randn(32, 5)
    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    torch.compile(lambda data: net(data).sum(), backend=backend, fullgraph=True)(x)
    targets = {str(node.target) for node in graphs[0].graph.nodes if node.op == "call_function"}
    assert "torchrl_silp.relu.default" in targets
    assert not any("relu" in t and "torchrl_silp" not in t for t in targets)


def test_without_gradient_the_compiled_graph_keeps_the_plain_relu():
    net = nn.Sequential(nn.Linear(5, 16), ReLU(), nn.Linear(16, 1))
    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    with torch.no_grad():
        torch.compile(lambda data: net(data), backend=backend, fullgraph=True)(torch.randn(4, 5))
    targets = {str(node.target) for node in graphs[0].graph.nodes if node.op == "call_function"}
    assert "torchrl_silp.relu.default" not in targets
    assert any("relu" in t for t in targets)


def test_a_state_dict_of_an_mlp_with_nn_relu_loads():
    old = MLP(in_features=4, num_cells=[8], out_features=2, activation_class=nn.ReLU)
    new = MLP(in_features=4, num_cells=[8], out_features=2, activation_class=ReLU)
    new.load_state_dict(old.state_dict())
    x = torch.randn(10, 4)
    torch.testing.assert_close(new(x), old(x))
