"""Share of episodes in each stage over training (the paper's Fig. 5), with curriculum
regressions detected and shaded.

    python recipes/analyze/stage_progression.py results/stage_progression_dual \\
        results/train_dual/dual_mj1/metrics.jsonl results/train_dual/dual_mj2/metrics.jsonl

Several metrics files are one consecutive run (each continues from the previous one's last
checkpoint): each file's iterations are offset by the previous file's last iteration and the
boundaries are marked. Episodes end in bursts, so every share is an episode-weighted mean
over a centred window of ``--window`` iterations.

A *regression* is read off the share of episodes that reached stage k or later (k >= 1):
that share falls at least ``--min-drop`` below its running maximum and later comes back to
within ``--recover`` of it (or the run ends first). Overlapping regressions of several k
are shaded as one interval, labelled A, B, C, ...

Writes OUT_PREFIX.png (stacked shares above, the reached-stage-k shares below) and
OUT_PREFIX.json (the regressions, inputs, options and provenance).
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import string
import time
from pathlib import Path
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pnp.training.plots import load_metrics  # noqa: E402
from pnp.training.provenance import provenance  # noqa: E402


class Regression(NamedTuple):
    """An interval where a series stayed more than ``recover`` below its running maximum
    and went at least ``min_drop`` below it."""
    start_iteration: float  # first iteration more than ``recover`` below the peak
    end_iteration: float  # first iteration back within ``recover`` (the last one if never)
    depth: float  # peak minus the lowest value inside the interval
    stage: int | None  # which series: share of episodes that reached this stage or later
    trough_iteration: float
    recovered: bool


def find_regressions(iterations, series, min_drop: float = 0.1, recover: float = 0.05,
                     stage: int | None = None) -> list[Regression]:
    """Regressions of a 1-D ``series`` sampled at ``iterations``; NaNs are skipped.

    Walk the series keeping its running maximum (the peak). Once the series falls more
    than ``recover`` below the peak, an excursion starts; it ends at the first sample back
    within ``recover`` of that peak, or at the last sample (``recovered=False``). An
    excursion is a regression when its depth (peak minus its minimum) is >= ``min_drop``.
    """
    if not 0 <= recover < min_drop:
        raise ValueError(f"need 0 <= recover < min_drop, got recover={recover}, min_drop={min_drop}")
    x, y = np.asarray(iterations, dtype=float), np.asarray(series, dtype=float)
    ok = np.isfinite(y)
    x, y = x[ok], y[ok]
    out, peak, start = [], -math.inf, None
    trough = trough_x = math.nan
    for xi, yi in zip(x, y):
        if start is None:
            if yi >= peak - recover:
                peak = max(peak, yi)
                continue
            start, trough, trough_x = xi, yi, xi  # left the band below the peak
        elif yi >= peak - recover:  # back near the peak: the excursion is over
            if peak - trough >= min_drop:
                out.append(Regression(float(start), float(xi), float(peak - trough), stage, float(trough_x), True))
            start, peak = None, max(peak, yi)
            continue
        if yi < trough:
            trough, trough_x = yi, xi
    if start is not None and peak - trough >= min_drop:  # the run ended inside the excursion
        out.append(Regression(float(start), float(x[-1]), float(peak - trough), stage, float(trough_x), False))
    return out


def load_runs(paths: list[str | Path]) -> tuple[list[dict], list[dict]]:
    """Rows of consecutive runs on one iteration axis, and per input file its offset and
    iteration range (offset = the previous files' last iterations, summed)."""
    rows, inputs, offset = [], [], 0
    for path in paths:
        part = load_metrics(path)
        if not part:
            raise SystemExit(f"{path}: no rows")
        rows += [{**r, "iteration": r["iteration"] + offset} for r in part]
        inputs.append({"path": str(path), "rows": len(part), "offset": offset,
                       "first_iteration": part[0]["iteration"] + offset,
                       "last_iteration": part[-1]["iteration"] + offset})
        offset += part[-1]["iteration"]
    return rows, inputs


def stage_keys(rows: list[dict]) -> list[str]:
    keys = {k for r in rows for k in r if k.startswith("stage_share/S")}
    return sorted(keys, key=lambda k: int(k.split("S")[-1]))


def smooth(episodes: np.ndarray, values: np.ndarray, window: int) -> np.ndarray:
    """Episode-weighted means of ``values`` (shape [..., iterations]) over centred windows
    of ``window`` iterations; NaN where the window holds no ended episode."""
    weight = np.where(np.isfinite(values) & (np.nan_to_num(episodes) > 0), np.nan_to_num(episodes), 0.0)
    weight = np.broadcast_to(weight, values.shape)
    num, den = _window_sum(weight * np.nan_to_num(values), window), _window_sum(weight, window)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def _window_sum(a: np.ndarray, window: int) -> np.ndarray:
    return np.apply_along_axis(np.convolve, -1, a, np.ones(max(1, window)), mode="same")


def progression(rows: list[dict], inputs: list[dict], window: int, min_drop: float, recover: float) -> dict:
    """Smoothed stage shares, reached-stage-k shares and their regressions."""
    keys = stage_keys(rows)
    if not keys:
        raise SystemExit("no stage_share/S* columns in the metrics")
    it = np.array([r["iteration"] for r in rows], dtype=float)
    eps = np.array([r.get("episodes", math.nan) for r in rows], dtype=float)
    raw = np.array([[r.get(k, math.nan) for r in rows] for k in keys], dtype=float)
    # each run smoothed on its own: a window across a restart would smear the restart's
    # first (short, low-stage) episodes back into the previous run
    cuts = np.cumsum([0] + [inp["rows"] for inp in inputs])
    shares = np.concatenate([smooth(eps[a:b], raw[:, a:b], window) for a, b in itertools.pairwise(cuts)], axis=1)
    # reached[k-1]: share of episodes whose stage is k or later; S0 falling == reached[0] rising
    reached = np.cumsum(shares[::-1], axis=0)[::-1][1:]
    found = [r for k in range(1, len(keys)) for r in find_regressions(it, reached[k - 1], min_drop, recover, k)]
    return {"iterations": it, "stages": [k.split("/")[-1] for k in keys], "shares": shares, "reached": reached,
            "regressions": sorted(found, key=lambda r: (r.start_iteration, r.stage)), "episodes": eps}


def label_intervals(regressions: list[Regression], restarts: list[float], window: int) -> list[dict]:
    """Overlapping regressions (of any stage) merged into one labelled interval each.
    ``at_restart``: the interval touches the first ``window`` iterations after a restart
    (an offset in ``restarts``), where the first episodes to end are the short ones of the
    desynchronised reset rather than a learning regression."""
    groups: list[dict] = []
    for r in sorted(regressions, key=lambda r: r.start_iteration):
        if groups and r.start_iteration <= groups[-1]["end_iteration"]:
            g = groups[-1]
            g["end_iteration"] = max(g["end_iteration"], r.end_iteration)
        else:
            g = {"start_iteration": r.start_iteration, "end_iteration": r.end_iteration, "regressions": []}
            groups.append(g)
        g["regressions"].append(r)
    for i, g in enumerate(groups):
        g["label"] = _label(i)
        g["max_depth"] = max(r.depth for r in g["regressions"])
        g["stages"] = sorted(r.stage for r in g["regressions"])
        g["recovered"] = all(r.recovered for r in g["regressions"])
        g["at_restart"] = any(g["start_iteration"] <= o + window and g["end_iteration"] > o for o in restarts)
    return groups


def _label(i: int) -> str:
    letters = string.ascii_uppercase
    return letters[i] if i < len(letters) else letters[i // len(letters) - 1] + letters[i % len(letters)]


def plot(prog: dict, intervals: list[dict], inputs: list[dict], path: Path, window: int) -> Path:
    it, stages = prog["iterations"], prog["stages"]
    colors = plt.get_cmap("viridis")(np.linspace(0.0, 0.95, len(stages)))
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True, height_ratios=(3, 2))
    ok = np.isfinite(prog["shares"]).all(0)
    top.stackplot(it[ok], prog["shares"][:, ok], labels=stages, colors=colors, lw=0)
    top.set(ylabel="share of episodes by stage", ylim=(0, 1), xlim=(it[0], it[-1]))
    note = " (*: at a restart)" if any(g["at_restart"] for g in intervals) else ""
    top.set_title(f"Stage progression (episode-weighted means over {window}-iteration windows); "
                  f"shaded: regressions{note}", fontsize=10, pad=18)
    for k in range(1, len(stages)):
        line = prog["reached"][k - 1]
        bottom.plot(it, line, color=colors[k], lw=1.2, label=f"reached {stages[k]}+")
    bottom.set(xlabel="iteration (runs concatenated)", ylabel="share reaching stage k or later", ylim=(0, 1))
    bottom.grid(alpha=0.3)
    for ax in (top, bottom):
        for g in intervals:
            # hatched, light and behind the lines: the shares stay readable through it
            ax.axvspan(g["start_iteration"], g["end_iteration"], facecolor="0.5", alpha=0.18, hatch="//",
                       edgecolor="k", lw=0, zorder=2.5 if ax is top else 0)
        for inp in inputs[1:]:
            ax.axvline(inp["offset"] + 0.5, color="r", lw=1.2, ls="--", zorder=3)
    for g in intervals:
        mid = (g["start_iteration"] + g["end_iteration"]) / 2
        top.text(mid, 1.01, g["label"] + ("*" if g["at_restart"] else ""), transform=top.get_xaxis_transform(),
                 ha="center", va="bottom", fontsize=9, fontweight="bold")
    for inp in inputs:  # run names low in the lower panel, where the lines rarely are
        bottom.text(inp["offset"] + 0.5, 0.04, f" {Path(inp['path']).parent.name}", color="r", fontsize=8,
                    va="bottom", zorder=4, bbox={"facecolor": "w", "edgecolor": "none", "alpha": 0.8, "pad": 1})
    top.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8, title="stage", title_fontsize=8)
    bottom.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def summary(prog: dict, intervals: list[dict], inputs: list[dict], args: argparse.Namespace) -> dict:
    stages = prog["stages"]
    shaded = [{"label": g["label"], "start_iteration": g["start_iteration"], "end_iteration": g["end_iteration"],
               "max_depth": round(g["max_depth"], 4), "stages": [f"{stages[k]}+" for k in g["stages"]],
               "recovered": g["recovered"], "at_restart": g["at_restart"]} for g in intervals]
    label_of = {id(r): g["label"] for g in intervals for r in g["regressions"]}
    regressions = [{**r._asdict(), "depth": round(r.depth, 4), "series": f"share reaching {stages[r.stage]} or later",
                    "label": label_of[id(r)]} for g in intervals for r in g["regressions"]]
    return {"intervals": shaded, "regressions": regressions, "inputs": inputs,
            "options": {"window": args.window, "min_drop": args.min_drop, "recover": args.recover},
            "iterations": len(prog["iterations"]), "episodes": int(np.nansum(prog["episodes"])),
            **provenance()}


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out_prefix", help="writes OUT_PREFIX.png and OUT_PREFIX.json")
    p.add_argument("metrics", nargs="+", help="metrics.jsonl files of consecutive runs, in order")
    p.add_argument("--window", type=int, default=20, help="smoothing window in iterations")
    p.add_argument("--min-drop", type=float, default=0.1, help="smallest drop below the running maximum")
    p.add_argument("--recover", type=float, default=0.05, help="back within this of the maximum = recovered")
    return p.parse_args(argv)


def main(argv: list[str]) -> dict:
    args, t0 = parse_args(argv), time.monotonic()
    rows, inputs = load_runs(args.metrics)
    prog = progression(rows, inputs, args.window, args.min_drop, args.recover)
    intervals = label_intervals(prog["regressions"], [inp["offset"] for inp in inputs[1:]], args.window)
    out = Path(args.out_prefix)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot(prog, intervals, inputs, out.with_name(out.name + ".png"), args.window)
    # No randomness: the figure is a function of the metrics files (seed is their runs').
    result = {**summary(prog, intervals, inputs, args), "seed": None, "wall_s": time.monotonic() - t0}
    out.with_name(out.name + ".json").write_text(json.dumps(result, indent=1) + "\n")
    for g in result["intervals"]:
        print(f"{g['label']}: iterations {g['start_iteration']:.0f}-{g['end_iteration']:.0f}, "
              f"depth {g['max_depth']:.2f} ({', '.join(g['stages'])}){'' if g['recovered'] else ', not recovered'}"
              f"{', at a restart' if g['at_restart'] else ''}")
    return result
