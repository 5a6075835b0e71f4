"""The recipes' gradient update: one step on a sampled batch, and its compilation.

:class:`GradientStep` sums the loss's ``loss_*`` terms, steps every optimiser and the target
update (TorchRL's SOTA recipes' ``update(td)``); :func:`compile_update` compiles it under
``cfg.compile`` (``torch.compile`` of the loss, optionally a CUDA graph of the whole step), falling
back on the eager step, with a line on the console, when compiling or capturing fails;
:func:`check_compile` refuses what cannot run.
"""

from __future__ import annotations

import torch

from torchrl_silp.compiling import compile_kwargs as _compile_kwargs
from torchrl_silp.recipes.builders import demo_rows_of


def check_compile(cfg, device: torch.device) -> None:
    """Refuses a ``cfg.compile`` that cannot run on ``device``, naming the field."""
    comp = cfg.get("compile")
    if comp is None:
        return
    compile_kwargs(cfg)  # refuses an unknown compile.guards
    if not comp.get("cudagraphs", False):
        return
    if device.type != "cuda":
        raise ValueError(f"compile.cudagraphs captures the update in a CUDA graph: it needs device=cuda, "
                         f"but the run's device is {device.type}")
    if comp.get("compile_mode") == "reduce-overhead":
        raise ValueError("compile.cudagraphs and compile.compile_mode=reduce-overhead both capture CUDA graphs: "
                         "choose one")
    if cfg.silp.bc and demo_rows_of(cfg) != "mask":
        raise ValueError(f"compile.cudagraphs needs fixed shapes: set silp.demo_rows=mask or auto (got "
                         f"{cfg.silp.demo_rows!r}, whose demo rows are a shape that depends on the batch)")


class GradientStep:
    """One gradient update on a sampled batch: the losses, backward, every optimiser's step, the target
    update; calling it returns the detached loss TensorDict.

    :attr:`loss_fn` (the loss's forward) is the part :func:`compile_update` compiles; AOTAutograd
    compiles its backward with it. ``.backward()`` and the optimisers' fused steps and the target
    update run eagerly around it: dynamo cannot trace ``Tensor.backward()``, and a graph break there
    makes it trace the whole loss a second time; traced, each
    ``Optimizer.step`` breaks the graph twice, and in a loop over optimisers dynamo gives up on the
    whole function.
    """

    def __init__(self, loss, optimizers: dict, updater):
        self.loss, self.optimizers, self.updater = loss, optimizers, updater
        self.loss_fn = loss

    def forward_backward(self, sample):
        loss_td = self.loss_fn(sample)
        sum(v for k, v in loss_td.items() if k.startswith("loss_")).backward()
        return loss_td.detach()

    def zero_grad(self) -> None:
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)

    def __call__(self, sample):
        self.zero_grad()
        loss_td = self.forward_backward(sample)
        for opt in self.optimizers.values():
            opt.step()
        self.updater.step()
        return loss_td


def make_gradient_step(loss, optimizers: dict, updater) -> GradientStep:
    """The recipe's update (:class:`GradientStep`)."""
    return GradientStep(loss, optimizers, updater)


def compile_update(cfg, gradient_step):
    """``gradient_step`` compiled with ``torch.compile`` when ``cfg.compile.compile`` (TorchRL's SOTA recipes'
    switch), else itself: of a :class:`GradientStep`, its loss's forward (and so, through AOTAutograd, its
    backward); any other callable whole; with :func:`compile_kwargs` (``compile.compile_mode`` and
    ``compile.guards``). A first call whose compilation fails (a ``RuntimeError``: e.g. no C++ compiler for
    inductor's CPU code) says so on the console and runs eagerly from then on; any other error is the
    step's own and propagates.

    With ``cfg.compile.cudagraphs`` the whole step (forward, backward, the optimisers' steps and the target
    update) is then captured in a CUDA graph by tensordict's ``CudaGraphModule``, as TorchRL's SOTA recipes
    do, and replayed on each call after ``cfg.compile.warmup`` warm-up calls; a capture that fails (a
    ``RuntimeError``, as CUDA refuses an operation while it captures) says so on the console and the step
    runs uncaptured from then on (:func:`check_compile` has refused what cannot work)."""
    step = _compile_loss(cfg, gradient_step) if cfg.compile.compile else gradient_step
    if not cfg.compile.get("cudagraphs", False):
        return step
    return _capture_cuda_graph(step, cfg.compile.warmup)


def _capture_cuda_graph(step, warmup: int):
    from tensordict.nn import CudaGraphModule

    done = []  # the outputs of the step's own runs during the capturing call

    def counted(sample):
        out = step(sample)
        done.append(out)
        return out

    graphed = CudaGraphModule(counted, in_keys=[], out_keys=[], warmup=warmup)
    chosen = []

    def call(sample):
        if chosen:
            return chosen[0](sample)
        if graphed.counter < warmup - 1:  # a warm-up call: the step runs as itself
            return graphed(sample)
        done.clear()
        try:
            out = graphed(sample)  # one run of the step, then its capture (recorded, not run)
            chosen.append(graphed)
        # CUDA and CudaGraphModule refuse what cannot be captured with RuntimeErrors; a failed capture ran
        # none of what it recorded
        except RuntimeError as err:
            _say_fallback("compile.cudagraphs: the capture failed", err, "the update runs without a CUDA graph")
            chosen.append(step)
            # the batch's update ran before the capture began: not again
            out = done[0] if done else step(sample)
        return out

    return call


def compile_kwargs(cfg) -> dict:
    """``torch.compile``'s keyword arguments for the update under ``cfg.compile``: its ``compile_mode``, and
    with ``guards=inputs`` no checks on the loss's modules or on module globals before each call
    (:func:`torchrl_silp.compiling.compile_kwargs`). The recipes build their loss once and change its
    parameters only in place, so those checks cannot fail in their runs; a script that changes a loss
    attribute mid-run needs ``compile.guards=all``."""
    return _compile_kwargs(cfg.compile.get("guards", "all"), cfg.compile.compile_mode, name="compile.guards")


def _compile_loss(cfg, gradient_step):
    if not isinstance(gradient_step, GradientStep):
        return _falling_back(torch.compile(gradient_step, **compile_kwargs(cfg)), gradient_step)
    # a new step on the same loss and optimisers; its first forward and backward (where inductor
    # compiles the backward) fall back on the eager ones together
    step = GradientStep(gradient_step.loss, gradient_step.optimizers, gradient_step.updater)
    step.loss_fn = torch.compile(gradient_step.loss_fn, **compile_kwargs(cfg))
    step.forward_backward = _falling_back(step.forward_backward, gradient_step.forward_backward,
                                          on_failure=step.zero_grad)
    return step


def _falling_back(compiled, eager, on_failure=None):
    """``compiled`` from its first call on, or ``eager`` if that call raises (warning once)."""
    chosen = []

    def call(sample):
        if chosen:
            return chosen[0](sample)
        try:
            out = compiled(sample)
            chosen.append(compiled)
        # dynamo's and inductor's failures (no C++ compiler, a backend or lowering error) are RuntimeErrors;
        # any other error is the function's own, which the eager function would raise too
        except RuntimeError as err:
            _say_fallback("compile.compile: torch.compile failed", err, "the update runs eagerly")
            chosen.append(eager)
            if on_failure is not None:
                on_failure()  # whatever the failed call accumulated
            out = eager(sample)
        return out

    return call


def _say_fallback(what: str, err: Exception, then: str) -> None:
    """One console line: what failed, the error's first 300 characters, and how the update runs instead."""
    message = " ".join(str(err).split())[:300]
    print(f"{what} ({type(err).__name__}: {message}); {then}", flush=True)


def normalize_batch(norm, sample):
    """``sample`` with its normalised observation recomputed by ``norm`` (a
    :class:`~torchrl_silp.RunningObservationNorm`) at the root and under ``"next"``, with the statistics
    of now: the buffers hold raw observations, and what they stored of an older normalisation is replaced."""
    norm(sample)
    norm(sample.get("next"))
    return sample


def run_updates(n: int, stop, gradient_step, buffers, averaged, actor, counters: dict, state, progress,
                norm=None) -> list:
    """Up to ``n`` gradient updates on batches of ``buffers``, stopping early on a stop request; the updates
    left go to ``counters["updates_owed"]`` (made first on resume). Each update also steps the averaged actor.
    ``norm``: the run's :class:`~torchrl_silp.RunningObservationNorm`, applied to each batch (:func:`normalize_batch`).

    ``state.compile_left`` counts the updates until the compiled update has settled: the progress bar says
    "compiling" meanwhile. Returns the updates' loss TensorDicts.
    """
    losses = []
    for i in range(n):
        if stop.requested:
            counters["updates_owed"] = n - i
            break
        if state.compile_left:
            progress.show(phase="compiling")
        sample = buffers.sample()
        if norm is not None:
            sample = normalize_batch(norm, sample)
        losses.append(gradient_step(sample))
        if averaged is not None:
            averaged.update_parameters(actor)
        counters["updates"] += 1
        if state.compile_left:
            state.compile_left -= 1
            if not state.compile_left:
                progress.show(phase="training")
        elif i % 20 == 0:
            progress.show(phase="training")
    else:
        counters["updates_owed"] = 0
    progress.show()
    return losses
