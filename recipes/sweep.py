"""The sweep of the paper's tables: every method x every seed as a Ray task, one run directory each.

    python recipes/sweep.py                                  # every row of every table, seeds 0-2, a local Ray
    python recipes/sweep.py methods=[sac,sac_silp_plus] seeds=[0] \\
        "overrides.sac_silp=['collector.total_episodes=2000','eval.every_frames=4000']"
    python recipes/sweep.py --config-name sweep_ablations    # another grid: its own methods and seeds
    python recipes/sweep.py ray.address=auto resources.num_gpus=1   # a running cluster, a GPU per run
    python recipes/sweep.py dry_run=true                     # print the grid and what is finished

The methods, the recipe each one runs and its config overrides are the registry
of ``recipes/config/sweep.yaml``. Each run composes its recipe's config with
hydra's compose API (``overrides.all``, ``overrides.<recipe>``, then its
registry overrides, so that a method's own setting wins over the grid's, then
``seed=<k> run_dir=<results_dir>/<method>/seed<k> resume=true``, plus
``device=cuda`` when it reserves a GPU), calls the recipe's
function with it and writes its stdout/stderr to ``<run_dir>/run.log`` and what
ran where to ``<run_dir>/sweep.json``.

A run whose ``summary.json`` exists is finished: started again, the sweep skips
it. A run killed midway resumes from its checkpoint. A method with ``after: X``
(``bc_sac_silp_plus`` clones the policy of ``sac_silp_plus``) waits for the run
of X of the same seed: its Ray task takes X's task's result as an argument, so
Ray starts it only once X has finished, and it fails without running if X
failed. A failed run is reported (method, seed, error) and the others go on;
the exit status is 1 if any failed. Each task runs in a fresh worker process
(``fresh_worker=true``, Ray's ``max_calls=1``), so no torch or recipe state
(thread count, TorchRL's timers, cached allocations, the recipe code as it was
imported) carries over from one run into the next.

Without ``ray.address`` the sweep starts a local Ray and stops it when it
ends, with whatever other drivers had queued on it. Several sweeps sharing
one machine's CPUs: ``ray start --head --num-cpus N`` first, then every sweep
with ``ray.address=auto``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import importlib
import importlib.util
import json
import os
import platform
import re
import shlex
import sys
import time
import traceback
from pathlib import Path

import hydra
from hydra import compose
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_silp.recipes.schema import CONFIG_DIR, config_context, free_model_keys

RECIPES = Path(__file__).resolve().parent
_has_ray = importlib.util.find_spec("ray") is not None
_RAY_HINT = 'recipes/sweep.py runs its grid on Ray, which is not installed: pip install "torchrl_silp[sweep]"'
# results_dir is spliced into hydra overrides: a plain path (no spaces, quotes, commas or "=")
_PLAIN_PATH = re.compile(r"^[\w./\-+~@%]+$")
_PLACEHOLDERS = ("{results_dir}", "{seed}")


@dataclasses.dataclass(frozen=True)
class Run:
    """One cell of the grid: a method's run with one seed."""

    method: str
    seed: int
    recipe: str
    config: str      # the hydra config name in recipes/config
    function: str    # "<module>.<function>" of recipes/<module>.py (torchrl_silp.recipes.<module>)
    overrides: tuple[str, ...]
    run_dir: Path
    after: str | None = None
    context: tuple[tuple[str, object], ...] = ()  # what the sweep records in sweep.json
    check: str | None = None  # "<module>.<function>" that checks the composed config (raises ConfigError)

    @property
    def name(self) -> str:
        return f"{self.method}/seed{self.seed}"

    @property
    def finished(self) -> bool:
        return (self.run_dir / "summary.json").exists()


# ------------------------------------------------------------------ config
def load_config(overrides: list[str] | tuple[str, ...] = (), config_name: str = "sweep") -> DictConfig:
    """A sweep's config (``recipes/config/<config_name>.yaml``) with hydra overrides, outside ``@hydra.main``.

    Examples:
        >>> cfg = load_config(["methods=[sac]", "seeds=[0]"])
        >>> [run.name for run in plan(cfg, check_configs=False)]
        ['sac/seed0']
    """
    with config_context():
        return compose(config_name, overrides=list(overrides))


def _plain(value):
    """A config value as plain Python (lists for ListConfigs)."""
    return OmegaConf.to_container(value) if isinstance(value, (ListConfig, DictConfig)) else value


def plan(cfg: DictConfig, check_configs: bool = True) -> list[Run]:
    """Validate the sweep's config and list its runs, each one after the method it waits for.

    Raises ``ValueError`` naming the parameter and the allowed values before
    anything runs. With ``check_configs`` every selected method's config is
    composed once, so a bad override fails here rather than in a Ray task.
    """
    registry, recipes = cfg.registry, cfg.recipes
    for name, entry in registry.items():
        if not _PLAIN_PATH.match(name) or "/" in name:
            raise ValueError(f"registry: method names are directory names, got {name!r}")
        if entry.get("recipe") not in recipes:
            raise ValueError(f"registry.{name}.recipe must be one of {tuple(recipes)}, got {entry.get('recipe')!r}")
        own = _plain(entry.get("overrides", []))
        if not isinstance(own, list) or not all(isinstance(o, str) for o in own):
            raise ValueError(f"registry.{name}.overrides must be a list of hydra overrides (strings), got {own!r}")
        after = entry.get("after", None)
        if after is not None and after not in registry:
            raise ValueError(f"registry.{name}.after must be null or one of {tuple(registry)}, got {after!r}")
    for name, entry in recipes.items():
        if not isinstance(entry.get("function"), str) or entry.function.count(".") != 1:
            raise ValueError(f"recipes.{name}.function must be '<module>.<function>', got {entry.get('function')!r}")

    methods = list(registry) if cfg.methods == "all" else _plain(cfg.methods)
    unknown = [m for m in methods if m not in registry] if isinstance(methods, list) else methods
    if not isinstance(methods, list) or unknown or not methods or len(set(methods)) != len(methods):
        raise ValueError(f"methods must be 'all' or a non-empty list of distinct names among {tuple(registry)}, "
                         f"got {_plain(cfg.methods)!r}" + (f" (unknown: {unknown})" if unknown else ""))
    seeds = _plain(cfg.seeds)
    if (not isinstance(seeds, list) or not seeds or len(set(seeds)) != len(seeds)
            or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seeds)):
        raise ValueError(f"seeds must be a non-empty list of distinct non-negative ints, got {seeds!r}")
    bad_keys = [k for k in cfg.overrides if k != "all" and k not in recipes]
    if bad_keys:
        raise ValueError(f"overrides keys must be 'all' or one of {tuple(recipes)}, got {bad_keys}")
    for key, value in cfg.overrides.items():
        value = _plain(value)
        if not isinstance(value, list) or not all(isinstance(o, str) for o in value):
            raise ValueError(f"overrides.{key} must be a list of hydra overrides (strings), got {value!r}")
    cpus, gpus = cfg.resources.num_cpus, cfg.resources.num_gpus
    if isinstance(cpus, bool) or not isinstance(cpus, (int, float)) or cpus <= 0:
        raise ValueError(f"resources.num_cpus must be a number > 0, got {cpus!r}")
    if isinstance(gpus, bool) or not isinstance(gpus, (int, float)) or gpus < 0:
        raise ValueError(f"resources.num_gpus must be a number >= 0, got {gpus!r}")
    if not isinstance(cfg.fresh_worker, bool):
        raise ValueError(f"fresh_worker must be true or false, got {cfg.fresh_worker!r}")
    if isinstance(cfg.max_retries, bool) or not isinstance(cfg.max_retries, int) or cfg.max_retries < 0:
        raise ValueError(f"max_retries must be an int >= 0, got {cfg.max_retries!r}")
    address = cfg.ray.address
    if address is not None and not (address == "auto" or str(address).startswith("ray://") or ":" in str(address)):
        raise ValueError(f"ray.address must be null, 'auto', 'host:port' or 'ray://host:port', got {address!r}")
    if not _PLAIN_PATH.match(str(cfg.results_dir)):
        raise ValueError(f"results_dir must be a plain path (letters, digits, ./-_+~@%), got {cfg.results_dir!r}")
    results_dir = Path(cfg.results_dir).expanduser().resolve()

    def make_run(method: str, seed: int) -> Run:
        entry = registry[method]
        recipe = recipes[entry.recipe]
        run_dir = results_dir / method / f"seed{seed}"
        own = [o.replace("{results_dir}", str(results_dir)).replace("{seed}", str(seed)) for o in entry.get("overrides", [])]
        overrides = [*cfg.overrides.get("all", []), *cfg.overrides.get(entry.recipe, []), *own,
                     f"seed={seed}", f"run_dir={run_dir}", "++resume=true"]
        if gpus > 0:
            overrides.append("++device=cuda")
        return Run(method, seed, entry.recipe, recipe.config, recipe.function, tuple(overrides), run_dir,
                   entry.get("after", None), check=recipe.get("check", None))

    # the methods a selected one waits for come first; one not selected must have finished already
    ordered: list[str] = []

    def visit(method: str, chain: tuple[str, ...]) -> None:
        if method in chain:
            raise ValueError(f"registry: `after` makes a cycle: {' -> '.join((*chain, method))}")
        after = registry[method].get("after", None)
        if after is not None and after in methods:
            visit(after, (*chain, method))
        if method not in ordered:
            ordered.append(method)

    for method in methods:
        visit(method, ())
    if cfg.get("order", "method") not in ("method", "seed"):
        raise ValueError(f"order must be 'method' or 'seed', got {cfg.get('order')!r}")
    if cfg.get("order", "method") == "seed":  # every method's seed 0 first: a stopped sweep has whole seeds
        runs = [make_run(m, s) for s in seeds for m in ordered]
    else:
        runs = [make_run(m, s) for m in ordered for s in seeds]
    for run in runs:
        if run.after is not None and run.after not in methods:
            upstream = results_dir / run.after / f"seed{run.seed}" / "summary.json"
            if not run.finished and not upstream.exists():
                raise ValueError(f"methods: {run.method} needs the finished run of {run.after} (seed {run.seed}), "
                                 f"and {upstream} does not exist: add {run.after} to methods")
    if check_configs:
        _check_configs(runs)
    return runs


def _check_configs(runs: list[Run]) -> None:
    """Compose every method's config once (its first seed), so that bad overrides fail before Ray starts."""
    checked = set()
    with config_context():
        for run in runs:
            if run.method in checked or run.finished:
                continue
            checked.add(run.method)
            module = run.function.split(".")[0]
            if not (RECIPES / f"{module}.py").exists():
                raise ValueError(f"method {run.method}: recipe {run.recipe} runs recipes/{module}.py, which does not exist")
            if not (CONFIG_DIR / f"{run.config}.yaml").exists():
                raise ValueError(f"method {run.method}: recipe {run.recipe}'s config recipes/config/{run.config}.yaml "
                                 "does not exist")
            try:
                compose(run.config, overrides=free_model_keys(run.overrides))
            except Exception as exc:  # hydra's override and config errors
                raise ValueError(f"method {run.method}: the overrides {list(run.overrides)} do not compose with "
                                 f"recipes/config/{run.config}.yaml: {exc}") from exc


# ------------------------------------------------------------ one run (a Ray task)
def _load_function(spec: str):
    """The function ``"<module>.<function>"`` names: ``<function>`` of ``torchrl_silp.recipes.<module>``."""
    module, name = spec.split(".")
    return getattr(importlib.import_module(f"torchrl_silp.recipes.{module}"), name)


def _machine() -> dict:
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    info = {"cpu": cpu, "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS")}
    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        info.update(torch=torch.__version__, torch_threads=torch.get_num_threads())
        if torch.cuda.is_available():
            info["gpus"] = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    return info


def _record(run: Run, attempt: dict) -> None:
    """Append this attempt to ``<run_dir>/sweep.json`` (a resumed run has several)."""
    path = run.run_dir / "sweep.json"
    record = json.loads(path.read_text()) if path.exists() else {"attempts": []}
    attempts = [a for a in record["attempts"] if a.get("started") != attempt["started"]] + [attempt]
    record.update(method=run.method, seed=run.seed, recipe=run.recipe, config=run.config, function=run.function,
                  overrides=list(run.overrides), after=run.after, **dict(run.context), machine=_machine(),
                  attempts=attempts)
    path.write_text(json.dumps(record, indent=2, default=str))


@contextlib.contextmanager
def _output_to(path: Path, restore_descriptors: bool = True):
    """Send this process's stdout and stderr to ``path`` (appending): Python's streams and file descriptors 1, 2.

    The descriptors too, so that what C code and child processes of the run
    write lands in the run's log rather than on the sweep's console. With
    ``restore_descriptors=False`` they stay on the log after the block: what
    the process writes until it exits goes there too.
    """
    with open(path, "a", buffering=1) as log:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
                yield
        finally:
            log.flush()
            if restore_descriptors:
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


def _result(run: Run, status: str, **extra) -> dict:
    return {"method": run.method, "seed": run.seed, "run_dir": str(run.run_dir), "status": status,
            "error": None, **extra}


def run_one(run: Run, after_result: dict | None = None, last_in_process: bool = False) -> dict:
    """Compose the run's config, call its recipe, return ``{"status": "ok" | "failed", ...}``; never raises.

    ``after_result`` is the result of the run it waits for (``Run.after``): a
    failed one fails this one without running it. ``last_in_process``: the
    process exits after this run (a fresh Ray worker per run), so its output
    stays on the run's log to the end.
    """
    if after_result is not None and after_result["status"] != "ok":
        return _result(run, "failed", error=f"needs {run.after}/seed{run.seed}, which failed")
    run.run_dir.mkdir(parents=True, exist_ok=True)
    started = datetime.datetime.now().isoformat(timespec="seconds")
    tick = time.perf_counter()
    attempt = {"started": started, "status": "running"}
    # what a worker that exits after this task writes while exiting is the run's too (Ray ends the
    # run's child processes, e.g. multiprocessing's resource tracker, which then complains)
    with _output_to(run.run_dir / "run.log", restore_descriptors=not last_in_process):
        print(f"==== sweep: {run.name} started {started}; overrides: {' '.join(run.overrides)}")
        try:
            with config_context():
                cfg = compose(run.config, overrides=free_model_keys(run.overrides))
            if run.check is not None:  # what the script's command line checks first, before any file of the run
                _load_function(run.check)(cfg)
            _record(run, attempt)
            function = _load_function(run.function)
            summary = function(cfg)
            if not (run.run_dir / "summary.json").exists():
                raise RuntimeError(f"{run.function} returned without writing {run.run_dir / 'summary.json'}")
        except Exception as exc:
            traceback.print_exc()
            error = f"{type(exc).__name__}: {exc}"
            attempt.update(status="failed", error=error, wall_s=time.perf_counter() - tick)
            with contextlib.suppress(Exception):
                _record(run, attempt)
            return _result(run, "failed", error=error, wall_s=attempt["wall_s"])
        attempt.update(status="ok", finished=datetime.datetime.now().isoformat(timespec="seconds"),
                       wall_s=time.perf_counter() - tick)
        _record(run, attempt)
        print(f"==== sweep: {run.name} finished in {attempt['wall_s']:.0f} s")
    summary = summary if isinstance(summary, dict) else json.loads((run.run_dir / "summary.json").read_text())
    return _result(run, "ok", wall_s=attempt["wall_s"], success_rate=summary.get("success_rate"))


# ------------------------------------------------------------------ the sweep
def _describe(result: dict) -> str:
    where = Path(result["run_dir"]) / "run.log"
    if result["status"] == "ok":
        success = result.get("success_rate")
        success = f"success {success:.3f}" if isinstance(success, (int, float)) else "done"
        return f"ok      {result['method']} seed {result['seed']}: {success} in {result['wall_s']:.0f} s ({where})"
    return f"FAILED  {result['method']} seed {result['seed']}: {result['error']}" + (f" (log: {where})" if where.exists() else "")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _grouped(runs: list[Run]) -> str:
    """``sac (seeds 0, 1), sac_demon (seed 2)``."""
    seeds: dict[str, list[int]] = {}
    for run in runs:
        seeds.setdefault(run.method, []).append(run.seed)
    return ", ".join(f"{m} (seed{'s' if len(s) > 1 else ''} {', '.join(map(str, s))})" for m, s in seeds.items())


def _short(exc: BaseException) -> str:
    lines = [line for line in str(exc).strip().splitlines() if line.strip()]
    return f"{type(exc).__name__}: {lines[-1][:300] if lines else ''}"


def run_sweep(cfg: DictConfig, command: str | None = None) -> list[dict]:
    """Run the grid; returns one result per run (``status`` ok / failed / skipped) in the grid's order.

    Uses the Ray session already started in this process if there is one
    (and leaves it running), else starts one from ``cfg.ray`` and shuts it
    down at the end.
    """
    import tqdm

    runs = plan(cfg)
    skipped = [run for run in runs if run.finished]
    todo = [run for run in runs if not run.finished]
    results_dir = Path(cfg.results_dir).expanduser().resolve()
    n_methods = len({r.method for r in runs})
    print(f"sweep: {_count(n_methods, 'method')} x {_count(len(cfg.seeds), 'seed')} = {_count(len(runs), 'run')} "
          f"into {results_dir}")
    if skipped:
        print(f"skipped {len(skipped)} finished run(s) (summary.json exists): {_grouped(skipped)}")
    resumed = [run for run in todo if (run.run_dir / "checkpoint").exists()]
    if resumed:
        print(f"resuming {len(resumed)} run(s) from their checkpoint: {_grouped(resumed)}")
    new = [run for run in todo if run not in resumed]
    if new:
        print(f"starting {len(new)} new run(s): {_grouped(new)}")
    results = {run: _result(run, "skipped") for run in skipped}
    if cfg.dry_run or not todo:
        print("dry run: nothing started" if cfg.dry_run else "nothing to run: every run is finished")
        return [results[run] for run in runs if run in results]

    if not _has_ray:
        raise ImportError(_RAY_HINT)
    import ray

    started_ray = not ray.is_initialized()
    if started_ray:
        if cfg.ray.address is None:
            # "local": a Ray of its own even when another one (`ray start`) runs on this machine
            ray.init(address="local", num_cpus=cfg.ray.num_cpus, num_gpus=cfg.ray.num_gpus,
                     include_dashboard=cfg.ray.include_dashboard)
        else:
            ray.init(address=cfg.ray.address)
    try:
        available = ray.cluster_resources()
        need = {"CPU": cfg.resources.num_cpus, "GPU": cfg.resources.num_gpus}
        short = {k: v for k, v in need.items() if v > available.get(k, 0)}
        if short:
            message = (f"resources {need} per run, but the Ray cluster has "
                       f"{ {k: available.get(k, 0) for k in need} }: no run could be scheduled")
            if cfg.ray.address is None:
                raise ValueError(message)
            print(f"warning: {message} (unless the cluster scales up)")
        context = (("sweep_command", command), ("results_dir", str(results_dir)),
                   ("resources_per_run", {"num_cpus": cfg.resources.num_cpus, "num_gpus": cfg.resources.num_gpus}),
                   ("ray_cluster", {k: available.get(k, 0) for k in ("CPU", "GPU")}))
        task = ray.remote(max_calls=1 if cfg.fresh_worker else 0)(run_one).options(
            num_cpus=cfg.resources.num_cpus, num_gpus=cfg.resources.num_gpus, max_retries=cfg.max_retries)
        refs = {}
        for run in todo:
            upstream = next((r for r in todo if r.method == run.after and r.seed == run.seed), None)
            after_ref = refs[upstream] if upstream is not None else None
            refs[run] = task.remote(dataclasses.replace(run, context=context), after_ref, bool(cfg.fresh_worker))
        pending = {ref: run for run, ref in refs.items()}
        with tqdm.tqdm(total=len(pending), desc="runs", unit="run") as bar:
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                run = pending.pop(ref)
                try:
                    results[run] = ray.get(ref)
                except Exception as exc:  # the worker died, or the run it waited for did
                    results[run] = _result(run, "failed", error=_short(exc))
                bar.update()
                tqdm.tqdm.write(f"[{bar.n}/{bar.total}] {_describe(results[run])}", file=sys.stdout)
    finally:
        if started_ray:
            ray.shutdown()

    ordered = [results[run] for run in runs]
    counts = {s: sum(r["status"] == s for r in ordered) for s in ("ok", "failed", "skipped")}
    print(f"sweep done: {counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} skipped (finished before)")
    for result in ordered:
        if result["status"] == "failed":
            print(_describe(result))
    return ordered


@hydra.main(version_base="1.3", config_path="config", config_name="sweep")
def main(cfg: DictConfig) -> None:
    command = " ".join(["python", shlex.quote(os.path.relpath(sys.argv[0])), *map(shlex.quote, sys.argv[1:])])
    results = run_sweep(cfg, command=command)
    if any(r["status"] == "failed" for r in results):
        sys.exit(1)


if __name__ == "__main__":
    main()
