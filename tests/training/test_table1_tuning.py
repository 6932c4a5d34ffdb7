"""Table I's equal tuning: every method tries the same candidates on selection trials, and
its reported seeds train the one chosen."""
from __future__ import annotations

import pytest

from pnp.studies import table1
from pnp.training.pipeline import load_state
from tests.training.test_baselines import _table1_cfg

PHASES = ("pipeline=[kin]", "++phases={kin: {max_frames: 40}}")


def _tuned(tmp_path, candidates):
    cfg = _table1_cfg(tmp_path, "[dynamic,liu_max]", "[0]", *PHASES)
    cfg.mujoco_seeds = []
    cfg.tuning.candidates = candidates
    cfg.tuning.eval.update({"trials": 3, "num_worlds": 3, "max_episode_steps": 5})
    return cfg


def test_each_method_tries_the_same_candidates_and_its_seeds_train_the_chosen_one(tmp_path):
    candidates = {"as_built": {}, "calm": {"kin": {"loss.entropy_coeff": 0.0, "optim.desired_kl": 0.005}}}
    doc = table1.run_table1(_tuned(tmp_path, candidates))
    for method in ("dynamic", "liu_max"):
        tuning = doc["methods"][method]["tuning"]
        assert tuning["configs_tried"] == 2 and tuning["chosen_on"] == "selection seeds"
        assert (tuning["selection_seed"], tuning["training_seed"]) == (777, 100)
        assert tuning["candidates"]["calm"]["overrides"] == candidates["calm"]
        tried = tuning["candidates"]
        best = max(tried, key=lambda n: (tried[n]["success_rate"], tried[n]["mean_end_stage"]))
        assert tuning["chosen"] == best
        # the candidate's overrides reached its phase; the reported seed trained the choice
        calm = load_state(tmp_path / "runs" / "tuning" / f"{method}_calm_s100")[0]["overrides"]
        assert calm["loss.entropy_coeff"] == 0.0 and calm["optim.desired_kl"] == 0.005
        reported = tmp_path / "runs" / table1.run_name(method, best, 0)
        assert [p["name"] for p in load_state(reported)] == ["kin"]
    assert "- Liu et al. (max): chose" in (tmp_path / "table1.md").read_text()


def test_tuning_refuses_a_reported_seed_a_non_selection_seed_and_an_unknown_phase(tmp_path):
    cfg = _tuned(tmp_path, {"as_built": {}, "other": {"kin": {"loss.entropy_coeff": 0.0}}})
    cfg.tuning.seed = 0
    with pytest.raises(ValueError, match="tuning.seed=0 is one of the reported seeds"):
        table1.run_table1(cfg)
    cfg.tuning.seed, cfg.tuning.eval.seed = 100, 12345
    with pytest.raises(ValueError, match="tuning.eval.seed=12345 is not a selection seed"):
        table1.run_table1(cfg)
    cfg.tuning.eval.seed, cfg.tuning.candidates = 777, {"as_built": {}, "x": {"mujoco": {"loss.entropy_coeff": 0.0}}}
    with pytest.raises(ValueError, match="phase 'mujoco' is not in the pipeline"):
        table1.run_table1(cfg)
    cfg.tuning.candidates = {"other": {}}
    with pytest.raises(ValueError, match="must start with 'as_built'"):
        table1.run_table1(cfg)
