"""``torch.compile`` for functions called many times on inputs of one structure: the update, a robot's step."""

from __future__ import annotations

import torch

from torchrl_silp.choices import GUARDS
from torchrl_silp.validation import check_choice

__all__ = ["GUARDS", "compile_kwargs", "skip_module_and_global_guards"]


def skip_module_and_global_guards(guard_entries) -> list[bool]:
    """A ``guard_filter_fn`` for ``torch.compile``: dynamo's ``skip_guard_on_all_nn_modules_unsafe`` and
    ``skip_guard_on_globals_unsafe`` together.

    What stays checked on each call: the compiled function's own arguments (their types, keys,
    shapes, dtypes and devices), attributes of non-module objects, and torch's global state
    (grad mode, default device).
    """
    keep_modules = torch.compiler.skip_guard_on_all_nn_modules_unsafe(guard_entries)
    keep_globals = torch.compiler.skip_guard_on_globals_unsafe(guard_entries)
    return [module and glob for module, glob in zip(keep_modules, keep_globals)]


def compile_kwargs(guards: str = "inputs", mode: str | None = None, *, name: str = "guards") -> dict:
    """``torch.compile``'s keyword arguments for a function compiled once and called many times.

    Before each call of a compiled function, dynamo checks its guards: that no attribute of
    the ``nn.Module`` objects it reads and no global of the modules its code reads has changed
    since it compiled, and that the arguments have the structure it compiled for. Over
    TensorDict and TorchRL objects these are thousands of checks, and for a small function
    (a policy's step on one task, a loss at batch 256 on one thread) checking them is a
    visible part of each call.

    Args:
        guards: ``"inputs"`` drops the checks on modules and globals
            (:func:`skip_module_and_global_guards`) and keeps those on the arguments and on
            torch's global state. Parameters that change in place (an optimiser's step, a
            ``load_state_dict``) are read on each call either way. What the compiled code would
            miss is a changed module attribute (a coefficient, a key, a swapped sub-network) or a
            changed module global: it keeps running the graph compiled before the change.
            ``"all"`` keeps every guard, for code that changes those between calls.
        mode: ``torch.compile``'s mode.
        name: what the error for an unknown ``guards`` calls it (a config field, for a recipe).

    Under ``"inputs"`` each ``torch.compile`` call keeps its compiled graphs to itself
    (``isolate_recompiles``): dynamo otherwise shares them among every compile of the same
    function, and a graph that checks no module would run for another object of the same class
    compiled later, whatever that object's attributes.

    Examples:
        >>> import torch
        >>> net = torch.nn.Linear(3, 2)
        >>> step = torch.compile(net, **compile_kwargs("inputs"))
        >>> step(torch.zeros(4, 3)).shape
        torch.Size([4, 2])
    """
    check_choice(guards, GUARDS, name=name)
    if guards == "all":
        return {"mode": mode}
    # torch.compile takes a mode or options, not both, and the guard filter only goes in through options: the
    # mode goes in as the options it stands for. No public API maps a mode to its options; torch.compile's own
    # docstring points to this one (tests/test_compiling.py pins the options of two modes).
    from torch._inductor import list_mode_options  # private: no public equivalent

    return {"options": {**list_mode_options(mode or "default"), "guard_filter_fn": skip_module_and_global_guards},
            "isolate_recompiles": True}
