"""A comparison's run records: reused while the run's settings hold, across added keys."""
from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

from pnp.studies.run_records import load_record, reuse_or_finish, save_record
from tests.training._tiny import TINY, compose_cfg


def test_a_record_is_reused_while_its_settings_hold_and_a_key_added_since_takes_its_default(tmp_path, capsys):
    cfg = compose_cfg("train", [*TINY, "model.per_stage=erskine", "curriculum.schedule=fixed"])
    path = tmp_path / "erskine_s0.json"
    save_record(path, cfg, {"x": 1})
    assert load_record(path, cfg) == {"x": 1}
    # a record written before `completed_share` existed: reused while the key holds its default
    saved = json.loads(path.read_text())
    del saved["config"]["baseline"]["erskine"]["completed_share"]
    path.write_text(json.dumps(saved))
    assert load_record(path, cfg) == {"x": 1}
    # ... and not once the run asks for another value: that run trains again
    other = OmegaConf.merge(cfg, {"baseline": {"erskine": {"completed_share": 1.0}}})
    assert load_record(path, other) is None
    assert "baseline.erskine.completed_share" in capsys.readouterr().out
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not a run record"):
        load_record(path, cfg)


def test_reuse_or_finish_reruns_only_when_the_evaluation_or_a_check_changed(tmp_path):
    cfg = compose_cfg("train", list(TINY))
    path, calls = tmp_path / "ours_s0.json", []

    def finish(n):
        calls.append(n)
        return {"eval_settings": {"trials": n}, "n": n}

    assert reuse_or_finish(path, cfg, {"trials": 5}, lambda: finish(5))["n"] == 5
    assert reuse_or_finish(path, cfg, {"trials": 5}, lambda: finish(5))["n"] == 5  # kept
    assert reuse_or_finish(path, cfg, {"trials": 9}, lambda: finish(9))["n"] == 9  # another evaluation
    assert reuse_or_finish(path, cfg, {"trials": 9}, lambda: finish(9), holds=lambda k: k["n"] > 9)["n"] == 9
    assert calls == [5, 9, 9] and load_record(path, cfg)["n"] == 9
