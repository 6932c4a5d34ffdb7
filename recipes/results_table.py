"""The quoted evaluations as one Markdown table, read from results/quoted.yaml and the JSONs.

    python recipes/results_table.py                 # print it
    python recipes/results_table.py RESULTS.md      # write it between the file's quoted markers

Success with its 95 % Wilson interval over the trials, completion time (mean ± std over the
successes), the figure the same checkpoint had before the evaluation protocol (development
seed 12345, unpaired) and what backs the row. Nothing is typed by hand.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pnp.training.paired import wilson  # noqa: E402
def row(name: str, meta: dict) -> str:
    r = json.loads((ROOT / "results" / f"{name}.json").read_text())
    lo, hi = wilson(r["success_rate"], r["trials"])
    t = r["completion_time_mean_s"]
    time_s = "-" if t is None else f"{t:.2f} ± {r['completion_time_std_s']:.2f}"
    prev = r.get("previous_evaluation") or {}
    before = "-" if prev.get("success_rate") is None else f"{100 * prev['success_rate']:.1f} %"
    seed = f"{r['seed']}" + ("" if r.get("seed_role") == "reporting" else f" ({r.get('seed_role', 'unlabelled')})")
    return (f"| {meta['task']} | {meta['label']} | **{100 * r['success_rate']:.1f} %** ({100 * lo:.1f}-{100 * hi:.1f}) "
            f"| {time_s} | {before} | {seed} | {meta['backing']} | [{name}.json](results/{name}.json) |")


def table() -> str:
    quoted = yaml.safe_load((ROOT / "results" / "quoted.yaml").read_text())
    head = ("| task | policy | success, 500 paired trials (95 % interval) | completion time (s) | before (seed 12345) "
            "| seed | what backs it | result |\n| --- | --- | --- | --- | --- | --- | --- | --- |")
    return "\n".join([head, *(row(n, m) for n, m in quoted.items())]) + "\n"


BEGIN, END = "<!-- quoted:begin (recipes/results_table.py) -->", "<!-- quoted:end -->"


def write_into(path: Path) -> None:
    text = path.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{path} has no {BEGIN} ... {END} markers")
    head, rest = text.split(BEGIN, 1)
    path.write_text(head + BEGIN + "\n" + table() + rest[rest.index(END):])


if __name__ == "__main__":
    if len(sys.argv) > 1:
        write_into(Path(sys.argv[1]))
    else:
        sys.stdout.write(table())
