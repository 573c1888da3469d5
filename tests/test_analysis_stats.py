"""analysis.stats (paired / Welch t statistics across seeds) and the findings worded from it.

Hand-computed reference: a = [10, 12, 14], b = [11, 13, 15.5] on seeds 0, 1, 2.
Per-seed differences a - b = [-1, -1, -1.5]: mean -7/6, sample sd sqrt(1/12), standard error
1/6, t = -7 with 2 degrees of freedom, half-width t_{0.975,2} / 6 = 4.302652729749462 / 6 and,
from the closed-form t(2) CDF F(t) = 1/2 + t / (2 sqrt(2 + t^2)), p = 1 - 7 / sqrt(51).
Unpaired, the two 95 % intervals (12 ± 4.97 and 13.17 ± 5.60) overlap widely.
"""

from __future__ import annotations

import math
import subprocess
import sys
import warnings
from pathlib import Path

import pandas as pd
import pytest
from scipy import stats as st

from analysis import findings
from analysis.results import mean_ci, metric_ci, nonneg_mean_ci, records_to_frame
from analysis.stats import Difference, log_interval, paired_difference, t_quantile_975
from mixed_traffic.schema import METRICS

REPO = Path(__file__).resolve().parents[1]
A = [10.0, 12.0, 14.0]
B = [11.0, 13.0, 15.5]
T2 = 4.302652729749462  # t_{0.975, 2}
PAIRED_MEAN = -7 / 6
PAIRED_HALF = T2 / 6
PAIRED_P = 1 - 7 / math.sqrt(51)


def _series(values: list[float], seeds: list[int]) -> pd.Series:
    return pd.Series(values, index=pd.Index(seeds, name="seed"))


# ---------------------------------------------------------------- t quantile


def test_t_quantile_975_from_scipy():
    assert t_quantile_975(2) == pytest.approx(T2, rel=1e-12)
    assert t_quantile_975(1) == pytest.approx(12.706204736, rel=1e-9)
    assert t_quantile_975(3) == pytest.approx(3.182446305, rel=1e-9)
    assert t_quantile_975(1000) == pytest.approx(1.962339, rel=1e-6)
    assert t_quantile_975(3.5) == pytest.approx(st.t.ppf(0.975, 3.5))  # Welch's fractional df
    for bad in (0, 0.5, -1, math.nan):
        with pytest.raises(ValueError, match="degrees of freedom"):
            t_quantile_975(bad)


def test_mean_ci_uses_exact_quantile():
    mean, half, n = mean_ci(A)
    assert (mean, n) == (12.0, 3)
    assert half == pytest.approx(T2 * 2.0 / math.sqrt(3), rel=1e-12)


# ---------------------------------------------------------------- intervals of non-negative means

SPREAD = [0.3, 2.5, 5.0]  # a speed std over 3 seeds whose t-interval reaches below 0


def test_log_interval_stays_above_zero_where_the_t_interval_crosses_it():
    mean, half, _ = mean_ci(SPREAD)
    assert mean - half < 0  # the impossible interval of issue 59
    m, lo, hi, n = nonneg_mean_ci(SPREAD)
    assert (m, n) == (mean, 3) and 0 < lo < m < hi
    # mean * exp(-+t s / (sqrt(n) mean)), s the sample sd
    s = math.sqrt(sum((v - mean) ** 2 for v in SPREAD) / 2)
    assert lo == pytest.approx(mean * math.exp(-T2 * s / (math.sqrt(3) * mean)), rel=1e-12)
    assert hi == pytest.approx(mean * math.exp(T2 * s / (math.sqrt(3) * mean)), rel=1e-12)
    assert (lo, hi) == log_interval(mean, half)


def test_log_interval_is_the_t_interval_for_tight_samples():
    mean, half, _ = mean_ci([100.0, 100.1, 99.9])
    _, lo, hi, _ = nonneg_mean_ci([100.0, 100.1, 99.9])
    assert lo == pytest.approx(mean - half, abs=1e-3) and hi == pytest.approx(mean + half, abs=1e-3)
    assert hi - mean > mean - lo  # still skewed upward, by O(half^2 / mean)


def test_log_interval_edge_cases():
    assert nonneg_mean_ci([0.0, 0.0, 0.0]) == (0.0, 0.0, 0.0, 3)  # no spread, no interval width
    m, lo, hi, n = nonneg_mean_ci([7.0, None, math.nan])
    assert (m, n) == (7.0, 1) and math.isnan(lo) and math.isnan(hi)  # no interval from one seed
    assert all(math.isnan(v) for v in nonneg_mean_ci([])[:3])
    mean, half, _ = mean_ci([1.0, -1.0, 3.0])  # not non-negative after all: the t-interval
    assert nonneg_mean_ci([1.0, -1.0, 3.0]) == (mean, mean - half, mean + half, 3)


def test_signed_metrics_keep_the_t_interval():
    assert not METRICS["wave_speed"].nonnegative and not METRICS["avg_r"].nonnegative
    for key in ("speed_std", "fuel", "dt_tf", "avg_dt_a", "avg_at_c", "route_completion"):
        assert METRICS[key].nonnegative, key
    mean, half, n = mean_ci(SPREAD)
    assert metric_ci("wave_speed", SPREAD) == (mean, mean - half, mean + half, n)
    assert metric_ci("speed_std", SPREAD) == nonneg_mean_ci(SPREAD)


# ---------------------------------------------------------------- paired difference


def test_paired_hand_computed():
    d = paired_difference(_series(A, [0, 1, 2]), _series(B, [0, 1, 2]))
    assert isinstance(d, Difference)
    assert d.paired and d.n == 3 and d.test == "paired t-test"
    assert d.mean == pytest.approx(PAIRED_MEAN, rel=1e-12)
    assert d.half_width == pytest.approx(PAIRED_HALF, rel=1e-12)
    assert d.half_width == pytest.approx(0.7171087883, rel=1e-9)
    assert d.p == pytest.approx(PAIRED_P, rel=1e-9)
    assert d.p == pytest.approx(0.0198039412, rel=1e-8)
    assert d.significant is True  # CI [-1.88, -0.45] excludes 0


def test_paired_matches_by_seed_not_position():
    a = _series(A, [0, 1, 2])
    b = _series(list(reversed(B)), [2, 1, 0])
    d = paired_difference(a, b)
    assert d.paired and d.mean == pytest.approx(PAIRED_MEAN)
    assert d.half_width == pytest.approx(PAIRED_HALF)


def test_paired_uses_shared_seeds_only_and_drops_nan():
    a = _series([*A, 99.0], [0, 1, 2, 7])  # seed 7 has no partner
    b = _series([B[0], B[1], math.nan], [0, 1, 2])  # seed 2 is not finite in b
    d = paired_difference(a, b)
    assert d.paired and d.n == 2
    assert d.mean == pytest.approx(-1.0)
    assert d.half_width == 0.0 and d.p == 0.0 and d.significant is True


def test_unpaired_intervals_overlap_but_paired_ci_excludes_zero():
    ma, ha, _ = mean_ci(A)
    mb, hb, _ = mean_ci(B)
    assert abs(ma - mb) < ha + hb  # the old rule ("intervals do not overlap") saw no difference
    d = paired_difference(_series(A, [0, 1, 2]), _series(B, [0, 1, 2]))
    assert d.mean + d.half_width < 0  # the paired rule does


def test_welch_fallback_without_shared_seeds():
    d = paired_difference(_series(A, [0, 1, 2]), _series(B, [3, 4, 5]))
    assert not d.paired and d.n == 3 and d.test == "Welch's t-test"
    assert d.mean == pytest.approx(PAIRED_MEAN)
    # se^2 = 4/3 + (61/12)/3 = 109/36; Welch-Satterthwaite df = 23762/6025
    se = math.sqrt(109) / 6
    df = 23762 / 6025
    assert d.half_width == pytest.approx(st.t.ppf(0.975, df) * se, rel=1e-12)
    assert d.p == pytest.approx(2 * st.t.sf((7 / 6) / se, df), rel=1e-9)
    assert d.p == pytest.approx(0.5397674967, rel=1e-8)
    assert d.significant is False


def test_welch_fallback_with_one_shared_seed_and_significant():
    a = _series([10.0, 11.0, 12.0], [0, 1, 2])
    b = _series([20.0, 21.0, 22.5], [2, 3, 4])  # only seed 2 shared: fewer than 2 pairs
    d = paired_difference(a, b)
    assert not d.paired
    expected = st.ttest_ind([10.0, 11.0, 12.0], [20.0, 21.0, 22.5], equal_var=False)
    assert d.p == pytest.approx(expected.pvalue)
    assert d.significant is True and d.mean == pytest.approx(11 - 63.5 / 3)


def test_too_few_values_for_a_test():
    d = paired_difference(_series([1.0], [0]), _series([2.0, 3.0], [0, 1]))
    assert not d.paired and d.n == 1
    assert math.isnan(d.half_width) and math.isnan(d.p) and d.significant is None
    empty = paired_difference(_series([], []), _series([2.0], [0]))
    assert empty.significant is None and math.isnan(empty.mean)


def test_degenerate_differences_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        same = paired_difference(_series(A, [0, 1, 2]), _series(A, [0, 1, 2]))
        assert (same.mean, same.half_width, same.p, same.significant) == (0.0, 0.0, 1.0, False)
        shifted = paired_difference(_series(A, [0, 1, 2]), _series([a - 1 for a in A], [0, 1, 2]))
        assert shifted.mean == 1.0 and shifted.p == 0.0 and shifted.significant is True
        near = paired_difference(
            _series([1e9, 1e9, 1e9], [0, 1, 2]), _series([1e9, 1e9 + 1e-6, 1e9], [0, 1, 2])
        )
        assert near.significant is False


# ---------------------------------------------------------------- findings


def _frame(rows: list[tuple[str, float, int, str, float]]) -> pd.DataFrame:
    """Tidy table from (policy, penetration, seed, metric, value) rows at 120 veh/km."""
    records = []
    for policy, pen, seed, metric, value in rows:
        cell = {
            "policy": policy, "scenario": "straight", "density": 120.0, "penetration": pen,
            "weather": "normal", "seed": seed,
        }  # fmt: skip
        records.append({"cell": cell, "status": "ok", "code": "c0de", "metrics": {metric: value}})
    return records_to_frame(records)


def _policies(a_seeds: list[int], b_seeds: list[int], b_values: list[float] = B) -> pd.DataFrame:
    rows = [("auto", 0.2, s, "avg_dt_a", v) for s, v in zip(a_seeds, A)]
    rows += [("acc-lc", 0.2, s, "avg_dt_a", v) for s, v in zip(b_seeds, b_values)]
    return _frame(rows)


def test_findings_call_paired_difference_despite_overlap():
    text = findings.policy_comparisons(_policies([0, 1, 2], [0, 1, 2]), ("avg_dt_a",))
    assert text == [
        "auto vs acc-lc AvgDT-A at 120 veh/km: 12.00 vs 13.17 s/km (auto better; lower is "
        "better; paired t-test over 3 seeds: difference -1.17 ± 0.72 s/km, p = 0.020)."
    ]


def test_findings_welch_fallback_wording():
    text = findings.policy_comparisons(_policies([0, 1, 2], [3, 4, 5]), ("avg_dt_a",))
    assert len(text) == 1
    assert text[0].startswith("auto vs acc-lc AvgDT-A at 120 veh/km: 12.00 vs 13.17 s/km (")
    assert (
        "(within noise; Welch's t-test (fewer than 2 shared seeds): difference -1.17 ± " in text[0]
    )
    assert text[0].endswith(", p = 0.54).")
    worse = findings.policy_comparisons(
        _policies([0, 1, 2], [3, 4, 5], [5.0, 6.0, 7.0]), ("avg_dt_a",)
    )
    assert "(auto worse; lower is better; Welch's t-test (fewer than 2 shared seeds)" in worse[0]


def test_findings_too_few_seeds():
    text = findings.policy_comparisons(_policies([0], [0]), ("avg_dt_a",))
    assert text == ["auto vs acc-lc AvgDT-A at 120 veh/km: 10.00 vs 11.00 s/km (too few seeds for a test)."]  # fmt: skip


def test_trend_paired_by_seed():
    rows = [("auto", 0.2, s, "dt_tf", v) for s, v in zip([0, 1, 2], A)]
    rows += [("auto", 1.0, s, "dt_tf", v) for s, v in zip([0, 1, 2], B)]
    text = findings.trend(_frame(rows), "penetration", "dt_tf")
    assert text == [
        "DT-TF with auto rises from 12.00 s at 20 % to 13.17 s at 100 % (paired t-test over "
        "3 seeds: difference 1.17 ± 0.72 s, p = 0.020)."
    ]
    rows[3:] = [("auto", 1.0, s, "dt_tf", v) for s, v in zip([3, 4, 5], B)]
    text = findings.trend(_frame(rows), "penetration", "dt_tf")
    assert text[0].startswith("DT-TF with auto changes from 12.00 s at 20 % to 13.17 s at 100 %")
    assert "(within noise; Welch's t-test" in text[0]


# ---------------------------------------------------------------- imports and CLI


def test_analysis_modules_import_without_sumo_or_torch():
    code = (
        "import analysis.report, analysis.figures, analysis.findings, analysis.tables, "
        "analysis.results, analysis.style, sys; "
        "bad=[m for m in ('libsumo','torch','traci') if m in sys.modules]; assert not bad, bad"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert proc.returncode == 0, proc.stderr


def test_cli_lives_in_analysis_report():
    import analysis.report
    import mixed_traffic.report

    assert mixed_traffic.report.main is analysis.report.main
    proc = subprocess.run(
        [sys.executable, "-m", "analysis.report", "--help"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0 and "RESULTS_DIR" in proc.stdout and "--title" in proc.stdout
