"""recipes/ablation_ee.py end to end at toy size: every run, the JSON and the plots."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[2]
from pnp.studies import ablation_ee

from pnp.training.checkpoint import load_checkpoint  # noqa: E402


def test_ablation_runs_resumes_and_reports(tmp_path):
    overrides = [
        "schedules=[dynamic,liu_min]", "seeds=[0]", "iterations=2", "eval_trials=3", "window=1",
        f"runs_dir={tmp_path / 'runs'}", f"records_dir={tmp_path / 'records'}", f"out={tmp_path / 'ablation.json'}",
    ]
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("ablation_ee", overrides=overrides)
    cfg.variants = {"floor": {"schedule": "dynamic", "overrides": ["curriculum.completed_floor=0.5"]}}
    cfg.train = [
        "experiment=ee_tracking_ablation", "env.num_worlds=4", "env.max_episode_steps=5",
        "collect.frames_per_batch=24", "collect.minibatch_size=12", "collect.num_epochs=1", "model.actor_cells=[16]",
        "model.critic_cells=[16]", "logger.backend=csv", "progress=false",
    ]
    doc = ablation_ee.run_ablation(cfg)
    saved = json.loads((tmp_path / "ablation.json").read_text())
    assert saved["results"].keys() == {"dynamic", "liu_min", "floor"} and saved["backend"] == "kinematic"
    assert saved["methods"]["floor"] == ["curriculum.schedule=dynamic", "curriculum.completed_floor=0.5"]
    floor_cfg = load_checkpoint(tmp_path / "runs" / "floor_s0" / "checkpoint.pt")["cfg"]
    assert floor_cfg["curriculum"]["completed_floor"] == 0.5 and floor_cfg["curriculum"]["schedule"] == "dynamic"
    for method in ("dynamic", "liu_min", "floor"):
        r = saved["results"][method]["seed_0"]
        # A share of 3 trials, with a completion time exactly when something succeeded.
        assert r["trials"] == 3 and r["success_rate"] * 3 == pytest.approx(round(r["success_rate"] * 3))
        assert (r["completion_time_mean_s"] is None) == (r["success_rate"] == 0.0)
        for ev in (r, r["sampled"]):  # deterministic, and the same trials with drawn actions
            assert ev["trials"] == 3 and 0 <= ev["mean_end_stage"] <= 4
            assert ev["success_rate"] == 0.0 or ev["mean_end_stage"] > 0
        assert r["budget"]["iterations"] == 2 and r["budget"]["frames"] == 48
    for key in [*ablation_ee.CURVES, "rho"]:
        assert (tmp_path / f"ablation_ee_{key}.png").stat().st_size > 0
    assert doc["commit"] and doc["command"]
    # A rerun takes the finished runs from their records, even with their run folders gone.
    shutil.rmtree(tmp_path / "runs" / "liu_min_s0")
    again = ablation_ee.run_ablation(cfg)
    assert again["results"]["liu_min"] == saved["results"]["liu_min"]
    assert not (tmp_path / "runs" / "liu_min_s0").exists()
    rows = json.loads((tmp_path / "records" / "dynamic_s0.json").read_text())["record"]["rows"]
    assert [r["iteration"] for r in rows] == [1, 2] and any(k.startswith("rho/") for k in rows[0])
    # A larger budget trains the finished runs on.
    cfg.iterations = 3
    longer = ablation_ee.run_ablation(cfg)
    assert longer["results"]["floor"]["seed_0"]["budget"]["iterations"] == 3


def test_first_majority_and_windows():
    rows = [{"iteration": i, "episodes": 10.0, "stage_share/S4": s, "success_rate": s, "completion_time_s": 5.0}
            for i, s in enumerate([0.0, 0.2, 0.6, 0.4, 0.9], start=1)]
    assert ablation_ee.first_majority_in_final(rows) == 3
    assert ablation_ee.first_majority_in_final(rows[:2]) is None
    shares = [{"iteration": 1, "episodes": 4.0, "stage_share/S0": 0.5, "stage_share/S1": 0.25, "stage_share/S2": 0.25},
              {"iteration": 2, "episodes": 4.0, "stage_share/S0": 0.25, "stage_share/S1": 0.5, "stage_share/S2": 0.25}]
    assert [ablation_ee.first_majority_at_least(shares, k) for k in (1, 2)] == [2, None]
    assert ablation_ee.final_mean(rows, "success_rate", frac=0.4) == 0.65  # iterations 4 and 5
    x, y = ablation_ee.windowed(rows, "success_rate", 2)
    assert list(x[:3]) == [2, 4, 6] and list(y[:3]) == [0.1, 0.5, 0.9]


def test_a_signal_stops_the_whole_ablation(tmp_path, monkeypatch):
    calls = []

    def fake_train(cfg):
        calls.append(cfg.curriculum.schedule)
        return {"stopped_by_signal": True}

    monkeypatch.setattr(ablation_ee, "train", fake_train)
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("ablation_ee", overrides=[f"runs_dir={tmp_path}", f"records_dir={tmp_path / 'rec'}",
                                                f"out={tmp_path / 'a.json'}"])
    with pytest.raises(SystemExit, match="stopped by a signal during dynamic seed 0"):
        ablation_ee.run_ablation(cfg)
    assert calls == ["dynamic"] and not (tmp_path / "a.json").exists()


def test_variants_are_added_and_dropped_from_the_command_line():
    add = "+variants.dynamic_floor={schedule: dynamic, overrides: ['curriculum.completed_floor=0.5']}"
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("ablation_ee", overrides=["schedules=[dynamic,fixed]", add])
        dropped = compose("ablation_ee", overrides=[add, "variants.dynamic_floor=null"])
    assert ablation_ee.methods(cfg) == {"dynamic": ["curriculum.schedule=dynamic"], "fixed": ["curriculum.schedule=fixed"],
                                        "dynamic_floor": ["curriculum.schedule=dynamic", "curriculum.completed_floor=0.5"]}
    assert list(ablation_ee.methods(dropped)) == ["dynamic", "liu_max", "liu_min"]
