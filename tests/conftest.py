"""Fixtures shared by the test files: the task model, a seconds-long recipe config, the benchmark scripts."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import settings

from torchrl_silp.models import UR5eReach
from torchrl_silp.recipes.schema import load_config

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

# Property tests check values, not speed: no per-example deadline, which a loaded machine (the suite runs
# on every core, see pytest_configure) would turn into spurious failures.
settings.register_profile("project", deadline=None)
settings.load_profile("project")


def pytest_configure(config):
    """Under pytest-xdist (``-n``, on by default in pyproject's ``addopts``) each worker gets its share of the
    cores, as torch threads and as ``OMP_NUM_THREADS`` for the recipe processes the tests start: torch's
    default of one thread per core in every worker makes them spin against each other, several times slower
    than the cores' share."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        threads = max(1, cores // workers)
        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)

# a recipe run of seconds: 4 envs, 100 transitions per collector batch, 8 evaluation tasks, an eager
# update, no progress bar, no logger
TINY_RECIPE = ("env.num_envs=4", "collector.frames_per_batch=100", "eval.n_tasks=8", "progress=false",
               "logger.backend=", "compile.compile=false")


@pytest.fixture(scope="module")
def model():
    """The UR5e reach task model with its defaults (stateless, so a module's tests share one)."""
    return UR5eReach()


@pytest.fixture(scope="module")
def model64():
    """The UR5e reach task model in float64: for the exact geometric comparisons (brute force, finite differences,
    gradcheck), which float32's rounding would blur."""
    return UR5eReach(dtype=torch.float64)


@pytest.fixture(scope="module")
def one_thread():
    """torch on one thread while a module's tests run (``pytestmark = pytest.mark.usefixtures("one_thread")``):
    small tensors and single-state checks, where OpenMP threads on a shared machine only contend."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def tiny_config(tmp_path):
    """``tiny_config(*overrides, name="sac_silp")``: a recipe's config (``recipes/config/<name>.yaml``) cut to a
    seconds-long run (:data:`TINY_RECIPE`) writing to ``tmp_path / "run"``, then ``overrides``."""

    def compose(*overrides: str, name: str = "sac_silp"):
        return load_config(name, [*TINY_RECIPE, f"run_dir={tmp_path / 'run'}", *overrides])

    return compose


def _load_script(name: str):
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


@pytest.fixture(scope="session")
def load_benchmark():
    """``load_benchmark(name)``: the script ``benchmarks/<name>.py`` as a module.

    The benchmarks are scripts, not a package: run as ``python benchmarks/<name>.py`` they import
    their helper ``benchmarks/timing.py`` as ``timing``, which is loaded first under that name here.
    """

    def load(name: str):
        _load_script("timing")
        return _load_script(name)

    return load
