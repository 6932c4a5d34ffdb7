"""The regression detector of recipes/analyze/stage_progression.py on a synthetic curve, and
the script end to end on a tiny synthetic metrics.jsonl."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
from pnp.analysis import stage_progression


def _curve() -> tuple[np.ndarray, np.ndarray]:
    """A clean rise to 0.8, a dip of 0.3 that recovers, a 0.05 wiggle, a final drop of 0.4."""
    x = np.arange(500)
    y = np.minimum(x / 100, 1.0) * 0.8
    y[150:250] -= 0.3 * np.sin(np.linspace(0, np.pi, 100))
    y[300:320] -= 0.05 * np.sin(np.linspace(0, np.pi, 20))
    y[400:] -= np.minimum((x[400:] - 400) / 20, 1.0) * 0.4
    return x, y


def test_detects_the_dip_and_the_final_drop_only():
    x, y = _curve()
    y[50] = math.nan  # iterations with no ended episode are skipped
    dip, drop = stage_progression.find_regressions(x, y, min_drop=0.1, recover=0.03, stage=2)
    assert 150 < dip.start_iteration < dip.trough_iteration < dip.end_iteration < 250
    assert abs(dip.trough_iteration - 199.5) <= 1
    assert dip.depth == pytest.approx(0.3, abs=1e-3) and dip.recovered and dip.stage == 2
    assert 400 < drop.start_iteration < 420 and drop.end_iteration == 499
    assert drop.depth == pytest.approx(0.4) and not drop.recovered


def test_small_wiggle_and_rise_are_not_regressions():
    x, y = _curve()
    assert stage_progression.find_regressions(x[:400], y[:400], min_drop=0.1, recover=0.03)[1:] == []
    assert stage_progression.find_regressions(x[:150], y[:150]) == []
    with pytest.raises(ValueError):
        stage_progression.find_regressions(x, y, min_drop=0.05, recover=0.1)


def _write_run(path: Path, reached: list[float]) -> None:
    """One row per iteration; every third iteration no episode ends (shares NaN)."""
    rows = []
    for i, p in enumerate(reached, start=1):
        ended = 0 if i % 3 == 0 else 10
        shares = [1 - p, p, 0.0] if ended else [math.nan] * 3
        rows.append({"iteration": i, "episodes": ended, **{f"stage_share/S{k}": v for k, v in enumerate(shares)}})
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_main_writes_png_and_json_with_the_regression(tmp_path):
    # S0's share falls, rises again in the second run (S1+ share 0.9 -> 0.4), then recovers
    _write_run(tmp_path / "a.jsonl", [0.1, 0.5, 0.9, 0.9, 0.9, 0.9])
    _write_run(tmp_path / "b.jsonl", [0.9, 0.9, 0.9, 0.4, 0.4, 0.4, 0.4, 0.9, 0.9, 0.9])
    out = stage_progression.main([str(tmp_path / "fig"), str(tmp_path / "a.jsonl"), str(tmp_path / "b.jsonl"),
                                  "--window", "1"])
    assert (tmp_path / "fig.png").stat().st_size > 0
    saved = json.loads((tmp_path / "fig.json").read_text())
    assert saved == json.loads(json.dumps(out))
    assert [inp["offset"] for inp in saved["inputs"]] == [0, 6] and saved["inputs"][1]["last_iteration"] == 16
    (only,) = saved["intervals"]
    assert only["label"] == "A" and only["stages"] == ["S1+"] and only["recovered"] and not only["at_restart"]
    assert (only["start_iteration"], only["end_iteration"]) == (10, 14)  # iteration 12 has no episodes
    assert only["max_depth"] == pytest.approx(0.5)
    assert saved["regressions"][0]["series"] == "share reaching S1 or later"
    assert saved["options"]["window"] == 1 and saved["commit"] and saved["machine"]
