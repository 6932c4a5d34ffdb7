"""Paired comparison statistics: exact McNemar, bootstrap intervals, refusal of unpaired records."""
import math

import pytest

from pnp.training.paired import comparison_md, mcnemar_exact, paired_comparison, wilson


def _records(successes, steps=None):
    steps = steps or [100] * len(successes)
    return [{"trial": i, "success": bool(s), "steps": n} for i, (s, n) in enumerate(zip(successes, steps))]


def test_mcnemar_exact_matches_the_binomial_tail():
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(5, 5) == 1.0
    # 8 discordant trials all one way: 2 * (1/2)^8
    assert mcnemar_exact(8, 0) == pytest.approx(2 / 256)
    assert mcnemar_exact(1, 9) == pytest.approx(2 * (1 + 10) / 1024)
    assert mcnemar_exact(2, 9) == mcnemar_exact(9, 2)


def test_paired_comparison_counts_discordant_trials_and_brackets_the_difference():
    a = _records([1] * 90 + [0] * 10, steps=[100] * 100)
    b = _records([1] * 80 + [0] * 15 + [1] * 5, steps=[110] * 100)
    c = paired_comparison(a, b)
    assert (c["only_a_succeeded"], c["only_b_succeeded"], c["both_succeeded"]) == (10, 5, 80)
    assert c["success_diff"] == pytest.approx(0.05)
    lo, hi = c["success_diff_interval"]
    assert lo < 0.05 < hi and hi - lo < 0.2
    assert c["mcnemar_exact_p"] == pytest.approx(mcnemar_exact(10, 5))
    assert c["time_diff_s"] == pytest.approx(-1.0) and c["time_diff_interval_s"] == pytest.approx([-1.0, -1.0])
    assert "only" in comparison_md(c, "teacher", "student")


def test_unpaired_records_are_refused():
    a = _records([1, 0, 1])
    with pytest.raises(ValueError, match="different trials"):
        paired_comparison(a, _records([1, 0]))
    with pytest.raises(ValueError, match="'trial' index"):
        paired_comparison(a, [{k: v for k, v in r.items() if k != "trial"} for r in a])
    assert not math.isnan(paired_comparison(a, a)["success_diff"])


def test_wilson_interval_matches_the_textbook_values():
    lo, hi = wilson(0.5, 100)
    assert (lo, hi) == (pytest.approx(0.4038, abs=1e-4), pytest.approx(0.5962, abs=1e-4))
    lo, hi = wilson(1.0, 500)  # all successes: the interval stays below 1 and excludes nothing above
    assert hi == pytest.approx(1.0) and 0.99 < lo < 1.0
