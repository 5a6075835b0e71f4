"""The benchmarks' clock: the median wall time of a call, waiting for a GPU's queued kernels."""

from __future__ import annotations

import statistics
import time

import torch


def median_ms(fn, reps: int, device: torch.device | str = "cpu") -> float:
    """Median milliseconds of ``reps`` calls of ``fn`` after one warm-up call.

    A CUDA call returns once its kernels are queued, so on CUDA the clock is read
    after ``torch.cuda.synchronize``.
    """
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    fn()
    times = []
    for _ in range(reps):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def interleaved_median_ms(fns: dict, rounds: int, per_round: int, device: torch.device | str = "cpu") -> dict:
    """Median milliseconds per call of each of ``fns`` (name -> call), timed taking turns.

    Each round calls every function ``per_round`` times, one function after the other, after one
    warm-up call each, so a machine whose speed drifts during the run slows all of them alike.
    """
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    times = {name: [] for name in fns}
    for fn in fns.values():
        fn()
    for _ in range(rounds):
        for name, fn in fns.items():
            for _ in range(per_round):
                sync()
                start = time.perf_counter()
                fn()
                sync()
                times[name].append(time.perf_counter() - start)
    return {name: 1e3 * statistics.median(ts) for name, ts in times.items()}
