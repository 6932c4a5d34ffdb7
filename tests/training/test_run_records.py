"""A comparison's run records: reused while the run's settings hold, across added keys."""
from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

from pnp.training.run_records import load_record, save_record
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
