"""95 % intervals of Table I's ratios over training seeds (issue 68).

A ratio of two methods' means over their seeds, ``mean(a) / mean(b)``, gets its interval on
the log scale (delta method: the relative standard errors add in quadrature) with Student's t
at Welch's degrees of freedom, rounded down. With three seeds a method the quantile is ~4, so
the intervals are wide: that is what three seeds know.
"""
from __future__ import annotations

import math
import statistics

# Two-sided 95 % quantiles of Student's t by degrees of freedom; above 30, the normal's.
_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228,
         11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131, 16: 2.120, 17: 2.110, 18: 2.101, 19: 2.093,
         20: 2.086, 21: 2.080, 22: 2.074, 23: 2.069, 24: 2.064, 25: 2.060, 26: 2.056, 27: 2.052, 28: 2.048,
         29: 2.045, 30: 2.042}


def t975(df: float) -> float:
    """The quantile at ``df`` rounded down (the wider interval)."""
    return _T975[max(1, int(df))] if df < 31 else 1.960


def ratio_ci95(a: list[float | None], b: list[float | None]) -> list[float] | None:
    """``[low, high]`` of ``mean(a) / mean(b)``; None unless each side has >= 2 positive values
    and no missing one (a seed that never reached a threshold has no frames to average)."""
    if any(v is None for v in (*a, *b)) or len(a) < 2 or len(b) < 2 or min(*a, *b) <= 0:
        return None
    ma, mb = statistics.fmean(a), statistics.fmean(b)
    ra, rb = statistics.variance(a) / (len(a) * ma * ma), statistics.variance(b) / (len(b) * mb * mb)
    se = math.sqrt(ra + rb)
    if se == 0.0:
        return [ma / mb, ma / mb]
    df = se**4 / (ra * ra / (len(a) - 1) + rb * rb / (len(b) - 1))  # Welch-Satterthwaite
    half = t975(df) * se
    return [ma / mb * math.exp(-half), ma / mb * math.exp(half)]


def table1_intervals(methods: dict, ours: str, key: str, best_frames: str | None, best_time: str | None) -> dict:
    """The efficiency ratio's (``best_frames``' frames to ``key`` over ours') and the execution
    time ratio's (ours' MuJoCo completion time over ``best_time``'s) intervals over seeds."""
    def frames(m):
        return [s[key] for s in methods[m]["seeds"].values()]

    def times(m):
        return [s["eval"]["completion_time_mean_s"] for s in methods[m]["seeds"].values() if "eval" in s]

    return {"efficiency_ratio_ci95": ratio_ci95(frames(best_frames), frames(ours)) if best_frames else None,
            "execution_time_ratio_ci95": ratio_ci95(times(ours), times(best_time)) if best_time else None}
