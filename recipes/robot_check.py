"""Judge robots' sphere covers: per link the spheres and their volume over the collision geometry's, the
self-collision pairs kept and dropped, FK against pytorch-kinematics, and the cover against FCL on the
robot's own meshes (missed contacts and false alarms). One JSON per robot under results/robots/.

    python recipes/robot_check.py                        # every robot of recipes/config/robots.yaml
    python recipes/robot_check.py --robot ur10 --configs 2000
    python recipes/robot_check.py --urdf my_arm.urdf --joints j1,j2,j3 --ee-link tool0 --picture my_arm.png

``python recipes/report.py --block robots`` renders the files (and draws each cover over its meshes).
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from torchrl_silp import robots
from torchrl_silp.robots.exact_check import exact_collision_check

CONFIG = Path(__file__).resolve().parent / "config" / "robots.yaml"


def build(spec: dict, dtype=torch.float32) -> robots.ArmKinematics:
    """The robot a ``robots.yaml`` entry names: a package class (``class: UR5e``) or URDFArm's keyword arguments."""
    spec = dict(spec)
    name = spec.pop("class", None)
    if name is not None:
        return getattr(robots, name)(dtype=dtype, **spec)
    return robots.URDFArm(**spec, dtype=dtype)


def srdf_disabled(path: str) -> dict[frozenset, str]:
    """MoveIt's allowed-collision pairs of an SRDF: ``{frozenset((link1, link2)): reason}``, reasons lower-case."""
    import xml.etree.ElementTree as ET

    from torchrl_silp.robots.urdf import resolve_urdf_path

    root = ET.parse(resolve_urdf_path(path)).getroot()
    return {frozenset((e.get("link1"), e.get("link2"))): (e.get("reason") or "").lower()
            for e in root.iter("disable_collisions")}


def moveit_agreement(arm, srdf: str) -> dict:
    """Our reason for each link pair (or "check") against MoveIt's SRDF's, over the links with collision geometry."""
    import itertools

    theirs = srdf_disabled(srdf)
    ours = {frozenset(p): r for r, pairs in arm.self_collision_matrix.dropped.items() for p in pairs}
    links = list(dict.fromkeys(arm.sphere_link_names))
    pairs = [frozenset(p) for p in itertools.combinations(links, 2)]
    same = [p for p in pairs if ours.get(p, "check") == theirs.get(p, "check")]
    return {"srdf": srdf, "pairs": len(pairs), "same_reason": len(same),
            "differ": [[*sorted(p), ours.get(p, "check"), theirs.get(p, "check")] for p in pairs if p not in same]}


def check_robot(name: str, spec: dict, configs: int, boxes_per_config: int, seed: int) -> dict:
    spec = dict(spec)
    srdf = spec.pop("srdf", None)
    started = time.perf_counter()
    arm = build(spec)
    built_s = time.perf_counter() - started
    arm64 = build(spec, torch.float64)
    gen = torch.Generator().manual_seed(seed)
    q = arm64.joint_low + torch.rand(1000, arm64.config_dim, generator=gen, dtype=torch.float64) * (
        arm64.joint_high - arm64.joint_low)
    fk_error = float((arm64.fk(q) - arm64.reference_fk(q)).norm(dim=-1).max())
    links = [dict(link=r.link, spheres=r.spheres, cover_volume=r.cover_volume, geometry_volume=r.geometry_volume,
                  ratio=r.ratio) for r in arm.cover_report()] if isinstance(arm, robots.URDFArm) else []
    kinds = sorted({p.kind for p in arm.primitives})
    names = arm.sphere_link_names
    checked = sorted({(names[i], names[j]) for i, j in zip(arm.self_pair_a.tolist(), arm.self_pair_b.tolist())})
    acm = getattr(arm, "self_collision_matrix", None)
    exact = exact_collision_check(arm, configs=configs, boxes_per_config=boxes_per_config, seed=seed)
    return {
        "robot": name,
        "spec": spec,
        "urdf": Path(arm.urdf_path).name,
        "joints": list(arm.joint_names),
        "geometry": kinds,
        "spheres": arm.n_spheres,
        "links": links,
        "table_links": list(arm.table_links),
        "self_pairs": {
            "found": acm is not None,
            "checked": [list(p) for p in checked],
            "dropped": {k: [list(p) for p in v] for k, v in acm.dropped.items()} if acm is not None else None,
            "samples": acm.samples if acm is not None else None,
        },
        "moveit": moveit_agreement(arm, srdf) if srdf else None,
        "fk_max_error_m": fk_error,
        "exact": exact,
        "build_s": built_s,
        "machine": f"{platform.machine()}, {torch.get_num_threads()} threads",
        "command": "python recipes/robot_check.py " + shlex.join(sys.argv[1:]),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", action="append", help="a robot of recipes/config/robots.yaml (default: all)")
    parser.add_argument("--urdf", help="a robot of yours instead: its URDF file (or package:// path)")
    parser.add_argument("--joints", help="with --urdf: the configuration's joints, comma-separated")
    parser.add_argument("--ee-link", help="with --urdf: the link the TCP rides on")
    parser.add_argument("--package-dirs", help="with --urdf: folders holding its packages, comma-separated")
    parser.add_argument("--picture", help="also draw the robot's cover over its geometry into this PNG")
    parser.add_argument("--configs", type=int, default=20_000, help="configurations of the exact check")
    parser.add_argument("--boxes-per-config", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/robots")
    args = parser.parse_args(argv)
    specs = OmegaConf.to_container(OmegaConf.load(CONFIG))
    if args.urdf is not None:
        if not args.joints or not args.ee_link:
            parser.error("--urdf needs --joints and --ee-link")
        spec = dict(urdf_path=args.urdf, joints=args.joints.split(","), ee_link=args.ee_link)
        if args.package_dirs:
            spec["package_dirs"] = args.package_dirs.split(",")
        try:
            build(spec)
        except ValueError as error:  # one line naming what to fix, no traceback
            parser.error(" ".join(str(error).split()))
        specs = {Path(args.urdf).stem: spec}
        args.robot = list(specs)
    wanted = args.robot or list(specs)
    unknown = sorted(set(wanted) - set(specs))
    if unknown:
        parser.error(f"--robot: {unknown} not in {CONFIG.name}; one of {', '.join(specs)}")
    out = Path(args.out)
    if args.urdf is None:
        out.mkdir(parents=True, exist_ok=True)
    for name in wanted:
        result = check_robot(name, specs[name], args.configs, args.boxes_per_config, args.seed)
        if args.urdf is None:
            (out / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
        for link in result["links"]:
            print(f"  {link['link']}: {link['spheres']} spheres, cover / geometry volume {link['ratio']:.2f}")
        pairs = result["self_pairs"]
        dropped = ", ".join(f"{len(v)} {k}" for k, v in (pairs["dropped"] or {}).items() if v)
        print(f"  self pairs: {len(pairs['checked'])} checked" + (f"; dropped: {dropped}" if dropped else ""))
        if args.picture:
            from torchrl_silp.viz import save_cover_png

            save_cover_png(build(specs[name]), args.picture)
            print(f"  picture: {args.picture}")
        e = result["exact"]
        print(f"{name}: {result['spheres']} spheres; box contacts {e['box']['contacts']}, missed {e['box']['missed']}, "
              f"false alarms {e['box']['false_alarm_rate']:.1%}; self contacts {e['self']['contacts']}, missed "
              f"{e['self']['missed']}; FK error {result['fk_max_error_m']:.1e} m")


if __name__ == "__main__":
    main()
