"""The documentation's examples run, in order, and do what the text says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.fixture(scope="module")
def blocks():
    """docs/your_own_task.md's python blocks run in one scope, in order: after each, a snapshot of the
    names it left, what it printed, and the demo buffer's size."""
    text = (DOCS / "your_own_task.md").read_text()
    code = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(code) == 3
    scope: dict = {}
    printed: list[str] = []
    snapshots = []
    for i, block in enumerate(code):
        scope["print"] = lambda *a, **k: printed.append(" ".join(map(str, a)))
        exec(compile(block, f"docs/your_own_task.md[{i}]", "exec"), scope)
        demo_buffer = getattr(scope.get("buffers"), "demo_buffer", None)
        snapshots.append({**scope, "_printed": list(printed), "_demos": len(demo_buffer) if demo_buffer is not None else 0})
        printed.clear()
    return snapshots


def test_the_point_robot_trains_on_planned_demonstrations(blocks):
    scope = blocks[0]
    model, out = scope["model"], scope["out"]
    assert float(out["num_demos"]) > 0 and float(out["bc_mse"]) > 0
    demos = scope["buffers"].demo_buffer.sample(256)
    # every stored demonstration step moves by its action and is one the model lets pass
    assert bool((demos["action"].abs() <= 1).all())
    moved = demos["next", "joint_position"] - demos["joint_position"]
    assert torch.allclose(moved, demos["action"] * model.action_scale, atol=1e-6)
    keys = model.state_keys
    _, collision, _, _ = model.outcome(demos.select(*keys), demos["next"].select(*keys))
    assert not bool(collision.any())
    assert f"{scope['_demos']} demonstration transitions" in scope["_printed"][0]
    # the single-task rollout runs on the new model too: a path from the task's start, moved by its actions
    episode = scope["episode"]
    steps = int(episode["steps"])
    assert f"one task: {steps} steps" in scope["_printed"][1]
    assert episode["joint_position"].shape == (steps + 1, 2)
    moved = episode["joint_position"][1:] - episode["joint_position"][:-1]
    assert torch.allclose(moved, episode["action"].clamp(-1, 1) * model.action_scale, atol=1e-6)


def test_the_collector_loop_plans_whole_episodes_and_keeps_the_rest(blocks):
    scope = blocks[1]
    # 4 batches of 30 steps of 16 envs: 120 steps per env, two whole 50-step episodes each and 20 steps pending
    assert scope["assembler"].num_pending == 16 * 20
    assert scope["_printed"] == [f"{16 * 20} transitions wait for their episodes to finish"]
    assert scope["_demos"] > blocks[0]["_demos"]


def test_silp_loss_and_mixed_replay_without_a_task_model(blocks):
    scope = blocks[2]
    out, buffers = scope["out"], scope["buffers"]
    # exactly N_D = 0.25 * 128 demonstrations in each batch, and the BC term computed on them
    assert int(out["num_demos"]) == 32
    batch = buffers.sample()
    assert int(batch["is_demo"].sum()) == 32 and batch.batch_size == (128,)
    demos = batch[batch["is_demo"].squeeze(-1)]
    # the demonstrations are the swing-up controller's actions on their states
    replayed = scope["swing_up"](demos.select("observation").clone())
    torch.testing.assert_close(replayed["action"], demos["action"])
    assert torch.isfinite(out["loss_bc"]) and float(out["loss_bc"].detach()) > 0
    assert len(buffers.interaction_buffer) == 2 * 200


def test_the_urdf_commands_run_as_written(tmp_path):
    """docs/your_own_task.md's "your robot from its URDF" commands: the check runs (smaller), the training
    command composes to the UR10 task, and the picture is drawn."""
    import shlex
    import subprocess
    import sys

    from torchrl_silp.recipes.preflight import compose_command_line

    text = (DOCS / "your_own_task.md").read_text()
    section = text.split("## Your robot from its URDF")[1].split("\n## ")[0]
    commands = [" ".join(c.replace("\\\n", " ").split()) for c in re.findall(r"```bash\n(.*?)```", section, flags=re.S)]
    assert len(commands) == 3
    check = shlex.split(commands[0])
    assert check[:2] == ["python", "recipes/robot_check.py"]
    done = subprocess.run([sys.executable, str(DOCS.parent / check[1]), *check[2:], "--configs", "50"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "missed 0" in done.stdout and (tmp_path / "ur10_cover.png").stat().st_size > 10_000
    train = shlex.split(commands[1])
    assert train[:2] == ["python", "recipes/sac_silp.py"]
    cfg = compose_command_line("sac_silp", train[2:])
    assert cfg.env.name == "urdf_reach" and cfg.env.robot.ee_link == "tool0" and cfg.run_dir.startswith("runs/ur10_robot/")
    assert list(cfg.env.robot.joints) == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]
    # the third: urdf_reach.yaml copied into a folder of the user's, filled in
    template = (DOCS.parent / "recipes" / "config" / "env" / "urdf_reach.yaml").read_text()
    filled = (template.replace("urdf_path: ???", f"urdf_path: {cfg.env.robot.urdf_path}")
              .replace("joints: ???", "joints: [shoulder_pan_joint, shoulder_lift_joint, elbow_joint]")
              .replace("ee_link: ???", "ee_link: tool0"))
    (tmp_path / "myconfigs" / "env").mkdir(parents=True)
    (tmp_path / "myconfigs" / "env" / "ur10.yaml").write_text(filled)
    own = shlex.split(commands[2])
    assert own[2:] == ["--config-dir", "myconfigs", "env=ur10"]
    mine = compose_command_line("sac_silp", ["--config-dir", str(tmp_path / "myconfigs"), "env=ur10"])
    assert mine.env.robot == cfg.env.robot and mine.env.model == cfg.env.model
