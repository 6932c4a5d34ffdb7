"""Rerunning a plain (phase-less) training's command resumes it in place (what recipes/train.py
does); the library refuses a fresh start over a run, and a command with other settings."""
import json

import pytest

from pnp.training.trainer import resume_in_place, train
from tests.training._tiny import TINY, compose_cfg


def test_rerunning_into_a_run_folder_resumes_it(tmp_path):
    out = tmp_path / "run"
    train(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=1"]))
    cfg = resume_in_place(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=2"]))
    assert cfg.resume == str(out / "checkpoint.pt")
    train(cfg)
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2]  # continued, the first iteration's row kept
    # Called as a library without resume, the Trainer refuses to start over the run.
    with pytest.raises(ValueError, match=r"holds a run \(checkpoint.pt\): resume="):
        train(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=3"]))
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 2


def test_a_fresh_folder_starts_fresh(tmp_path):
    cfg = resume_in_place(compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'new'}"]))
    assert not cfg.resume


def test_a_folder_holds_one_run(tmp_path):
    """Launching into another run's folder with other settings refuses, naming the keys (a
    resume would run that run's settings and silently ignore these)."""
    out = tmp_path / "run"
    train(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=1"]))
    other = compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=2", "seed=7", "optim.lr=0.00042"])
    with pytest.raises(ValueError, match=r"other settings .*'optim.lr': \(0.001, 0.00042\), 'seed': \(0, 7\)"):
        resume_in_place(other)
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 1
