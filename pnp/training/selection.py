"""Checkpoint selection on seeds other than the reporting one.

The candidates are a run's newest snapshots (``snapshot_every``) and its last checkpoint;
each is judged by deterministic trials on the selection seeds, and the one with the highest
mean success is chosen (ties: the later iteration). The reporting seed's trials then judge
only the chosen one. A pipeline folder's candidates come from its newest phase.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pnp.training.checkpoint import load_checkpoint
from pnp.training.paired import trial_table
from pnp.training.provenance import provenance
from pnp.training.rollout import load_policy, run_trials, summarise

SELECTION = "selection.json"
_PHASE = re.compile(r"^(\d+)_")
_SNAPSHOT = re.compile(r"^iteration_(\d+)\.pt$")


def newest_folder(run: Path) -> Path:
    """``run`` itself, or for a pipeline folder its newest phase's folder (one with a checkpoint)."""
    run = Path(run)
    phases = [(int(m.group(1)), p) for p in run.iterdir() if p.is_dir() and (m := _PHASE.match(p.name))
              and (p / "checkpoint.pt").is_file()] if run.is_dir() else []
    if phases:
        return max(phases)[1]
    if not (run / "checkpoint.pt").is_file():
        raise FileNotFoundError(f"{run} holds no checkpoint.pt and no pipeline phase folder with one")
    return run


def candidates(run: Path, newest: int) -> list[tuple[int, Path]]:
    """``(iteration, path)`` of the ``newest`` snapshots of ``run`` and its last checkpoint, by iteration."""
    if newest < 0:
        raise ValueError(f"candidates must be >= 0, got {newest}")
    folder = newest_folder(run)
    snaps = sorted((int(m.group(1)), p) for p in (folder / "snapshots").glob("iteration_*.pt")
                   if (m := _SNAPSHOT.match(p.name)))
    chosen = snaps[len(snaps) - newest:] if newest else []
    last = folder / "checkpoint.pt"
    last_it = int(load_checkpoint(last)["counters"]["iteration"])
    if last_it not in {it for it, _ in chosen}:
        chosen.append((last_it, last))
    return sorted(chosen)


def select(run: Path, newest: int, seeds: list[int], trials: int, num_worlds: int, progress: bool = True,
           **env_overrides) -> dict:
    """Judge ``candidates(run, newest)`` on ``seeds`` (``trials`` each); writes and returns
    ``run/selection.json`` with every candidate's success per seed and the ``selected`` path."""
    if not seeds:
        raise ValueError("selection needs at least one seed")
    cands = candidates(run, newest)
    rows = []
    bar = tqdm(total=len(cands) * len(seeds), disable=not progress, desc="selection")
    for iteration, path in cands:
        success, causes, records = {}, {}, {}
        for seed in seeds:
            pol = load_policy(path, min(int(num_worlds), int(trials)), int(seed), **env_overrides)
            trial_records = run_trials(pol.env, pol.actor, int(trials))
            summary = summarise(trial_records)
            pol.env.close()
            success[str(seed)], causes[str(seed)] = summary["success_rate"], summary["failure_causes"]
            # Per trial, so that a later A/B on these seeds pairs with a candidate without re-running it.
            records[str(seed)] = trial_table(trial_records)
            bar.update(1)
            bar.set_postfix(iteration=iteration, success=f"{success[str(seed)]:.3f}")
        rows.append({"iteration": iteration, "checkpoint": str(path), "success": success,
                     "mean_success": float(np.mean(list(success.values()))), "failure_causes": causes,
                     "trial_records": records})
    bar.close()
    best = max(rows, key=lambda r: (r["mean_success"], r["iteration"]))
    result = {"run": str(run), "seeds": [int(s) for s in seeds], "trials": int(trials), "candidates": rows,
              "selected": best["checkpoint"], "selected_iteration": best["iteration"], **provenance()}
    (Path(run) / SELECTION).write_text(json.dumps(result, indent=1) + "\n")
    return result


def selected_checkpoint(run: Path) -> Path:
    """The checkpoint :func:`select` chose for ``run``."""
    path = Path(run) / SELECTION
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: run `python recipes/select_checkpoint.py run={run}` first")
    return Path(json.loads(path.read_text())["selected"])
