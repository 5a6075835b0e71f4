"""Results files -> records: training runs, transfer results, collision models, benchmark outputs.

A study folder holds ``<method>/seed<k>/`` run directories, each with the files a recipe and
``recipes/sweep.py`` write: ``summary.json`` (the final figures), ``history.json`` (the
periodic evaluations), ``config.yaml`` (the resolved config) and ``sweep.json`` (the sweep's
command and machine). ``results/benchmarks/<name>.txt`` is a benchmark's output, its first line
the command prefixed ``$``.

Examples:
    >>> flatten({"a": {"b": 1, "c": {"d": 2}}, "e": 3})
    {'a.b': 1, 'a.c.d': 2, 'e': 3}
    >>> get({"a": {"b": 1}}, "a.b"), get({"a": {"b": 1}}, "a.x")
    (1, None)
    >>> slug("SingleTaskRollout, all guards")
    'singletaskrollout_all_guards'
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path


@dataclasses.dataclass
class Run:
    """One training (or BC, or planner) run: its directory's files, read."""

    method: str
    seed: int
    dir: Path
    summary: dict
    history: list[dict]
    config: dict | None
    sweep: dict | None

    def value(self, key: str) -> float | None:
        """A number of ``summary.json`` (None when missing, not a number, or NaN); ``"<name>@episodes=<n>"``:
        ``<name>`` at the run's first periodic evaluation after ``n`` training episodes (``history.json``).

            >>> run = Run("m", 0, Path("."), {"success_rate": 0.9}, [{"episodes": 500, "success_rate": 0.2},
            ...           {"episodes": 1040, "success_rate": 0.6}], None, None)
            >>> run.value("success_rate"), run.value("success_rate@episodes=1000"), run.value("success_rate@episodes=2000")
            (0.9, 0.6, None)
        """
        if "@episodes=" in key:
            name, episodes = key.split("@episodes=")
            after = [h for h in self.history if h.get("episodes", -1) >= int(episodes) and name in h]
            value = min(after, key=lambda h: h["episodes"])[name] if after else None
        else:
            value = self.summary.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
            return None
        return float(value)


def flatten(tree: dict, prefix: str = "") -> dict:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def get(tree: dict | None, dotted: str):
    """The value at ``dotted`` (``"optim.utd_ratio"``) of a nested dict, None where a key is missing."""
    for key in dotted.split("."):
        if not isinstance(tree, dict) or key not in tree:
            return None
        tree = tree[key]
    return tree


def read_yaml(path: Path) -> dict | None:
    if not path.exists():
        return None
    import yaml

    return yaml.safe_load(path.read_text())


def _seed_of(path: Path) -> int:
    match = re.fullmatch(r"seed(\d+)", path.name)
    return int(match.group(1)) if match else -1


def load_runs(folder: Path) -> dict[str, list[Run]]:
    """``{method: [run, ...]}`` of every ``<folder>/<method>/seed*/summary.json``, methods by name, runs by seed.

    Raises:
        FileNotFoundError: no run has a summary.
    """
    runs: dict[str, list[Run]] = {}
    paths = sorted(Path(folder).glob("*/seed*/summary.json"), key=lambda p: (p.parents[1].name, _seed_of(p.parent)))
    for summary_path in paths:
        run_dir = summary_path.parent
        history = run_dir / "history.json"
        sweep = run_dir / "sweep.json"
        runs.setdefault(run_dir.parent.name, []).append(Run(
            method=run_dir.parent.name,
            seed=_seed_of(run_dir),
            dir=run_dir,
            summary=json.loads(summary_path.read_text()),
            history=json.loads(history.read_text()).get("history", []) if history.exists() else [],
            config=read_yaml(run_dir / "config.yaml"),
            sweep=json.loads(sweep.read_text()) if sweep.exists() else None,
        ))
    if not runs:
        raise FileNotFoundError(f"no <method>/seed*/summary.json under {folder}: run recipes/sweep.py "
                                f"with results_dir={folder} first")
    return runs


def load_transfer(folder: Path) -> dict[str, list[dict]]:
    """``{method: [result, ...]}`` of every ``*.json`` under ``folder`` (what ``recipes/transfer.py`` writes),
    each result with its path relative to ``folder`` as ``"file"``; methods by name, results by seed and file."""
    out: dict[str, list[dict]] = {}
    for path in sorted(Path(folder).rglob("*.json")):
        result = json.loads(path.read_text())
        result["file"] = path.relative_to(folder).as_posix()
        out.setdefault(result["method"], []).append(result)
    if not out:
        raise FileNotFoundError(f"no transfer results (*.json) under {folder}: run recipes/transfer.py first")
    return {m: sorted(rs, key=lambda r: (r["seed"], r["file"])) for m, rs in sorted(out.items())}


def load_collision_nets(folder: Path) -> list[dict]:
    """The collision models' test metrics (``<folder>/*.json``, what ``recipes/collision_net.py`` writes)."""
    found = [json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))]
    if not found:
        raise FileNotFoundError(f"no collision-model results (*.json) under {folder}: run recipes/collision_net.py")
    return found


# ------------------------------------------------------------------------------------------ benchmarks
@dataclasses.dataclass
class Benchmark:
    """A benchmark's output file: its command, the machine it names, and the figures of each run in it."""

    file: Path
    command: str
    machine: str
    runs: list[dict]


def slug(label: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", label.lower()).strip("_")


def number(text: str) -> float | str | None:
    text = text.strip()
    if text in ("None", "null"):
        return None
    try:
        return float(text.replace(",", "").rstrip("x"))
    except ValueError:
        return text


_VALUE = r"([\d.,]+) (ms|us|s)\b"


def _parse_timings(lines: list[str]) -> dict:
    """``label   1.23 ms   4.56 ms  (7 s)`` lines (update_step.py): ``label_ms`` for one value,
    ``label_eager_ms`` / ``label_compiled_ms`` (and ``label_compile_s``) for two; ``... (1.09x)`` as ``label_ratio``."""
    out = {}
    for line in lines:
        match = re.match(rf"^\s*([A-Za-z][^:]*?)\s{{2,}}{_VALUE}(?:\s+{_VALUE})?(?:\s+\((\d+) s\))?(?:\s+\(([\d.]+)x\))?", line)
        if not match:
            continue
        key = slug(match.group(1))
        if match.group(4):
            out[f"{key}_eager_{match.group(3)}"] = number(match.group(2))
            out[f"{key}_compiled_{match.group(5)}"] = number(match.group(4))
        else:
            out[f"{key}_{match.group(3)}"] = number(match.group(2))
        if match.group(6):
            out[f"{key}_compile_s"] = number(match.group(6))
        if match.group(7):
            out[f"{key}_ratio"] = number(match.group(7))
    return out


def _parse_summary(lines: list[str]) -> dict:
    """``key: value`` lines (time_to_success.py prints the run's summary so)."""
    out = {}
    for line in lines:
        match = re.match(r"^\s*([a-z_0-9]+): (.*)$", line)
        if match:
            out[match.group(1)] = number(match.group(2))
    return out


def _parse_rollouts(lines: list[str]) -> dict:
    """``label: 1.8 ms, success 97/100 (...; 102 us per step)`` lines (rollout_time.py)."""
    out = {}
    for line in lines:
        match = re.match(r"^\s*(.+?):\s+([\d.,]+) ms", line)
        if not match:
            continue
        key = slug(match.group(1))
        out[f"{key}_ms"] = number(match.group(2))
        step = re.search(r"([\d.,]+) us per step", line)
        if step:
            out[f"{key}_us_per_step"] = number(step.group(1))
        success = re.search(r"success (\d+)/(\d+)", line) or re.search(r"success ([\d.]+)$", line)
        if success:
            out[f"{key}_success"] = (int(success.group(1)) / int(success.group(2)) if success.lastindex == 2
                                     else number(success.group(1)))
    return out


def _parse_throughput(lines: list[str]) -> dict:
    """env_throughput.py: MuJoCo's configs/s, and ``<variant>_<batch>_configs_s`` / ``_vs_mujoco`` per table row."""
    out = {}
    for line in lines:
        mujoco = re.match(r"^MuJoCo .*: ([\d,]+) configs/s", line)
        if mujoco:
            out["mujoco_configs_s"] = number(mujoco.group(1))
        row = re.match(r"^(eager|compiled)\s+(\d+)\s+[\d,]+\s+[\d,]+\s+[\d,]+\s+([\d,]+)\s+([\d.]+)x", line)
        if row:
            out[f"{row.group(1)}_{row.group(2)}_configs_s"] = number(row.group(3))
            out[f"{row.group(1)}_{row.group(2)}_vs_mujoco"] = number(row.group(4))
    return out


def _parse_tables(lines: list[str]) -> dict:
    """Markdown tables (planner.py): each column of a table's first row as ``<column>``, the first table holding it."""
    out, header = {}, None
    for line in lines:
        if not line.startswith("|"):
            header = None
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            header, first = [slug(c) for c in cells], True
        elif set(line) <= set("|:- "):
            continue
        elif first:
            for column, cell in zip(header, cells):
                out.setdefault(column, number(cell))
            first = False
    return out


def markdown_tables(path: Path) -> dict[str, tuple[list[str], list[list[str]]]]:
    """A benchmark output's markdown tables by their ``### `` title: ``(header, rows of cells)``."""
    tables, title = {}, None
    for line in Path(path).read_text().splitlines():
        if line.startswith("### "):
            title = line[4:].strip()
        elif line.startswith("|") and title is not None:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if title not in tables:
                tables[title] = (cells, [])
            elif not set(line) <= set("|:- "):
                tables[title][1].append(cells)
        elif title in tables:  # the table under this title has ended
            title = None
    return tables


PARSERS = {"update_step.py": _parse_timings, "time_to_success.py": _parse_summary, "rollout_time.py": _parse_rollouts,
           "env_throughput.py": _parse_throughput, "planner.py": _parse_tables}


def load_benchmark(path: Path) -> Benchmark:
    """A benchmark output file: each ``$ command`` in it starts a run, parsed by its script's parser.

    The machine is the first line after the command that starts with ``torch `` or ``machine:``, up to
    a ``;``.
    """
    text = Path(path).read_text()
    chunks = [c for c in re.split(r"^(?=\$ )", text, flags=re.M) if c.strip()]
    if not chunks or not chunks[0].startswith("$ "):
        raise ValueError(f"{path}: a benchmark output starts with its command ('$ ...')")
    runs, command, machine = [], None, None
    for chunk in chunks:
        lines = chunk.splitlines()
        command = command or lines[0][2:].split("   #")[0].strip()
        script = next((s for s in PARSERS if s in lines[0]), None)
        if script is None:
            raise ValueError(f"{path}: no parser for the command {lines[0]!r} (known: {', '.join(PARSERS)})")
        runs.append(PARSERS[script](lines[1:]))
        if machine is None:
            line = next((l for l in lines[1:] if l.startswith(("torch ", "machine:"))), "")
            machine = line.removeprefix("machine:").split(";")[0].strip()
    return Benchmark(file=Path(path), command=command, machine=machine or "not recorded", runs=runs)
