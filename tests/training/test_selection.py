"""Checkpoint selection: snapshots as candidates, judged on selection seeds, then evaluated."""
from __future__ import annotations

import json
import shutil

import pytest

from pnp.training.pipeline import run_pipeline
from pnp.training.plots import plot_selection
from pnp.training.selection import candidates, newest_folder, select, selected_checkpoint
from tests.training._tiny import TINY, compose_cfg, tiny_train
from pnp.training import evaluation as evaluate_recipe


def test_candidates_are_the_newest_snapshots_and_the_last_checkpoint(tmp_path):
    run = tmp_path / "run"
    tiny_train(run, "total_iterations=5", "snapshot_every=2")
    assert [(it, p.name) for it, p in candidates(run, 1)] == [(4, "iteration_000004.pt"), (5, "checkpoint.pt")]
    assert [it for it, _ in candidates(run, 5)] == [2, 4, 5]
    assert [(it, p.name) for it, p in candidates(run, 0)] == [(5, "checkpoint.pt")]
    tiny_train(run, "total_iterations=6", "snapshot_every=2", f"resume={run}")  # last checkpoint = newest snapshot
    assert [(it, p.name) for it, p in candidates(run, 1)] == [(6, "iteration_000006.pt")]
    with pytest.raises(ValueError, match="candidates must be >= 0"):
        candidates(run, -1)


def test_a_pipeline_folder_selects_in_its_newest_phase(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no checkpoint.pt"):
        newest_folder(tmp_path / "empty")
    pipe = tmp_path / "pipe"
    for name in ("0_a", "1_b", "2_c"):
        (pipe / name).mkdir(parents=True)
    tiny_train(tmp_path / "src", "total_iterations=1")
    for name in ("0_a", "1_b"):  # 2_c has started nothing yet
        shutil.copy(tmp_path / "src" / "checkpoint.pt", pipe / name / "checkpoint.pt")
    assert newest_folder(pipe) == pipe / "1_b"


def test_selection_then_evaluation_of_the_selected_checkpoint(tmp_path):
    run = tmp_path / "run"
    out = run_pipeline(compose_cfg("train", [
        *TINY, f"out_dir={run}", "snapshot_every=1", "pipeline=[near,far]",
        "++phases={near: {max_frames: 80, overrides: {}}, far: {max_frames: 120, overrides: {}}}"]))
    with pytest.raises(FileNotFoundError, match="select_checkpoint.py"):
        selected_checkpoint(run)
    result = select(run, 2, [1, 2], 4, 4, progress=False, max_episode_steps=5)
    assert [c["iteration"] for c in result["candidates"]] == [2, 3]  # the far phase's
    best = max(result["candidates"], key=lambda c: (c["mean_success"], c["iteration"]))
    for c in result["candidates"]:
        assert set(c["success"]) == set(c["failure_causes"]) == {"1", "2"} and c["mean_success"] == pytest.approx(sum(c["success"].values()) / 2)
        for seed, rows in c["trial_records"].items():  # [trial, success, steps, cause], one per trial
            assert sorted(r[0] for r in rows) == [0, 1, 2, 3]
            assert sum(r[1] for r in rows) / 4 == pytest.approx(c["success"][seed])
    assert result["selected"] == best["checkpoint"] and "1_far" in best["checkpoint"]
    assert json.loads((run / "selection.json").read_text())["selected"] == best["checkpoint"]
    assert selected_checkpoint(run).as_posix() == best["checkpoint"]
    plot_selection(result, tmp_path / "selection.png")
    assert (tmp_path / "selection.png").stat().st_size > 0
    ev = evaluate_recipe.evaluate(compose_cfg("evaluate", [
        f"checkpoint={run}", "selected=true", "trials=4", "env.num_worlds=4", "env.max_episode_steps=5",
        f"out={tmp_path / 'eval.json'}", "progress=false"]))
    assert ev["checkpoint"] == best["checkpoint"] and ev["phases"] == out["phases"]
    assert ev["selection"].endswith("selection.json")
    with pytest.raises(ValueError, match="selected=true judges"):
        evaluate_recipe.evaluate(compose_cfg("evaluate", [f"checkpoint={run}", "selected=true", "phase=near"]))
