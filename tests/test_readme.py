"""README.md: its quickstart runs and trains on planned demonstrations; it reads as a README."""

from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def _text() -> str:
    return README.read_text()


def test_quickstart_plans_valid_demonstrations_and_trains_on_them(capsys):
    blocks = re.findall(r"```python\n(.*?)```", _text(), flags=re.S)
    assert len(blocks) == 1
    scope: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), scope)
    demo_buffer = scope["buffers"].demo_buffer
    printed = capsys.readouterr().out
    assert f"{len(demo_buffer)} demonstration transitions" in printed and len(demo_buffer) > 0
    # the demonstrations are motions the task model lets pass, moved by their own actions
    model = scope["model"]
    demos = demo_buffer.sample(512)
    moved = demos["next", model.config_key] - demos[model.config_key]
    torch.testing.assert_close(moved, model.next_config(demos[model.config_key], demos["action"]) - demos[model.config_key])
    keys = model.state_keys
    _, collision, _, _ = model.outcome(demos.select(*keys), demos["next"].select(*keys))
    assert not bool(collision.any())
    # the last update mixed demonstrations into the batch and the BC term saw them
    out = scope["out"]
    assert float(out["num_demos"]) > 0 and torch.isfinite(out["loss_bc"]).all()


def test_readme_is_short_and_undated():
    text = _text()
    assert len(text.splitlines()) <= 150
    prose = [p for p in re.split(r"\n\s*\n", re.sub(r"```.*?```", "", text, flags=re.S)) if not p.lstrip().startswith("|")]
    assert max(len(p) for p in prose) <= 1200
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text)


def test_the_two_fresh_machine_commands_come_first():
    blocks = re.findall(r"```bash\n(.*?)```", _text(), flags=re.S)
    train, tests = blocks[0].strip(), blocks[1].strip()
    for command in (train, tests):
        assert command.startswith("python3 -m venv .venv") and "pip install torch==2.13.0" in command
    assert train.endswith("python recipes/sac_silp.py")
    assert 'python -m pytest -q -m "not slow"' in tests
