"""compile_kwargs: which of dynamo's checks run before each call of a compiled function."""

import pytest
import torch
from tensordict import TensorDict

from torchrl_silp.compiling import GUARDS, compile_kwargs


class Scaled(torch.nn.Module):
    """A module whose forward reads a plain attribute: dynamo bakes its value into the graph and guards it."""

    def __init__(self, factor: float):
        super().__init__()
        self.factor = factor

    def forward(self, td):
        return td["x"] * self.factor


def batch(n: int, dtype=torch.float32) -> TensorDict:
    return TensorDict(x=torch.arange(n, dtype=dtype), batch_size=[n])


def test_inputs_keeps_the_argument_checks_and_each_compile_its_own_graphs():
    for guards in ("inputs", "all"):  # inputs first: its graphs, which check no module, must not serve the others
        modules = [Scaled(2.0), Scaled(5.0)]  # two objects of one class, as two runs in one process
        compiled = [torch.compile(m, **compile_kwargs(guards)) for m in modules]
        for module, fn in zip(modules, compiled):
            torch.testing.assert_close(fn(batch(4)), module.factor * torch.arange(4.0), msg=guards)
            # the argument is checked either way: another shape or dtype compiles anew
            torch.testing.assert_close(fn(batch(7)), module.factor * torch.arange(7.0), msg=guards)
            torch.testing.assert_close(fn(batch(4, torch.float64)),
                                       module.factor * torch.arange(4.0, dtype=torch.float64), msg=guards)
        modules[0].factor = 3.0
        # all: the changed attribute fails a guard and compiles anew; inputs: the graph compiled before runs
        expected = 3.0 if guards == "all" else 2.0
        torch.testing.assert_close(compiled[0](batch(4)), expected * torch.arange(4.0), msg=guards)
    # and a plain torch.compile after them compiles its own
    torch.testing.assert_close(torch.compile(Scaled(7.0))(batch(4)), 7.0 * torch.arange(4.0))


def test_parameters_changed_in_place_are_read_under_inputs():
    net = torch.nn.Linear(3, 2)
    step = torch.compile(net, **compile_kwargs("inputs"))
    x = torch.randn(5, 3)
    torch.testing.assert_close(step(x), net(x))
    with torch.no_grad():
        net.load_state_dict({"weight": torch.randn(2, 3), "bias": torch.randn(2)})  # copies in place
        net.weight.mul_(3.0)
    torch.testing.assert_close(step(x), x @ net.weight.detach().T + net.bias.detach())


def test_the_mode_goes_in_as_its_options_and_an_unknown_guards_is_refused():
    from torch._inductor import list_mode_options

    assert GUARDS == ("all", "inputs")
    assert compile_kwargs("all", "max-autotune") == {"mode": "max-autotune"}
    kwargs = compile_kwargs("inputs", "reduce-overhead")
    assert kwargs["options"].pop("guard_filter_fn") is not None
    assert kwargs == {"options": list_mode_options("reduce-overhead"), "isolate_recompiles": True}
    assert kwargs["options"]["triton.cudagraphs"] is True
    # the private map from a mode to its options, as torch.compile(mode=...) applies it: nothing for the
    # default mode, max_autotune for max-autotune, and torch.compile's own refusal of a mode it does not know
    assert list(compile_kwargs("inputs")["options"]) == ["guard_filter_fn"]
    assert compile_kwargs("inputs", "max-autotune-no-cudagraphs")["options"]["max_autotune"] is True
    with pytest.raises(RuntimeError, match="Unrecognized mode=fastest"):
        torch.compile(torch.nn.Identity(), mode="fastest")
    with pytest.raises(RuntimeError, match="Unrecognized mode=fastest"):
        compile_kwargs("inputs", "fastest")
    with pytest.raises(ValueError, match="guards must be one of \\('all', 'inputs'\\), got 'some'"):
        compile_kwargs("some")
