"""A finished run's summary kept apart from its run folder (a comparison's per-run record).

Run folders live under ``runs/`` and are not committed; a comparison that spans several
sessions (``recipes/table1.py``: 15 runs, ~12 CPU-h here) would lose every finished run
with them. Each finished run's record (its metric rows, evaluations, efficiency) is written
as JSON with the configuration it ran, and is reused only while that configuration is
unchanged; a record of another configuration is ignored (the run trains again).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from omegaconf import DictConfig, OmegaConf

from pnp.training.migration import changed_settings, migrate
from pnp.training.trainer import RESUMABLE

# The rows' columns a comparison reads (curves, thresholds, Bendikas' sub-task ends).
ROW_KEYS = ("iteration", "frames", "wall_s", "phase", "episodes", "end_stage", "success_rate", "subtask",
            "subtask_exit")


def compact(rows: list[dict], keys: tuple[str, ...] = ROW_KEYS, prefixes: tuple[str, ...] = (),
            digits: int | None = None) -> list[dict]:
    """Each row's ``keys`` and keys starting with one of ``prefixes``; floats rounded to
    ``digits`` significant digits when given (curves only: a record stays small)."""
    def value(v):
        return float(f"{v:.{digits}g}") if digits is not None and isinstance(v, float) else v

    return [{k: value(v) for k, v in r.items() if k in keys or k.startswith(prefixes)} for r in rows]


def load_record(path: Path, cfg: DictConfig) -> dict | None:
    """The record at ``path`` if it was written by a run of ``cfg`` (settings a resume may
    change aside), else ``None``; a file that is not a record raises, naming it."""
    if not path.is_file():
        return None
    try:
        saved = json.loads(path.read_text())
        then = migrate(saved["config"])  # keys added since hold their defaults
        payload = saved["record"]
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a run record ({err!r}); move it away to retrain that run") from err
    changed = changed_settings(cfg, then, RESUMABLE)
    if changed:
        print(f"{path}: recorded for other settings ({sorted(changed)[:5]}), ignored: the run trains")
        return None
    return payload


def save_record(path: Path, cfg: DictConfig, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"config": OmegaConf.to_container(cfg, resolve=True), "record": payload}) + "\n")
    tmp.replace(path)  # a stop mid-write leaves the old record or none, never half of one


def reuse_or_finish(path: Path, cfg: DictConfig, eval_settings: dict, finish: Callable[[], dict],
                    holds: Callable[[dict], bool] = lambda payload: True) -> dict:
    """The record at ``path`` while it was written by a run of ``cfg`` evaluated under
    ``eval_settings`` (and ``holds`` of it), else ``finish()``'s payload, saved there first.
    Payloads carry their ``eval_settings``: an evaluation setting changes no training key."""
    kept = load_record(path, cfg)
    if kept is None or kept.get("eval_settings") != eval_settings or not holds(kept):
        kept = finish()
        save_record(path, cfg, kept)
    return kept
