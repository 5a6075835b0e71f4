"""The documentation's examples run."""

from __future__ import annotations

import re
from pathlib import Path

import torch

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_your_own_task_example_runs_silp_on_a_new_task(capsys):
    text = (DOCS / "your_own_task.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1
    scope: dict = {}
    exec(compile(blocks[0], "docs/your_own_task.md", "exec"), scope)
    # the planner found demonstrations on the new task and the loss trained on them
    assert len(scope["buffers"].demo_buffer) > 0
    out = scope["out"]
    assert float(out["num_demos"]) > 0 and float(out["bc_mse"]) > 0
    demos = scope["buffers"].demo_buffer.sample(256)
    # every stored demonstration step moves by its action and is one the model lets pass
    model = scope["model"]
    assert bool((demos["action"].abs() <= 1).all())
    moved = demos["next", "joint_position"] - demos["joint_position"]
    assert torch.allclose(moved, demos["action"] * model.action_scale, atol=1e-6)
    keys = model.state_keys
    _, collision, _, _ = model.outcome(demos.select(*keys), demos["next"].select(*keys))
    assert not bool(collision.any())
    printed = capsys.readouterr().out
    assert "demonstration transitions" in printed
    # the single-task rollout runs on the new model too: a path from the task's start, moved by its actions
    episode = scope["episode"]
    steps = int(episode["steps"])
    assert f"one task: {steps} steps" in printed and episode["joint_position"].shape == (steps + 1, 2)
    moved = episode["joint_position"][1:] - episode["joint_position"][:-1]
    assert torch.allclose(moved, episode["action"].clamp(-1, 1) * model.action_scale, atol=1e-6)
