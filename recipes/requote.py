"""Every quoted evaluation re-run at HEAD on the reporting seed, 500 paired trials each.

    python recipes/requote.py                      # all rows below, one after another
    python recipes/requote.py eval_single_pnp repro_dual_pnp   # some of them

Each row of ``results/quoted.yaml`` runs ``recipes/evaluate.py`` (or ``evaluate_student.py``)
on a committed checkpoint into ``results/<name>.json``. What the evaluation does not produce (a pipeline's phases and
cost, its selection, notes) is carried over from the committed file, and that file's former
figure is kept under ``previous_evaluation`` so that the move is visible. The reporting seed
(``pnp.training.protocol``) is for quoting only: see docs/guide/evaluation.md.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pnp.training.protocol import REPORTING_SEED  # noqa: E402

QUOTED = ROOT / "results" / "quoted.yaml"  # name: recipe, checkpoint, experiment, overrides
ROWS = yaml.safe_load(QUOTED.read_text())
# What previous_evaluation keeps of the committed file; the rest of that file (a pipeline's
# phases, selection, notes) is carried over where the new evaluation does not write it.
HEADLINE = ("seed", "trials", "success_rate", "completion_time_mean_s", "completion_time_std_s", "failure_causes",
            "commit", "date_utc", "command", "num_worlds")


UNRECORDED = "not recorded when written (before the evaluation protocol of 2026-12-03)"


def label_dirty(doc: dict) -> dict:
    """Give every ``-dirty`` commit the document carries over (its former figure, its training
    launches) a ``dirty_reason``: what the file says about it, else that nobody recorded one."""
    prev = doc.get("previous_evaluation") or {}
    if str(prev.get("commit", "")).endswith("-dirty") and "dirty_reason" not in prev:
        prev["dirty_reason"] = UNRECORDED
    note = doc.get("launch_note")
    for launch in doc.get("training_launches", []):
        if str(launch.get("commit", "")).endswith("-dirty") and "dirty_reason" not in launch:
            launch["dirty_reason"] = f"{UNRECORDED}; the result's launch_note: {note}" if note else UNRECORDED
    return doc


def same_checkpoint(old: dict, new: dict) -> bool:
    """Whether two evaluations are of the same checkpoint (iteration, frames, configuration)."""
    keys = ("checkpoint_iteration", "checkpoint_frames", "config_sha")
    return all(old.get(k) == new.get(k) for k in keys if k in old)


def requote(name: str) -> dict:
    row = ROWS[name]
    recipe, checkpoint, experiment, extra = row["recipe"], row["checkpoint"], row["experiment"], row.get("overrides", [])
    out = ROOT / "results" / f"{name}.json"
    old = json.loads(out.read_text()) if out.exists() else {}
    cmd = [sys.executable, f"recipes/{recipe}.py", f"checkpoint={checkpoint}", f"seed={REPORTING_SEED}",
           "trials=500", "env.num_worlds=100", "progress=false", f"out=results/{name}.json", *extra]
    t0 = time.monotonic()
    subprocess.run(cmd, cwd=ROOT, check=True)
    new = json.loads(out.read_text())
    if new.get("experiment") not in (None, experiment.split(":")[-1]):  # renamed or merged since its launch
        new["launched_experiment"] = new["experiment"]
    # The experiment that composes to the checkpoint's configuration today (test_quoted_configs.py);
    # distill:<name> is a distill_experiment.
    new["experiment"] = experiment
    if old and not same_checkpoint(old, new):  # another checkpoint: nothing of its file describes this one
        new["replaced_evaluation"] = {**{k: old.get(k) for k in HEADLINE},
                                      **{k: old.get(k) for k in ("checkpoint_iteration", "config_sha", "notes")}}
        old = {}
        print(f"{name}: a new checkpoint; its former file is kept under replaced_evaluation, write its notes", flush=True)
    carried = {k: v for k, v in old.items() if k not in new and k != "previous_evaluation"}
    if "previous_evaluation" not in old and old:
        carried["previous_evaluation"] = {k: old.get(k) for k in HEADLINE}
        if "dirty_reason" in old:
            carried["previous_evaluation"]["dirty_reason"] = old["dirty_reason"]
    else:
        carried["previous_evaluation"] = old.get("previous_evaluation")
    new.update(carried)
    label_dirty(new)
    out.write_text(json.dumps(new, indent=2) + "\n")
    print(f"{name}: {100 * new['success_rate']:.1f} % (was {100 * old.get('success_rate', float('nan')):.1f} % "
          f"on seed {old.get('seed')}), {time.monotonic() - t0:.0f} s", flush=True)
    return new


def main(names: list[str]) -> None:
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        raise SystemExit(f"unknown rows {unknown}; known: {list(ROWS)}")
    for name in names or list(ROWS):
        requote(name)


if __name__ == "__main__":
    main(sys.argv[1:])
