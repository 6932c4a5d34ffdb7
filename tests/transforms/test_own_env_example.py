"""Runs the code of docs/guide/own_env.md (the curriculum in your own env), from its markdown source."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import pnp.transforms  # noqa: F401  # pay the torchrl import at collection, not in the test

README = Path(__file__).resolve().parents[2] / "docs" / "guide" / "own_env.md"
TITLE = "# Use the curriculum in your own TorchRL env"


def section(text: str) -> str:
    start = text.index(TITLE)
    end = text.find("\n# ", start + len(TITLE))
    return text[start : end if end >= 0 else None]


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_readme_example_runs(tmp_path, monkeypatch):
    blocks = python_blocks(section(README.read_text()))
    assert len(blocks) == 1
    monkeypatch.chdir(tmp_path)  # the example saves a checkpoint in the working dir
    scope: dict = {"__name__": "readme_example"}
    exec(compile(blocks[0], str(README), "exec"), scope)
    rollout, schedule = scope["rollout"], scope["schedule"]
    assert rollout["next", "agents", "reward"].shape == (4, 100, 2, 1)
    assert rollout["next", "agents", "stage_one_hot"].shape == (4, 100, 2, 3)
    assert schedule.rho.shape == (4, 2, 2)
    assert (tmp_path / "curriculum.pt").exists()
    assert torch.all(schedule.rho >= 0.05)


GYM_TITLE = "# Wrap an existing env"


def test_wrapping_a_gym_env_runs():
    pytest.importorskip("gymnasium")  # in the [test] extra; a bare install of the transforms lacks it
    text = README.read_text()
    blocks = python_blocks(text[text.index(GYM_TITLE):])
    assert len(blocks) == 1
    scope: dict = {"__name__": "gym_example"}
    exec(compile(blocks[0], str(README), "exec"), scope)
    rollout, schedule = scope["rollout"], scope["env"].transform[-1]
    assert rollout["next", "agents", "reward"].shape == (400, 1, 1)
    assert rollout["next", "agents", "stage"].max() <= 2
    done = rollout["next", "done"].view(-1)
    assert int(done.sum()) == 2  # Pendulum's 200-step limit, twice
    assert schedule.pop_stage_histogram().sum() == 2  # both episodes reached Eq. 2
