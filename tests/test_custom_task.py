"""The main job on a task model of the user's own, given on the command line: no file of the repository
changed, the model checked first, its run folder named after it, and its rollout picture drawn."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TINY = ["env.num_envs=4", "collector.frames_per_batch=100", "collector.init_random_frames=100", "eval.n_tasks=8",
        "eval.every_frames=200", "optim.batch_size=16", "replay_buffer.size=5000", "replay_buffer.demo_size=5000",
        "exploration.n_candidates=8", "progress=false", "threads=1", "compile.compile=false", "logger.backend="]


def tree_state(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and "__pycache__" not in p.parts}


def recipe(cwd: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    # the user's package (here the repository's examples/) importable, as an installed one would be
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, str(REPO / "recipes" / "sac_silp.py"), *overrides], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_the_main_job_trains_a_user_s_task_model_given_on_the_command_line(tmp_path):
    before = tree_state(REPO / "recipes")
    out = recipe(tmp_path, *TINY, "collector.total_frames=300", "env=custom",
                 "env.model._target_=examples.planar_arm.PlanarArmReach", "env.model.n_discs=2")
    assert out.returncode == 0, out.stderr[-3000:]
    run_dir = tmp_path / "runs" / "PlanarArmReach" / "sac_silp_plus_ext" / "seed0"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env"] == "PlanarArmReach" and summary["frames"] == 300 and summary["updates"] > 0
    picture = run_dir / "test_rollouts.png"
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and picture.stat().st_size > 10_000
    assert tree_state(REPO / "recipes") == before


def test_a_user_s_env_yaml_in_a_config_dir_of_their_own(tmp_path):
    (tmp_path / "conf" / "env").mkdir(parents=True)
    (tmp_path / "conf" / "env" / "arm3.yaml").write_text(
        "name: arm3\nnum_envs: 4\nmax_steps: 30\ncollision_type: 2\n"
        "model:\n  _target_: examples.planar_arm.PlanarArmReach\n  n_discs: 1\n")
    out = recipe(tmp_path, "--config-dir", str(tmp_path / "conf"), "env=arm3", *TINY[1:], "collector.total_frames=200")
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads((tmp_path / "runs" / "arm3" / "sac_silp_plus_ext" / "seed0" / "summary.json").read_text())[
        "env"] == "arm3"


def test_a_custom_task_without_its_class_or_with_a_broken_model_is_refused_in_one_line(tmp_path):
    missing = recipe(tmp_path, "env=custom", timeout=60)
    assert missing.returncode == 2
    assert missing.stderr.strip() == ("error: env.model._target_: must be given (the task model's class, e.g. "
                                      "mypkg.tasks.MyReach): env.model._target_=...")
    wrong = recipe(tmp_path, "env=custom", "env.model._target_=examples.planar_arm.nothing_here", timeout=60)
    assert wrong.returncode == 2 and wrong.stderr.startswith("error: env.model._target_: ")
    broken = recipe(tmp_path, "env=custom", "env.model._target_=examples.planar_arm.PlanarArmReach",
                    "env.model.n_discs=0", timeout=120)
    assert broken.returncode == 2 and "n_discs must be a positive int" in broken.stderr
    assert len(broken.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists() and not (tmp_path / "outputs").exists()


def _flat(cfg) -> dict:
    from omegaconf import OmegaConf

    def walk(tree, prefix=""):
        for key, value in tree.items():
            if isinstance(value, dict):
                yield from walk(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}", value

    return dict(walk(OmegaConf.to_container(cfg, resolve=True)))


def test_the_like_for_like_baselines_change_only_what_their_method_changes():
    from torchrl_silp.recipes.schema import load_config

    ours = {"sac": _flat(load_config("sac_silp", ["method=sac_silp_plus_ext"])),
            "ddpg": _flat(load_config("sac_silp", ["method=ddpg_silp_plus_ext"]))}
    expected = {
        "sac_ext": ("sac", {"silp.demos": False, "silp.bc": False, "exploration.mode": "random"}),
        "sac_her_ext": ("sac", {"silp.demos": False, "silp.bc": False, "exploration.mode": "random",
                                "replay_buffer.her": True}),
        "sac_demon_ext": ("sac", {"silp.bc": False}),
        "ddpg_ext": ("ddpg", {"silp.demos": False, "silp.bc": False, "exploration.mode": "random"}),
    }
    for method, (base, changes) in expected.items():
        cfg = _flat(load_config("sac_silp", [f"method={method}"]))
        differ = {k: v for k, v in cfg.items() if ours[base].get(k) != v and k not in ("logger.exp_name", "run_dir")}
        differ.pop("silp.filter", None) if base == "ddpg" else None  # DDPG-SILP+'s reward filter acts on BC only
        assert differ == changes, method
        assert cfg["logger.exp_name"] == method
