"""recipes/train.py: rerunning a plain (phase-less) training's command resumes it in place;
the library refuses a fresh start over a run."""
import json
import sys

import pytest

from pnp.training.trainer import train
from tests.training._tiny import ROOT, TINY, compose_cfg

sys.path.insert(0, str(ROOT / "recipes"))
import train as train_recipe  # noqa: E402


def test_rerunning_into_a_run_folder_resumes_it(tmp_path):
    out = tmp_path / "run"
    train(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=1"]))
    cfg = train_recipe.resume_in_place(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=2"]))
    assert cfg.resume == str(out / "checkpoint.pt")
    train(cfg)
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2]  # continued, the first iteration's row kept
    # Called as a library without resume, the Trainer refuses to start over the run.
    with pytest.raises(ValueError, match=r"holds a run \(checkpoint.pt\): resume="):
        train(compose_cfg("train", [*TINY, f"out_dir={out}", "total_iterations=3"]))
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 2


def test_a_fresh_folder_starts_fresh(tmp_path):
    cfg = train_recipe.resume_in_place(compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'new'}"]))
    assert not cfg.resume
