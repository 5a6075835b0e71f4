"""The benchmarks' own arithmetic (their figures are printed, never asserted on timings)."""

import time

import pytest
import torch


@pytest.fixture(scope="module")
def update_step(load_benchmark):
    return load_benchmark("update_step")


@pytest.fixture(scope="module")
def timing(load_benchmark):
    return load_benchmark("timing")


def test_split_time_puts_each_profiled_event_in_its_part_and_leaves_the_rest_unaccounted(update_step):
    self_us = {  # summed over 4 calls
        "aten::mm": 400.0, "aten::bmm": 800.0, "aten::addmm": 200.0,
        "## Call CompiledFxGraph fabc123 (path)": 600.0,
        "Optimizer.step#Adam.step": 40.0, "aten::_fused_adam_": 80.0,
        "TorchDynamo Cache Lookup": 120.0,
        "aten::copy_": 60.0, "aten::nonzero": 20.0,
        "Torch-Compiled Region: 0/0": 0.0,  # a region's self time outside its kernels: not an operator's
    }
    parts = update_step.split_time(self_us, wall_us=2800.0, calls=4)
    assert parts == pytest.approx({
        "matrix products": 1.4 / 4, "inductor kernels": 0.6 / 4, "optimiser steps": 0.12 / 4,
        "dynamo guards": 0.12 / 4, "other ATen": 0.08 / 4,
        "unaccounted": (2.8 - 1.4 - 0.6 - 0.12 - 0.12 - 0.08) / 4, "total (wall)": 2.8 / 4,
    })


def test_a_fused_adam_step_counts_as_the_optimiser_not_as_other_aten(update_step):
    parts = update_step.split_time({"aten::_fused_adam_": 100.0, "aten::lerp_": 50.0}, 1000.0, 1)
    assert parts["optimiser steps"] == pytest.approx(0.1) and parts["other ATen"] == pytest.approx(0.05)


def test_profile_on_a_device_other_than_the_cpu_is_refused_before_anything_is_built(monkeypatch, capsys, update_step):
    monkeypatch.setattr(update_step, "resolve_device", lambda cfg: torch.device("cuda"))

    def build(*args, **kwargs):
        raise AssertionError("built the model before refusing --profile")

    monkeypatch.setattr(update_step, "make_model", build)
    with pytest.raises(SystemExit):
        update_step.main(["--profile", "3"])
    assert "--profile splits the update's CPU time; device=cuda" in capsys.readouterr().err


def test_a_negative_profile_count_is_refused(capsys, update_step):
    with pytest.raises(SystemExit):
        update_step.main(["--profile", "-3"])
    assert "--profile must be a number of updates >= 0" in capsys.readouterr().err


def test_the_benchmark_refuses_a_cuda_graph_off_cuda_as_the_recipe_does(update_step):
    with pytest.raises(ValueError, match="compile.cudagraphs captures the update in a CUDA graph: it needs device=cuda"):
        update_step.main(["compile.cudagraphs=true", "silp.demo_rows=mask", "device=cpu"])


def test_the_update_is_timed_on_copies_of_the_batch_so_a_loss_writing_into_it_compiles_one_graph(update_step):
    from tensordict import TensorDict

    def loss(td):  # a loss that writes its output into the batch it reads, as TorchRL's do
        td["td_error"] = (td["observation"] ** 2).sum(-1)
        return td["td_error"].mean()

    batch = TensorDict({"observation": torch.randn(8, 3), "next": {"observation": torch.randn(8, 3)}}, [8])
    keys = set(batch.keys(True, True))
    for on_copies, graphs in ((True, 1), (False, 2)):
        torch._dynamo.reset()
        torch._dynamo.utils.counters.clear()
        compiled = torch.compile(loss, backend="eager")
        call = update_step.on_the_batch(compiled, batch) if on_copies else (lambda: compiled(batch))
        for _ in range(3):
            assert call() == pytest.approx((batch["observation"] ** 2).sum(-1).mean().item())
        assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs
        assert set(batch.keys(True, True)) == (keys if on_copies else keys | {"td_error"})
    torch._dynamo.reset()


def test_interleaved_timing_takes_turns_and_times_each_call_on_its_own(timing):
    calls = []
    fns = {"fast": lambda: calls.append("fast"), "slow": lambda: (calls.append("slow"), time.sleep(0.002))}
    medians = timing.interleaved_median_ms(fns, rounds=3, per_round=2)
    # one warm-up call each, then rounds of per_round calls of each, in turn
    assert calls == ["fast", "slow"] + ["fast", "fast", "slow", "slow"] * 3
    assert medians["slow"] >= 2.0 > medians["fast"]


def test_against_is_refused_without_compilation_and_a_bad_peer_override_before_anything_is_built(monkeypatch, capsys, update_step):
    with pytest.raises(SystemExit):
        update_step.main(["--no-compile", "--against", "compile.guards=all"])
    assert "--against times two compiled updates; --no-compile has none" in capsys.readouterr().err

    def build(*args, **kwargs):
        raise AssertionError("built the model before refusing the peer's config")

    monkeypatch.setattr(update_step, "make_model", build)
    with pytest.raises(ValueError, match="compile.guards must be one of"):
        update_step.main(["--against", "compile.guards=none"])
