"""Table I's ratio intervals over seeds: log-scale delta method with Welch's t."""
from __future__ import annotations

import math

import pytest

from pnp.studies.ratio_ci import ratio_ci95, t975, table1_intervals


def test_the_interval_is_symmetric_in_log_around_the_ratio_and_widens_with_fewer_degrees():
    lo, hi = ratio_ci95([2.0, 4.0], [1.0, 1.0])  # ratio 3; relative se 1/3 at 1 degree of freedom
    assert lo * hi == pytest.approx(9.0) and hi / 3.0 == pytest.approx(math.exp(12.706 / 3))
    lo6, hi6 = ratio_ci95([2.0, 4.0, 2.0, 4.0, 2.0, 4.0], [1.0] * 6)
    assert lo < lo6 < 3.0 < hi6 < hi
    assert ratio_ci95([2.0, 2.0], [1.0, 1.0]) == [2.0, 2.0]
    assert t975(2.7) == 4.303 and t975(500.0) == 1.960


def test_no_interval_from_one_seed_a_missing_value_or_a_zero():
    assert ratio_ci95([2.0], [1.0, 1.0]) is None
    assert ratio_ci95([2.0, None], [1.0, 1.0]) is None
    assert ratio_ci95([2.0, 0.0], [1.0, 1.0]) is None


def test_table1_intervals_read_frames_and_mujoco_times_per_seed():
    def seeds(frames, times):
        return {"seeds": {str(i): {"f": f, **({"eval": {"completion_time_mean_s": t}} if t else {})}
                          for i, (f, t) in enumerate(zip(frames, times))}}
    methods = {"ours": seeds([1.0, 1.0, 1.0], [10.0, 10.0, None]), "b": seeds([2.0, 2.0, 2.0], [20.0, 20.0, None])}
    out = table1_intervals(methods, "ours", "f", "b", "b")
    assert out == {"efficiency_ratio_ci95": [2.0, 2.0], "execution_time_ratio_ci95": [0.5, 0.5]}
    assert table1_intervals(methods, "ours", "f", None, None) == {"efficiency_ratio_ci95": None,
                                                                 "execution_time_ratio_ci95": None}
