"""A run never damages another: run folders per task and method, bad input refused before anything is
written (one line naming the key, exit status 2), strict JSON, a picture for every task."""

from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from torchrl_silp.recipes.preflight import check_run_folder
from torchrl_silp.recipes.schema import ConfigError, check_config
from torchrl_silp.recipes.schema import load_config

RECIPES = Path(__file__).parents[1] / "recipes"
TINY = ["env.num_envs=4", "collector.frames_per_batch=100", "collector.init_random_frames=100", "eval.n_tasks=8",
        "eval.every_frames=200", "optim.batch_size=16", "replay_buffer.size=5000", "replay_buffer.demo_size=5000",
        "exploration.n_candidates=8", "checkpoint.every_iters=1", "progress=false", "threads=1",
        "compile.compile=false"]


def folder_state(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` by its bytes' hash, and its modification time."""
    return {str(p.relative_to(folder)): f"{hashlib.sha256(p.read_bytes()).hexdigest()} {p.stat().st_mtime_ns}"
            for p in sorted(folder.rglob("*")) if p.is_file()}


def recipe(cwd: Path, *overrides: str, script: str = "sac_silp.py", timeout: float = 300):
    return subprocess.run([sys.executable, str(RECIPES / script), *overrides], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


def strict_json(path: Path):
    return json.loads(path.read_text(), parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))


def signalled_after_first_checkpoint(cwd: Path, run_dir: Path, signum: int, *overrides: str) -> tuple[int, str, str]:
    """The main job started in ``cwd`` on a budget it will not reach, sent ``signum`` once ``run_dir`` holds its
    first checkpoint: ``(returncode, stdout, stderr)``."""
    proc = subprocess.Popen([sys.executable, str(RECIPES / "sac_silp.py"), *TINY, "collector.total_frames=100000",
                             *overrides], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    try:
        while not (run_dir / "checkpoint" / "state.pt").exists():
            assert proc.poll() is None, proc.stderr.read()[-3000:]
            assert time.monotonic() < deadline, "no checkpoint in 240 s"
            time.sleep(0.2)
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    return proc.returncode, out, err


@pytest.fixture(scope="module")
def stopped_ur5e_run(tmp_path_factory):
    """A UR5e run of the default method and seed in the default run folder, stopped by SIGTERM after its
    first checkpoint: ``(cwd, run_dir)``."""
    cwd = tmp_path_factory.mktemp("user")
    run_dir = cwd / "runs" / "ur5e_reach" / "sac_silp_plus_ext" / "seed0"
    returncode, _, _ = signalled_after_first_checkpoint(cwd, run_dir, signal.SIGTERM)
    assert returncode == 128 + signal.SIGTERM
    return cwd, run_dir


def test_a_panda_run_of_the_same_seed_and_method_leaves_the_ur5e_run_untouched(stopped_ur5e_run):
    cwd, ur5e = stopped_ur5e_run
    before = folder_state(ur5e)
    assert {"config.yaml", "checkpoint/state.pt"} <= set(before)
    panda = recipe(cwd, *TINY, "env=panda_reach", "collector.total_frames=200")
    assert panda.returncode == 0, panda.stderr[-3000:]
    assert folder_state(ur5e) == before
    panda_dir = cwd / "runs" / "panda_reach" / "sac_silp_plus_ext" / "seed0"
    assert strict_json(panda_dir / "summary.json")["env"] == "panda_reach"
    assert (panda_dir / "test_rollouts.png").stat().st_size > 0  # the picture of a task that is not the UR5e
    for path in panda_dir.rglob("*.json"):
        strict_json(path)
    assert not (cwd / "outputs").exists()


def test_a_fresh_start_onto_a_checkpoint_is_refused_and_writes_nothing(stopped_ur5e_run):
    cwd, ur5e = stopped_ur5e_run
    before = folder_state(ur5e)
    refused = recipe(cwd, *TINY, "collector.total_frames=400", timeout=60)
    assert refused.returncode == 2
    assert refused.stderr.strip() == ("error: run_dir: runs/ur5e_reach/sac_silp_plus_ext/seed0 holds a run's "
                                      "checkpoint; continue it with resume=true, or start a new run in another "
                                      "run_dir=... (nothing was written)")
    assert folder_state(ur5e) == before


BAD_INPUTS = [
    ("env.num_envs=-3", "env.num_envs: must be an integer >= 1, got -3"),
    ("method=bogus", "method: no option 'bogus'; one of: ddpg "),
    ("optim.lr=abc", "optim.lr: Value 'abc' of type 'str' could not be converted to Float"),
    ("planner.d=-1", "planner.d: must be a number > 0, got -1.0"),
    ("collector.frames_per_batch=7", "collector.frames_per_batch: must be a multiple of env.num_envs (4), got 7"),
    ("collector.total_frames=4000", "collector.total_frames: a budget of 4000 frames is used up by the 8000 frames"),
    ("resume=must", "resume: resume=must, but"),
]
if not torch.cuda.is_available():
    BAD_INPUTS.append(("device=cuda", "device: cuda asked, but torch finds no CUDA device here"))


@pytest.mark.parametrize("existing", [False, True], ids=["no folder", "a run's folder"])
def test_bad_input_exits_2_with_one_line_naming_the_key_and_writes_nothing(tmp_path, existing):
    run_dir = tmp_path / "run"
    if existing:  # another run's config and logs, no checkpoint (so that resume=must is refused for its reason)
        (run_dir / "logs").mkdir(parents=True)
        (run_dir / "config.yaml").write_text("env:\n  name: panda_reach\n")
        (run_dir / "logs" / "x.csv").write_text("100,1.0\n")
    before = folder_state(tmp_path)
    for override, message in BAD_INPUTS:
        base = ["env.num_envs=4"] if not override.startswith(("env.num_envs", "collector.total")) else []
        if override == "collector.total_frames=4000":
            base = ["collector.init_random_frames=8000"]
        started = time.monotonic()
        out = recipe(tmp_path, *base, f"run_dir={run_dir}", override, timeout=60)
        took = time.monotonic() - started
        assert out.returncode == 2, (override, out.stderr[-2000:])
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], (override, out.stderr)
        assert "Traceback" not in out.stdout + out.stderr
        if not override.startswith("device"):  # the checks before any heavy import
            assert took < 10, (override, took)  # (2 s alone; the tests may share the machine)
        assert folder_state(tmp_path) == before, override
        assert not (tmp_path / "outputs").exists()


def test_the_light_checks_refuse_before_importing_torch():
    code = ("import sys; from torchrl_silp.recipes.preflight import main\n"
            "try:\n    main('sac_silp', 'x:y', ['planner.d=-1'])\n"
            "except SystemExit as e:\n    print(e.code, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["2", "False"], out.stderr


def test_the_config_check_takes_its_choices_from_the_library():
    from torchrl_silp.data.her import HER_STRATEGIES
    from torchrl_silp.envs import COLLISION_TYPES
    from torchrl_silp.eval import DEFAULT_TEST_SEED, DEFAULT_VALIDATION_SEED
    from torchrl_silp.modules.gp_exploration import GP_EXPLORATION_MODES
    from torchrl_silp.objectives.silp import BC_FILTERS, DEMO_ROWS
    from torchrl_silp.planning.demos import INSERT_NODES
    from torchrl_silp.planning.search import SEARCH_METHODS
    from torchrl_silp.recipes import schema

    assert schema.HER_STRATEGIES is HER_STRATEGIES
    assert schema.COLLISION_TYPES is COLLISION_TYPES
    assert set(schema.EXPLORATION_MODES) == {*GP_EXPLORATION_MODES, "none"}
    assert schema.BC_FILTERS is BC_FILTERS
    assert set(schema.DEMO_ROWS_CHOICES) == {*DEMO_ROWS, "auto"}
    assert schema.INSERT_NODES is INSERT_NODES
    assert schema.SEARCH_METHODS is SEARCH_METHODS
    assert (schema.DEFAULT_VALIDATION_SEED, schema.DEFAULT_TEST_SEED) == (DEFAULT_VALIDATION_SEED, DEFAULT_TEST_SEED)


def test_the_her_strategies_are_torchrl_s():
    from torchrl.data.replay_buffers.her import HindsightStrategy

    from torchrl_silp.choices import HER_STRATEGIES

    assert HER_STRATEGIES == tuple(s.value for s in HindsightStrategy)


@pytest.mark.parametrize("override,key", [
    ("seed=-1", "seed"), ("env.collision_type=3", "env.collision_type"), ("optim.gamma=1.5", "optim.gamma"),
    ("eval.actor_average_decay=1.0", "eval.actor_average_decay"), ("network.hidden_sizes=[]", "network.hidden_sizes"),
    ("silp.filter=bogus", "silp.filter"), ("logger.exp_name=a/b", "logger.exp_name"),
    ("collector.total_episodes=100", "collector.total_episodes"),  # 100 episodes x 50 steps < 8000 warm-up frames
    ("silp.demos=false", "silp.bc"),  # the BC term with no demonstrations
    ("compile.guards=some", "compile.guards"), ("stop_at_success=0", "stop_at_success"),
    ("silp.demo_rows=all", "silp.demo_rows"), ("exploration.mode=curious", "exploration.mode"),
    ("collector.frames_per_batch=101", "collector.frames_per_batch"),  # not a multiple of env.num_envs
])
def test_check_config_names_the_key(override, key):
    with pytest.raises(ConfigError) as error:
        check_config(load_config("sac_silp", [override]))
    assert error.value.key == key and str(error.value).startswith(f"{key}: ")


def test_every_method_config_passes_the_checks():
    for method in sorted(p.stem for p in (RECIPES / "config" / "method").glob("*.yaml")):
        check_config(load_config("sac_silp", [f"method={method}"]))
    check_config(load_config("ddpg_silp"))


def test_a_resume_into_another_task_s_run_is_refused_by_the_field(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoint").mkdir(parents=True)
    (run_dir / "checkpoint" / "state.pt").write_bytes(b"")
    cfg = load_config("sac_silp", [f"run_dir={run_dir}", "env=panda_reach"])
    OmegaConf.save(load_config("sac_silp", [f"run_dir={run_dir}"]), run_dir / "config.yaml", resolve=True)
    with pytest.raises(ConfigError, match="^env.name: is 'panda_reach' here but 'ur5e_reach' in the run being resumed"):
        check_run_folder(load_config("sac_silp", [f"run_dir={run_dir}", "env=panda_reach", "resume=true"]))
    assert check_run_folder(load_config("sac_silp", [f"run_dir={run_dir}", "resume=true"])) is True
    with pytest.raises(ConfigError, match="^run_dir: .* holds a run's checkpoint"):
        check_run_folder(cfg)


def test_ctrl_c_stops_with_exit_130_a_checkpoint_and_the_resume_command(tmp_path):
    run_dir = tmp_path / "run"
    returncode, out, err = signalled_after_first_checkpoint(tmp_path, run_dir, signal.SIGINT, f"run_dir={run_dir}")
    assert returncode == 130, err[-3000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    last = out.strip().splitlines()[-1]
    assert last.startswith("stopped at ") and last.endswith(f"run_dir={run_dir} resume=true")
    resumed = recipe(tmp_path, *TINY, "collector.total_frames=400", f"run_dir={run_dir}", "resume=must")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert strict_json(run_dir / "summary.json")["frames"] == 400
