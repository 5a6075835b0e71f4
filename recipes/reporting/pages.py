"""The results pages: each block of ``pages.yaml`` rendered from ``results/`` between its markers.

A page is a markdown file of prose and generated blocks; a block sits between
``<!-- NAME:begin -->`` and ``<!-- NAME:end -->`` and is rewritten whole, the prose around it kept.
``pages.yaml`` says which blocks each page holds and what each block is: its kind (``runs``,
``headline``, ``benchmarks``, ``transfer``, ``reaching``, ``pick_place``, ``collision_net``), its results folder and
its rows and columns. A new study is a new block there: no code.

    python recipes/report.py                  # every page's blocks and figures
    python recipes/report.py --block table2   # one block, in each page that holds it
    python recipes/report.py --check          # exit 1 when a page's block differs from what results/ gives
"""

from __future__ import annotations

import argparse
import functools
import json
import re
import shlex
import sys
from pathlib import Path

import numpy as np

from . import figures, load, tables
from .tables import Context, mean_std, paper, paper_cell, rate, relpath, table

DATA = Path(__file__).resolve().parent


@functools.cache
def spec() -> dict:
    import yaml

    return yaml.safe_load((DATA / "pages.yaml").read_text())


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def pages_of(name: str) -> list[Path]:
    """The pages holding block ``name``."""
    return [Path(p["path"]) for p in spec()["pages"].values() if name in p["blocks"]]


# --------------------------------------------------------------------------------------- block kinds
@functools.cache
def _runs_of(folder: str) -> dict:
    """A study folder's runs, read once per ``write``/``check``/``render`` call (each clears the cache)."""
    return load.load_runs(Path(folder))


def _runs_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    def runs(folder) -> dict:
        try:
            return _runs_of(str(folder))
        except FileNotFoundError:
            if block.get("staged"):  # the study's runs are still to come: each row reads "not run"
                return {}
            raise

    ctx = Context(block, tables.build_rows(block, runs))
    body, about = tables.runs_table(ctx)
    lines = [body, ""]
    if about:
        lines += ["Mean (std) over seeds (ddof=0). " + "; ".join(about) + ".", ""]
    if block.get("about"):
        lines += [block["about"].strip(), ""]
    for ref in block.get("references", []):  # a figure of the task itself, beside the runs
        value = load.get(json.loads(Path(ref["file"]).read_text()), ref["key"])  # a dotted key reads nested entries
        lines += [f"{ref['text']}: {value:.3f} (`{ref['file']}`, made by `{ref['command']}`).", ""]
    if block.get("planning"):
        lines += tables.planning_table(block["planning"])
    sections = [("Differences in mean test success:", tables.differences(ctx)),
                (f"Rows with fewer than {block.get('seed_notes')} seeds:", tables.seed_notes(ctx)),
                (f"Rows whose test success is more than {block['gaps']['threshold']} from the paper's figure (the "
                 "*vs paper* column), and the cause:" if block.get("gaps") else "",
                 tables.paper_gaps(ctx)),
                (block.get("checks_heading", "The paper's orderings, on our means:"), tables.checks(ctx))]
    for heading, items in sections:
        if items:
            lines += [heading, "", *items, ""]
    frames = tables.by_frames(ctx)
    if frames:
        lines += ["Periodic-evaluation success against frames (each run's last evaluation at or below the column's "
                  "frames):", "", frames, ""]
    figure = block.get("figure")
    if figure:
        ids = figure.get("rows", [r.id for r in ctx.rows])
        groups = {f"`{i}`": ctx.by_id[i].runs for i in ids}
        key = figure.get("key", "success_rate")
        drawn = list(figures.curves_of(groups, key))
        target = draw if draw is not None else page.parent / figure["file"]
        if drawn:
            if draw is not None or _drawing:
                figures.plot_curves(groups, target, key, figure.get("ylabel", "success rate (periodic evaluations)"))
            lines += [f"![{figure['caption']}]({relpath(target, page)})", "",
                      f"{figure['caption']}: mean ± std over seeds of {', '.join(drawn)}.", ""]
    return lines + tables.provenance(ctx, name)


def _headline_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    rows = []
    for item in block["rows"]:
        runs = _runs_of(item["results"]).get(item["method"], [])
        figures_ = paper()[item["paper"][0]][item["paper"][1]]
        machine = "; ".join(dict.fromkeys(tables._machine(r) for r in runs))
        rows.append([tables.method_label(item["method"], runs), item["measure"],
                     mean_std([r.value("success_rate") for r in runs]), paper_cell(figures_["success"]),
                     str(len(runs)), machine])
    time = block["time"]
    files = [Path(block["results"]) / f for f in time["files"]]
    parsed = [load.load_benchmark(f) for f in files]
    machine = "; ".join(dict.fromkeys(re.sub(r" \(not alone[^)]*\)", "", b.machine) for b in parsed))
    ours = time["ours"].format(**tables.benchmark_figures(files))
    rows.append([time["method"], time["measure"], ours, "—", str(len(files)), machine])
    folders = sorted({i["results"] for i in block["rows"]})
    return [table(["Method", "Measure", "Ours", "The paper", "Seeds", "Machine"], rows, ["l", "l", "r", "r", "r", "l"]),
            "", f"Test success: the 1000 test tasks, mean (std) over seeds. From {', '.join(f'`{f}/`' for f in folders)} "
            f"and `{block['results']}/` ({', '.join(f'`{f}`' for f in time['files'])}); regenerate with "
            f"`python recipes/report.py --block {name}`.", ""]


def _benchmarks_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    return [tables.speed_table(block, Path(block["results"]), page), "",
            f"Each file under `{block['results']}/` is one benchmark's latest output, its first line the command; "
            f"*Peer* is what the file (or the one named) measured beside ours. Regenerate with "
            f"`python recipes/report.py --block {name}`.", ""]


def _transfer_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    folder = Path(block["results"])
    results = load.load_transfer(folder)
    scenarios, noises = block["scenarios"], block["noises"]
    rows, n_tasks, control = [], set(), set()
    for method in block["methods"]:
        for scenario in scenarios:
            for noise in noises:
                cells = [row for r in results.get(method, []) for row in r["rows"]
                         if row["scenario"] == scenario and row["noise"] == noise]
                if not cells:
                    continue
                n_tasks.add(cells[0]["n_tasks"])
                control.update((r["control_dt"], r["max_steps"]) for r in results[method])
                times = [c["time_to_success_s"] for c in cells if c["time_to_success_s"] is not None]
                figure = paper()["fig9"][scenario] if method in block["paper_rows"] else {}
                rows.append([block["labels"][method], scenario, noise, mean_std(c["success_rate"] for c in cells),
                             mean_std(c["collision_rate"] for c in cells), mean_std(times, lambda x: f"{x:.2f}"),
                             str(len(cells)), paper_cell(figure.get("simulation"), lambda x: f"{x:.2f}"),
                             paper_cell(figure.get("real"), lambda x: f"{x:.2f}")])
    header = ["Method", "Scenario", "Noise", "Success", "Collisions", "Time to success (s)", "Seeds",
              "paper, simulation", "paper, real UR5e"]
    levels = "; ".join(f"*{n}*: box noise {p['obstacle_noise']} m, latency {p['latency_steps']} step(s), encoders "
                       f"{p['joint_noise']} rad" for n, p in _perceptions(results, noises).items())
    dt, steps = sorted(control)[0]
    return [table(header, rows, ["l", "l", "l", *"r" * 6]), "",
            f"Mean (std) over the policies' seeds; {', '.join(map(str, sorted(n_tasks)))} seeded tasks per scenario, "
            f"control period {dt} s, at most {steps} steps. Success: MuJoCo's TCP within 0.05 m of the goal after a "
            "control step; a collision (any contact of the arm with the table, the box or itself) ends a task. Time to "
            f"success: simulated seconds, over the tasks that succeed. Noise levels: {levels}. The paper's columns: "
            "its SAC-SILP+ in 50 trials per scenario (sec. 4.5), in Gazebo and on the real UR5e.", "",
            "Policies: " + _policies(results, block, lambda row: row["scenario"] in scenarios) + ".", "",
            f"Files: `{folder}/<method>/seed<k>/*.json` (each written by `python recipes/transfer.py "
            f"checkpoint=RUN_DIR`); regenerate with `python recipes/report.py --block {name}`.", ""]


def _reaching_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    """Table 5: each policy's share of the reaching test's trials per noise level, mean (std) over seeds, and
    each scenario's share; the paper's figures beside; the paper's claims on the ``checks`` noise level.

    A check (``tables.judge``) is an ordering of the means on its ``noise`` level (``order``: each at least
    the next) or, with ``max_difference``, a bound on how far the first may lie above the second."""
    folder = Path(block["results"])
    found = {row["method"]: [json.loads(p.read_text()) for p in sorted((folder / row["method"]).glob("seed*/summary.json"))]
             for row in block["rows"]}
    figures = paper()[block["paper"]]
    rows, per_scenario, means, shapes = [], [], {}, set()
    for spec in block["rows"]:
        results = found[spec["method"]]
        figure = figures.get(spec["paper"], {})
        for noise in block["noises"]:
            cells = [row for r in results for row in r["rows"] if row["scenario"] == "reaching" and row["noise"] == noise]
            if not cells:
                rows.append([spec["label"], noise, "not run", "—", "0", paper_cell(figure.get("simulation"), rate),
                             paper_cell(figure.get("real"), rate)])
                continue
            shapes.update((len(c["scenario_success"]), c["n_tasks"] // len(c["scenario_success"])) for c in cells)
            means[spec["method"], noise] = float(np.mean([c["success_rate"] for c in cells]))
            rows.append([spec["label"], noise, mean_std(c["success_rate"] for c in cells),
                         mean_std(c["collision_rate"] for c in cells), str(len(cells)),
                         paper_cell(figure.get("simulation"), rate), paper_cell(figure.get("real"), rate)])
            shares = np.mean([c["scenario_success"] for c in cells], axis=0)
            per_scenario.append([spec["label"], noise, *(f"{x:.2f}" for x in shares)])
    lines = [table(["Method", "Noise", "Success", "Collisions", "Seeds", "paper, simulation", "paper, real UR5e"], rows,
                   ["l", "l", *"r" * 5]), ""]
    if per_scenario:
        n = max(len(r) for r in per_scenario) - 2
        lines += ["Each scenario's share of its trials (mean over seeds; 1-5 *free*, 6-10 *block*):", "",
                  table(["Method", "Noise", *map(str, range(1, n + 1))], per_scenario, ["l", "l", *"r" * n]), ""]
    shape = ", ".join(f"{s} scenarios of {t} trials" for s, t in sorted(shapes)) or "10 scenarios of 10 trials"
    lines += [f"Mean (std) over the policies' seeds; {shape} (`torchrl_silp.sim.reaching_trials`), the trials of "
              "a scenario differing in what perception draws; success and collisions as in Fig. 9's block. The "
              "paper's columns: its Table 5, 100 trials of each policy in 10 scenarios it does not list, in "
              "simulation and on the real UR5e.", ""]
    def judged(check: dict) -> str:
        ordering = {k: check[k] for k in ("order", "max_difference") if k in check}
        return tables.judge({"text": check["text"], "all": [ordering]},
                            lambda m, key, stat: means.get((m, check["noise"])))

    checks = [judged(c) for c in block.get("checks", [])]
    if checks:
        lines += ["The paper's sentences, on our means:", "", *checks, ""]
    lines += [f"Files: `{folder}/<method>/seed<k>/summary.json` (sweep config `{block['sweep_config']}`: the training runs "
              "and, after each, `recipes/transfer.py scenario=reaching` on its checkpoint); regenerate with "
              f"`python recipes/report.py --block {name}`.", ""]
    return lines


def _pick_place_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    folder = Path(block["results"])
    results = load.load_transfer(folder)
    rows, n_tasks = [], set()
    for method in block["methods"]:
        for noise in block["noises"]:
            cells = [row for r in results.get(method, []) for row in r["rows"]
                     if row["scenario"] == "pick_place" and row["noise"] == noise]
            if not cells:
                continue
            n_tasks.add(cells[0]["n_tasks"])
            rows.append([block["labels"][method], noise, *(mean_std(c[f"{s}_rate"] for c in cells) for s in block["stages"]),
                         mean_std(c["collision_rate"] for c in cells), str(len(cells))])
    header = ["Method", "Noise", "Pre-grasp reached", "Grasped", "Carried to the basket", "Placed (success)",
              "Collisions", "Seeds"]
    return [table(header, rows, ["l", "l", *"r" * 6]), "",
            f"Mean (std) over the policies' seeds, {', '.join(map(str, sorted(n_tasks)))} seeded trials each; a "
            "stage's share counts the trials through it and every stage before it.", "",
            "Policies: " + _policies(results, block, lambda row: row["scenario"] == "pick_place") + ".", "",
            f"Files: `{folder}/<method>/seed<k>/*.json` (`python recipes/transfer.py checkpoint=RUN_DIR "
            f"scenario=pick_place`); regenerate with `python recipes/report.py --block {name}`.", ""]


def _policies(results: dict, block: dict, wanted) -> str:
    parts = []
    for method in block["methods"]:
        named = []
        for r in results.get(method, []):
            if not any(wanted(row) for row in r["rows"]):
                continue
            text = (f"seed {r['seed']} ({r['trained_episodes']:,} episodes, `{r['checkpoint']}`)" if r["checkpoint"]
                    else f"seed {r['seed']} (a planner, no training)")
            if text not in named:
                named.append(text)
        if named:
            parts.append(f"{block['labels'][method]}: {', '.join(named)}")
    return "; ".join(parts)


def _perceptions(results: dict, noises: list[str]) -> dict:
    out = {}
    for rs in results.values():
        for r in rs:
            for row in r["rows"]:
                out.setdefault(row["noise"], row["perception"])
    return {k: out[k] for k in noises if k in out}


def _collision_net_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    folder = Path(block["results"])
    nets = load.load_collision_nets(folder)
    p = paper()["collision_net"]
    rows = [["the paper's (appendix B)", f"{p['n']:,}", "—", *(rate(p[k]) for k in ("accuracy", "recall", "precision",
                                                                                      "specificity")), "—"]]
    for net in nets:
        m = net["metrics"]
        rows.append([f"ours, labels: {net['labeller']}", f"{net['n']:,}", rate(net["collision_share"]),
                     *(rate(m[k]) for k in ("accuracy", "recall", "precision", "specificity")), f"{net['roc']['auc']:.4f}"])
    lines = [table(["Model", "Configurations", "Collision share", "Accuracy", "Recall", "Precision", "Specificity",
                    "ROC AUC"], rows, ["l", *"r" * 7]), "",
             "CollisionNet (512-256-64, the paper's sizes) trained on 90 % of the configurations, the metrics on the "
             "other 10 % at a threshold of 0.5, collision the positive class. Labels *exact*: the task model's checker "
             "(its sphere cover: box, table, self, workspace); *mujoco*: the twin's contacts on the URDF's primitives "
             "(no workspace bound).", ""]
    target = draw if draw is not None else page.parent / block["figure"]
    if draw is not None or _drawing:
        figures.roc_figure(nets, target)
    lines += [f"![ROC of the collision model]({relpath(target, page)})", "",
              f"Files: `{folder}/*.json`, made by " + "; ".join(f"`{n['command']}`" for n in nets)
              + f"; regenerate with `python recipes/report.py --block {name}`.", ""]
    return lines


def _robots_block(name: str, block: dict, page: Path, draw: Path | None) -> list[str]:
    folder = Path(block["results"])
    found = [json.loads((folder / f"{r}.json").read_text()) for r in block["robots"]]
    rows = []
    for r in found:
        e, p = r["exact"], r["self_pairs"]
        dropped = ", ".join(f"{len(v)} {k}" for k, v in (p["dropped"] or {}).items() if v) or "—"
        rows.append([r["robot"], f"`{r['urdf']}`", ", ".join(r["geometry"]), str(len(r["joints"])), str(r["spheres"]),
                     f"{e['box']['contacts']:,} / {e['box']['tests']:,}", str(e["box"]["missed"]),
                     rate(e["box"]["false_alarm_rate"]), f"{e['self']['contacts']:,} / {e['self']['tests']:,}",
                     str(e["self"]["missed"]), rate(e["self"]["false_alarm_rate"]),
                     f"{len(p['checked'])} {'found' if p['found'] else 'the task’s rule'}; dropped {dropped}",
                     f"{r['fk_max_error_m']:.0e} m"])
    lines = [table(["Robot", "URDF", "Geometry", "Joints", "Spheres", "Box contacts (FCL) / tests", "Missed",
                    "False alarms", "Self contacts (FCL) / tests", "Missed", "False alarms", "Self pairs",
                    "FK vs pytorch-kinematics"], rows, ["l", "l", "l", *"r" * 9, "r"]), "",
             "Each configuration is drawn over the joint limits, with boxes near the arm (centred on a random "
             "point of a random link's cover, sides 1-30 cm); FCL judges each link's own collision geometry (its "
             "meshes or primitives) against each box and each checked self pair, the cover the same tests on its "
             "spheres. *Missed*: a contact FCL finds and the cover does not; *false alarms*: the cover's contacts "
             "FCL does not confirm, as a share of the cover's. Self pairs: found by sampling as MoveIt's setup "
             "assistant does (`torchrl_silp.robots.self_collision`), or the paper task's rule for the UR5e and "
             "the Panda. FK: the largest TCP distance to pytorch-kinematics' on the same URDF, 1,000 "
             "configurations, float64.", ""]
    for r in found:
        m = r.get("moveit")
        if m:
            differ = "; ".join(f"{a}-{b}: ours {o}, MoveIt's {t}" for a, b, o, t in m["differ"]) or "none"
            lines += [f"{r['robot']}: our reason for each link pair (checked, or dropped as adjacent, never, ...) is "
                      f"MoveIt's setup assistant's (`{Path(m['srdf']).name}`, shipped with the description) for "
                      f"{m['same_reason']} of {m['pairs']} pairs; differing: {differ}.", ""]
    for r in found:
        if not r["links"]:
            continue
        link_rows = [[f"`{x['link']}`", str(x["spheres"]), f"{x['cover_volume'] * 1e3:.2f}",
                      f"{x['geometry_volume'] * 1e3:.2f}", f"{x['ratio']:.2f}"] for x in r["links"]]
        total = [sum(x[k] for x in r["links"]) for k in ("cover_volume", "geometry_volume")]
        link_rows.append(["all links", str(r["spheres"]), f"{total[0] * 1e3:.2f}", f"{total[1] * 1e3:.2f}",
                          f"{total[0] / total[1]:.2f}"])
        picture = page.parent / block["figures"] / f"{r['robot']}_cover.png"
        if draw is not None or _drawing:
            from torchrl_silp.recipes.robot_check import build
            from torchrl_silp.viz import save_cover_png

            picture.parent.mkdir(parents=True, exist_ok=True)
            save_cover_png(build(r["spec"]), picture)
        lines += [f"**{r['robot']}**: the cover per link (volumes in litres; the geometry's is the union of the "
                  "link's solids, a mesh's convex hull where it is not closed).", "",
                  table(["Link", "Spheres", "Cover", "Geometry", "Cover / geometry"], link_rows, ["l", *"r" * 4]), "",
                  f"![{r['robot']}: collision geometry and sphere cover]({relpath(picture, page)})", ""]
    commands = "; ".join(dict.fromkeys(f"`{r['command']}`" for r in found))
    machines = "; ".join(dict.fromkeys(r["machine"] for r in found))
    lines += [f"Files: `{folder}/<robot>.json`, made by {commands} ({machines}); regenerate with "
              f"`python recipes/report.py --block {name}`.", ""]
    return lines


KINDS = {"runs": _runs_block, "headline": _headline_block, "benchmarks": _benchmarks_block,
         "transfer": _transfer_block, "reaching": _reaching_block, "pick_place": _pick_place_block, "collision_net": _collision_net_block,
         "robots": _robots_block}
_drawing = False  # set by write(): --check and tests render the text without drawing


def render(name: str, page: Path, results: Path | None = None, figure: Path | None = None) -> str:
    """Block ``name`` of pages.yaml for ``page``, markers included; ``results`` reads another folder (every row
    of a runs block), ``figure`` draws the block's figure there."""
    blocks = spec()["blocks"]
    if name not in blocks:
        raise KeyError(f"no block {name!r} in pages.yaml: one of {', '.join(blocks)}")
    block = dict(blocks[name])
    if results is not None:
        _runs_of.cache_clear()
        block["results"] = str(results)
        if block.get("rows", "all") != "all":
            block["rows"] = [{**(r if isinstance(r, dict) else {"method": r}), "results": str(results)}
                             for r in block["rows"]]
    return render_block(name, block, page, figure)


def render_block(name: str, block: dict, page: Path, figure: Path | None = None) -> str:
    """A block's text from its spec (a ``blocks`` entry of pages.yaml), markers included."""
    if block.get("kind") not in KINDS:
        raise ValueError(f"block {name!r}: kind {block.get('kind')!r} is not one of {', '.join(KINDS)}")
    begin, end = markers(name)
    body = KINDS[block["kind"]](name, block, page, figure)
    return "\n".join([begin, f"### {block['title']}", "", *body, end])


# ------------------------------------------------------------------------------------- pages on disk
def replace_block(text: str, name: str, block: str) -> str:
    """``text`` with block ``name`` replaced by ``block`` (appended at the end when its markers are missing)."""
    begin, end = markers(name)
    start, stop = text.find(begin), text.find(end)
    if start != -1 and stop > start:
        return text[:start] + block + text[stop + len(end):]
    return (text.rstrip("\n") + "\n\n" if text.strip() else "") + block + "\n"


def committed_block(text: str, name: str) -> str | None:
    begin, end = markers(name)
    start, stop = text.find(begin), text.find(end)
    return text[start:stop + len(end)] if start != -1 and stop > start else None


def write(names: list[str] | None = None) -> list[Path]:
    """Regenerate blocks ``names`` (every block by default) in the pages that hold them, figures included."""
    global _drawing
    written = []
    _drawing = True
    _runs_of.cache_clear()
    try:
        for page in spec()["pages"].values():
            path = Path(page["path"])
            old = path.read_text() if path.exists() else ""
            new = old
            for name in page["blocks"]:
                if names is None or name in names:
                    new = replace_block(new, name, render(name, path))
            if new != old:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(new)
            if names is None or set(names) & set(page["blocks"]):
                written.append(path)
    finally:
        _drawing = False
    return written


def check() -> list[str]:
    """What differs between the pages and what the results files give: a block missing, differing, or a
    figure it links that does not exist. Empty: every page is as generated."""
    problems = []
    _runs_of.cache_clear()
    for page in spec()["pages"].values():
        path = Path(page["path"])
        text = path.read_text() if path.exists() else ""
        for name in page["blocks"]:
            found = committed_block(text, name)
            if found is None:
                problems.append(f"{path}: no {name} block (markers {' '.join(markers(name))})")
                continue
            if found != render(name, path):
                problems.append(f"{path}: block {name} differs from what `python recipes/report.py --block {name}` "
                                f"writes")
            for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", found):
                if not (path.parent / link).exists():
                    problems.append(f"{path}: block {name} links {link}, which does not exist")
    return problems


def main(argv: list[str] | None = None) -> str:
    """The command line; returns the text of the block it rendered with ``--results``/``--out`` (else "")."""
    blocks = list(spec()["blocks"])
    parser = argparse.ArgumentParser(prog="python recipes/report.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--block", choices=blocks, help="regenerate this block only (every page holding it)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 listing each page block that differs from what results/ gives")
    parser.add_argument("--results", type=Path, help="read the block (default table1) from this folder instead and "
                                                     "write it to --out: a sweep's own results")
    parser.add_argument("--out", type=Path, help="with --results: the markdown file to put the block in")
    parser.add_argument("--figure", type=Path, help="with --results: where to draw the block's figure")
    args = parser.parse_args(argv)
    if args.check:
        problems = check()
        print("\n".join(problems) or "every page block is what results/ gives")
        raise SystemExit(1 if problems else 0)
    if args.results is not None or args.out is not None:
        name = args.block or "table1"
        out = args.out or Path(f"{name}.md")
        given = sys.argv[1:] if argv is None else argv
        text = render(name, out, args.results, args.figure)
        text = text.replace(f"`python recipes/report.py --block {name}`",
                            "`" + " ".join(["python recipes/report.py", *map(shlex.quote, given)]) + "`")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(replace_block(out.read_text() if out.exists() else "", name, text))
        print(f"wrote the {name} block to {out}")
        return text
    for path in write([args.block] if args.block else None):
        print(f"wrote {path}")
    return ""
