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
