"""Two policies compared on the same trials (docs/guide/evaluation.md).

Success is compared with McNemar's exact test (the discordant trials, binomial at 1/2) and a
paired bootstrap interval of the difference in success rate; completion time with a paired
bootstrap interval of the mean difference over the trials both policies completed. Every
difference is ``a - b``.
"""
from __future__ import annotations

import math

import numpy as np

from pnp.training.collect import seconds

LEVEL = 0.95
BOOTSTRAP = 10_000
Z95 = 1.959964  # the normal quantile of a two-sided 95 % interval


def wilson(p: float, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a success share ``p`` over ``n`` trials."""
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return centre - half, centre + half


def trial_table(records: list[dict]) -> list[list]:
    """``[trial, success, steps, cause]`` per trial: what a later evaluation on the same seed
    needs to pair with this one without re-running it."""
    return [[r["trial"], int(r["success"]), r["steps"], r["cause"]] for r in records]


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided exact p-value from the discordant counts (a succeeded alone, b alone)."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    k = min(only_a, only_b)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2 * tail)


def _interval(samples: np.ndarray) -> list[float]:
    lo, hi = np.quantile(samples, [(1 - LEVEL) / 2, (1 + LEVEL) / 2])
    return [float(lo), float(hi)]


def paired_comparison(a: list[dict], b: list[dict], seed: int = 0, resamples: int = BOOTSTRAP) -> dict:
    """Compare trial records ``a`` and ``b`` (``rollout.run_trials`` on paired envs)."""
    ta, tb = [r.get("trial") for r in a], [r.get("trial") for r in b]
    if None in ta or None in tb:
        raise ValueError("paired comparison needs records with a 'trial' index (an env with paired_trials)")
    if ta != tb:
        first = next((i for i, (x, y) in enumerate(zip(ta, tb)) if x != y), min(len(ta), len(tb)))
        raise ValueError(f"the two evaluations ran different trials ({len(ta)} vs {len(tb)} records, first "
                         f"difference at position {first}): use the same seed and trial count")
    sa = np.array([r["success"] for r in a], dtype=float)
    sb = np.array([r["success"] for r in b], dtype=float)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(sa), size=(resamples, len(sa)))
    diff = sa - sb
    out = {
        "trials": len(sa), "level": LEVEL, "bootstrap_resamples": resamples, "bootstrap_seed": seed,
        "success_rate_a": float(sa.mean()), "success_rate_b": float(sb.mean()),
        "success_diff": float(diff.mean()), "success_diff_interval": _interval(diff[idx].mean(1)),
        "only_a_succeeded": int(((sa == 1) & (sb == 0)).sum()), "only_b_succeeded": int(((sa == 0) & (sb == 1)).sum()),
    }
    out["mcnemar_exact_p"] = mcnemar_exact(out["only_a_succeeded"], out["only_b_succeeded"])
    both = (sa == 1) & (sb == 1)
    out["both_succeeded"] = int(both.sum())
    if both.sum() >= 2:
        dt = np.array([seconds(x["steps"]) - seconds(y["steps"]) for x, y, ok in zip(a, b, both) if ok])
        boot = dt[rng.integers(0, len(dt), size=(resamples, len(dt)))].mean(1)
        out.update(time_diff_s=float(dt.mean()), time_diff_interval_s=_interval(boot))
    else:
        out.update(time_diff_s=None, time_diff_interval_s=None)
    return out


def comparison_md(c: dict, name_a: str, name_b: str) -> str:
    """One paragraph: the paired differences and their intervals."""
    pct = lambda x: f"{100 * x:+.1f}"  # noqa: E731
    lo, hi = c["success_diff_interval"]
    text = (f"Paired on {c['trials']} trials: success {name_a} {100 * c['success_rate_a']:.1f} % vs {name_b} "
            f"{100 * c['success_rate_b']:.1f} %, difference {pct(c['success_diff'])} points "
            f"({100 * c['level']:.0f} % interval {pct(lo)} to {pct(hi)}; {c['only_a_succeeded']} trials only "
            f"{name_a} completed, {c['only_b_succeeded']} only {name_b}; exact McNemar p = {c['mcnemar_exact_p']:.3g}).")
    if c["time_diff_s"] is not None:
        tl, th = c["time_diff_interval_s"]
        text += (f" Completion time over the {c['both_succeeded']} trials both completed: {c['time_diff_s']:+.2f} s "
                 f"({tl:+.2f} to {th:+.2f} s).")
    return text + "\n"
