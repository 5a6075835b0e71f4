"""Where a training iteration's time goes: one gradient update of the recipe's loss, by part.

Builds the loss, optimisers and buffers exactly as ``recipes/sac_silp.py`` does
(same config, any hydra overrides), fills the buffers from a short rollout and
its planned demonstrations, then times (median of ``--reps`` calls):

* ``sample``: one ``MixedReplay.sample`` (N_D demos + N_pi interaction transitions);
* ``rl loss``: the wrapped actor-critic loss's forward (SAC: actor, 2 Q-nets, target);
* ``bc loss``: the SILP+ term's forward (actor on the demo rows + the reward filter's
  look-ahead through the task model's ``step``, f_s and f_r in one pass); ``bc loss,
  unfused model``: the same with the model's ``transition`` and ``outcome`` called
  one after the other (the kinematics run twice per look-ahead step), the A/B of
  the fused step in one run;
* ``update``: forward + backward + every optimiser step + the soft target update.

``--profile N`` then runs N more compiled updates under ``torch.profiler`` and splits their time
into what it went to: matrix products, inductor's generated kernels, other ATen operators, the
optimisers' steps, dynamo's guard checks, and what no operator accounts for (Python, autograd).

Each part runs eager and compiled (``torch.compile`` of the loss or its term with the recipe's
``compile_kwargs``; the update through the recipe's own ``compile_update``, so ``compile.compile_mode``
and ``compile.guards`` apply and ``compile.compile=false`` leaves it eager; ``--no-compile`` skips
those), and the arithmetic floor of the update is printed beside: its matrix products' FLOPs at the rate
this core reaches on a 256 x 256 x 256 product through torch's matmul, measured in the same run.

Run::

    python benchmarks/update_step.py                       # SAC-SILP+, the default config
    python benchmarks/update_step.py silp.bc=false silp.demos=false   # plain SAC
    python benchmarks/update_step.py --threads 1 optim.batch_size=512
    python benchmarks/update_step.py --threads 1 --profile 50    # and where the compiled update's time goes
    python benchmarks/update_step.py env=panda_reach      # another task model (an env config group)
    python benchmarks/update_step.py --threads 1 --against compile.guards=all   # and beside dynamo's every guard

``--against OVERRIDE`` builds the compiled update a second time, with the override added, and times the
two taking turns every 10 updates, so both see the same machine: the A/B of one setting in one
run, where two runs one after the other differ by the machine's own drift.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import torch
from timing import interleaved_median_ms, median_ms  # benchmarks/timing.py, beside this script

from torchrl_silp.objectives import SILPLoss
from torchrl_silp.recipes.builders import (
    make_actor_critic, make_buffers, make_env, make_loss, make_model, make_optimizers,
)
from torchrl_silp.recipes.schema import load_config
from torchrl_silp.recipes.start import resolve_device
from torchrl_silp.recipes.update import check_compile, compile_kwargs, compile_update, make_gradient_step


class _UnfusedModel:
    """A task model whose ``step`` is its ``transition`` then its ``outcome``: the kinematics run twice.

    Everything else is the wrapped model's. What ``SILPLoss`` would cost without the fused step.
    """

    def __init__(self, model):
        self.__dict__["_model"] = model

    def __getattr__(self, name):
        return getattr(self.__dict__["_model"], name)

    def step(self, state, action):
        nxt = self._model.transition(state, action)
        return (nxt, *self._model.outcome(state, nxt))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--reps", type=int, default=50)
    parser.add_argument("--no-compile", dest="compile", action="store_false", help="eager figures only")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="profile N compiled updates and print where their time goes")
    parser.add_argument("--against", action="append", default=[], metavar="OVERRIDE",
                        help="(repeatable) also build the compiled update with this hydra override added and time "
                             "it beside this config's, the two taking turns every 10 updates, --reps updates each")
    parser.add_argument("overrides", nargs="*", help="hydra overrides of recipes/config/sac_silp.yaml")
    args = parser.parse_args(argv)
    if args.profile < 0:
        parser.error(f"--profile must be a number of updates >= 0 (0: no profile), got {args.profile}")
    if args.against and not args.compile:
        parser.error("--against times two compiled updates; --no-compile has none")
    load = os.getloadavg()[0]  # before this benchmark's own work counts in it
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = _config(args.overrides)
    peer_cfg = _config(args.overrides + args.against) if args.against else None  # its errors before any work
    device = resolve_device(cfg)
    for each in (cfg, peer_cfg) if peer_cfg is not None else (cfg,):
        check_compile(each, device)  # as the recipe's start_run does
    if args.profile and device.type != "cpu":
        # the profiler's self times would be the host's kernel launches, not the device's work
        parser.error(f"--profile splits the update's CPU time; device={device.type} runs it elsewhere")
    loss, buffers, batch, gradient_step = _build(cfg, device)

    # name -> (eager call, maker of the compiled call); each compiled the way the recipe compiles it
    parts = {"sample": (buffers.sample, None)}
    if isinstance(loss, SILPLoss):
        parts["rl loss"] = (on_the_batch(loss.rl_loss, batch),
                            lambda: on_the_batch(torch.compile(loss.rl_loss, **compile_kwargs(cfg)), batch))
        parts["bc loss"] = (on_the_batch(loss.bc_loss, batch),
                            lambda: on_the_batch(torch.compile(loss.bc_loss, **compile_kwargs(cfg)), batch))
    else:
        parts["rl loss"] = (on_the_batch(loss, batch),
                            lambda: on_the_batch(torch.compile(loss, **compile_kwargs(cfg)), batch))
    compiled_update = []  # the update as compiled by its row, kept for --profile

    def make_compiled_update():
        compiled_update.append(on_the_batch(compile_update(cfg, gradient_step), batch))
        return compiled_update[-1]

    parts["update"] = (on_the_batch(gradient_step, batch), make_compiled_update)
    where = f", device {device} ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {platform.machine()}, "
          f"{os.cpu_count()} CPUs{where}{'' if load < 0.5 else f' (not alone: load average {load:.1f})'}; {cfg.env.name}, "
          f"batch {cfg.optim.batch_size}, network {list(cfg.network.hidden_sizes)}, overrides {args.overrides or 'none'}")
    print(f"{'part':>22s}  {'eager':>9s}  {'compiled':>9s}  (compile)")
    figures = {}

    def print_row(name):  # each row as soon as it is measured: a run cut short keeps what it has
        f = figures[name]
        compiled = f"{f['compiled']:6.2f} ms" if "compiled" in f else " " * 9
        took = f"  ({f['compile_s']:.0f} s)" if "compile_s" in f else ""
        print(f"{name:>22s}  {f['eager']:6.2f} ms  {compiled}{took}", flush=True)

    for name, (eager, make_compiled) in parts.items():
        figures[name] = {"eager": median_ms(eager, args.reps, device)}
        if args.compile and make_compiled is not None:  # (a buffer's sample is not compiled)
            # each part compiled afresh: the frames a part shares with another (the loss's forward)
            # would otherwise keep both parts' cache entries and check both sets of guards per call
            torch._dynamo.reset()
            compiled = make_compiled()
            start = time.perf_counter()
            compiled()
            figures[name]["compile_s"] = time.perf_counter() - start
            figures[name]["compiled"] = median_ms(compiled, args.reps, device)
        print_row(name)
    if isinstance(loss, SILPLoss) and cfg.silp.filter == "reward":
        # the same term through separate transition and outcome calls (FK twice per look-ahead step)
        fused = loss.model
        loss.model = _UnfusedModel(fused)
        try:
            figures["bc loss, unfused model"] = {"eager": median_ms(on_the_batch(loss.bc_loss, batch), args.reps, device)}
        finally:
            loss.model = fused
        print_row("bc loss, unfused model")
    flops, torch_rate = update_flops(cfg, loss, batch), gemm_rate(device)
    floor_ms = 1e3 * flops / torch_rate
    print(f"{'matmul floor of update':>22s}  {floor_ms:6.2f} ms  (its matrix products at this "
          f"{'device' if device.type == 'cuda' else 'core'}'s 256^3 rate)")
    if args.profile:
        update = compiled_update[-1] if compiled_update else on_the_batch(gradient_step, batch)
        figures["profile"] = profile_update(update, args.profile)
        print(f"where the {'compiled' if compiled_update else 'eager'} update's time goes "
              f"(torch.profiler, {args.profile} updates, self time per update):")
        for part, ms in figures["profile"].items():
            print(f"{part:>22s}  {ms:6.2f} ms")
    if peer_cfg is not None:
        _, _, peer_batch, peer_step = _build(peer_cfg, device)
        peer = on_the_batch(compile_update(peer_cfg, peer_step), peer_batch)
        ours = compiled_update[-1]
        rounds = max(1, args.reps // 10)
        figures["against"] = interleaved_median_ms({"this config": ours, "against": peer}, rounds, 10, device)
        print(f"the compiled update beside the one with {' '.join(args.against)} "
              f"(taking turns, {rounds} rounds of 10 updates each):")
        this, other = figures["against"]["this config"], figures["against"]["against"]
        print(f"{'this config':>22s}  {this:6.2f} ms")
        print(f"{'with ' + ' '.join(args.against):>22s}  {other:6.2f} ms  ({other / this:.2f}x)")
    return figures


def _config(overrides: list[str]):
    return load_config("sac_silp", overrides)


def _build(cfg, device: torch.device):
    """The recipe's loss, buffers (filled from one rollout and its demonstrations), a sampled batch and update."""
    model = make_model(cfg, device)
    env = make_env(cfg, model, device, seed=0)
    actor, critic = make_actor_critic(cfg, model, env, device)
    loss, updater = make_loss(cfg, actor, critic, model, env)
    optimizers = make_optimizers(cfg, loss)
    buffers = make_buffers(cfg, model, device)
    with torch.no_grad():
        episodes = env.rollout(cfg.env.max_steps, break_when_any_done=False)
    buffers.extend(episodes)
    if cfg.silp.demos:
        buffers.demo_buffer.extend(episodes)
    return loss, buffers, buffers.sample(), make_gradient_step(loss, optimizers, updater)


def on_the_batch(fn, batch):
    """``fn`` called on a shallow copy of ``batch`` (its tensors shared), as the recipe calls it on each fresh sample.

    The losses write their outputs (``td_error``, the actor's ``loc`` and ``scale``) into the batch they
    read. Called on the batch itself, a compiled loss would see those extra keys from its second call
    on, compile a second graph for them and check both graphs' guards on every call after: a cost the
    recipe's fresh samples never pay.
    """
    return lambda: fn(batch.copy())


# what each profiled event's self time is spent on; the first matching rule wins, the rest is "other ATen"
TIME_PARTS = (
    ("matrix products", lambda name: name in {"aten::mm", "aten::bmm", "aten::addmm", "aten::baddbmm",
                                              "aten::addbmm", "aten::addmv", "aten::mv", "aten::dot"}),
    ("inductor kernels", lambda name: name.startswith("## Call CompiledFxGraph")),
    ("optimiser steps", lambda name: name.startswith(("Optimizer.", "aten::_fused_adam"))),
    ("dynamo guards", lambda name: name == "TorchDynamo Cache Lookup"),
    ("other ATen", lambda name: name.startswith("aten::")),
)


def split_time(self_us: dict[str, float], wall_us: float, calls: int) -> dict[str, float]:
    """Milliseconds per call of each of :data:`TIME_PARTS`, from the events' self times (µs, summed over
    ``calls`` calls), plus ``unaccounted``: the wall time no ATen operator, kernel, optimiser or guard holds
    (the Python code between them, autograd's engine, the profiler's own records)."""
    parts = {part: 0.0 for part, _ in TIME_PARTS}
    for name, us in self_us.items():
        for part, matches in TIME_PARTS:
            if matches(name):
                parts[part] += us
                break
    parts["unaccounted"] = wall_us - sum(parts.values())
    parts["total (wall)"] = wall_us
    return {part: us / 1e3 / calls for part, us in parts.items()}


def profile_update(update, calls: int) -> dict[str, float]:
    """:func:`split_time` of ``calls`` calls of a CPU ``update`` under ``torch.profiler`` (after one warm-up call)."""
    from torch.profiler import ProfilerActivity, profile

    update()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        for _ in range(calls):
            update()
        wall_us = 1e6 * (time.perf_counter() - start)
    self_us = {}
    for event in prof.key_averages():
        self_us[event.key] = self_us.get(event.key, 0.0) + event.self_cpu_time_total
    return split_time(self_us, wall_us, calls)


def gemm_rate(device: torch.device = torch.device("cpu")) -> float:
    """FLOP/s of one 256 x 256 x 256 float32 product on ``device`` (median of 200)."""
    a, b = torch.randn(256, 256, device=device), torch.randn(256, 256, device=device)
    return 2 * 256**3 / (median_ms(lambda: a @ b, 200, device) / 1e3)


def update_flops(cfg, loss, batch) -> float:
    """The FLOPs of the update's matrix products, counted by torch's FLOP counter on one update."""
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils.flop_counter import flop_registry

    class Count(TorchDispatchMode):  # torch's FlopCounterMode tracks modules, which TensorDict modules upset
        total = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            rule = flop_registry.get(func._overloadpacket)
            if rule is not None:
                Count.total += rule(*args, **(kwargs or {}), out_val=out)
            return out

    with Count():
        out = loss(batch)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    for p in loss.parameters():
        p.grad = None
    return Count.total


if __name__ == "__main__":
    main()
