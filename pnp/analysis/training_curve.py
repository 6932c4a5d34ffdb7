"""A training run's curve as a table: per window of iterations, training success and the share
of episodes ending in S0 (both weighted by episode counts, as the pipeline's exit rules are),
with the PPO step's KL, learning rate, clip fraction and explained variance averaged.

    python recipes/analyze/training_curve.py metrics=runs/main/5_mujoco_sharp/metrics.jsonl window=100

``metrics`` is a phase's ``metrics.jsonl`` or a run's ``pipeline_metrics.jsonl`` (windows then
stop at phase boundaries). Prints a Markdown table; ``out=...json`` also saves the rows.
"""
from __future__ import annotations

import json
import math
from pathlib import Path


from pnp.training.collect import windowed_mean

from pnp.analysis.analysis_cli import save, settings

DEFAULTS = {"metrics": None, "window": 100, "out": None}
USAGE = __doc__
AVERAGED = {"kl": "train/kl", "lr": "train/lr", "clip": "train/clip_fraction", "ev": "train/explained_variance"}


def _mean(rows: list[dict], key: str) -> float:
    vals = [r[key] for r in rows if key in r and math.isfinite(r[key])]
    return sum(vals) / len(vals) if vals else math.nan


def windows(rows: list[dict], window: int) -> list[dict]:
    """One summary per ``window`` consecutive rows of one phase (the last may be shorter)."""
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    chunks, current = [], []
    for row in rows:
        if current and (len(current) == window or row.get("phase") != current[-1].get("phase")):
            chunks.append(current)
            current = []
        current.append(row)
    if current:
        chunks.append(current)
    out = []
    for c in chunks:
        summary = {"phase": c[0].get("phase"), "first": c[0]["iteration"], "last": c[-1]["iteration"],
                   "frames": c[-1]["frames"], "episodes": sum(r.get("episodes", 0) for r in c),
                   "success": windowed_mean(c, "success_rate", len(c)),
                   "end_s0": windowed_mean(c, "final_stage_share/S0", len(c))}
        summary.update({name: _mean(c, key) for name, key in AVERAGED.items()})
        out.append(summary)
    return out


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, float) and not v.is_integer():
        return f"{v:.3g}"
    return str(int(v)) if isinstance(v, float) else str(v)


def table(summaries: list[dict]) -> str:
    cols = ["phase", "first", "last", "frames", "episodes", "success", "end_s0", *AVERAGED]
    lines = ["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
    lines += ["| " + " | ".join(_fmt(s[c]) for c in cols) + " |" for s in summaries]
    return "\n".join(lines)


def main(argv: list[str]) -> list[dict]:
    cfg = settings(argv, DEFAULTS, USAGE, required=("metrics",))
    path = Path(cfg.metrics)
    if not path.is_file():
        raise SystemExit(f"metrics={path}: no such file (a phase's metrics.jsonl or a run's pipeline_metrics.jsonl)")
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    summaries = windows(rows, int(cfg.window))
    print(table(summaries))
    if cfg.out is not None:
        save({"metrics": str(path), "window": int(cfg.window), "windows": summaries}, cfg.out)
    return summaries
