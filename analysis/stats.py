"""Two-sided 95 % Student t statistics across seeds (scipy only; no SUMO, no torch).

- :func:`t_quantile_975`: the critical value t_{0.975, df} of the 95 % t-intervals
- :func:`log_interval`: the 95 % log-scale (delta-method) t-interval of a non-negative mean,
  which never crosses 0 (the levels of non-negative metrics; signed ones keep the t-interval)
- :func:`paired_difference`: the difference of one metric between two groups of episodes that
  differ in one factor (policy, or a sweep axis value), paired by seed when the seeds are shared
  (paired t-test), else Welch's t-test.

Significance rule (used by :mod:`analysis.findings`): a paired difference is significant when its
95 % t-interval excludes 0 (equivalently, the paired t-test has p < 0.05); an unpaired one when
Welch's t-test has p < 0.05.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats as _st

ALPHA = 0.05
"""Two-sided significance level of every test (the intervals are 1 - ALPHA = 95 %)."""
MIN_PAIRS = 2
"""Fewest shared seeds for the paired test; with fewer, Welch's test is used."""


def t_quantile_975(df: float) -> float:
    """Two-sided 95 % Student t critical value t_{0.975} for ``df`` (>= 1) degrees of freedom.

    ``df`` may be fractional (Welch-Satterthwaite). Raises ValueError for df < 1 or NaN.
    """
    if not df >= 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    return float(_st.t.ppf(1.0 - ALPHA / 2, df))


def log_interval(mean: float, half: float) -> tuple[float, float]:
    """95 % log-scale (delta-method) t-interval ``(lo, hi)`` of the mean of non-negative values.

    ``half`` is the half-width t_{0.975, n-1} s / sqrt(n) of the Student t-interval (sample sd
    s of n values). By the delta method log(mean) has standard error s / (sqrt(n) mean), so the
    t-interval of log(mean) maps back to ``(mean / exp(half / mean), mean * exp(half / mean))``:
    it contains the mean, stays above 0, is skewed upward like the mean of a non-negative
    quantity, and tends to ``(mean - half, mean + half)`` as ``half / mean`` goes to 0 (for
    non-negative values ``half / mean`` is at most t_{0.975, n-1}). A zero mean (all values 0)
    gives [0, 0]; a NaN ``half`` (fewer than two values) gives NaN bounds. Units: those of
    ``mean``.
    """
    if mean == 0:
        return mean - half, mean + half  # all values 0: half is 0 (or NaN from one value)
    factor = math.exp(half / mean)
    return mean / factor, mean * factor


@dataclass(frozen=True)
class Difference:
    """Difference ``a - b`` of one metric between two groups of episodes, in the metric's unit.

    Attributes:
        mean: paired: mean of the per-seed differences; unpaired: difference of the group means.
        half_width: half-width of its 95 % t-interval (NaN when it cannot be computed).
        p: two-sided p-value of the paired (``ttest_rel``) or Welch (``ttest_ind``) t-test
            (NaN when it cannot be computed).
        n: paired: number of shared seeds; unpaired: the smaller group's size.
        paired: True for the paired t-test over shared seeds, False for Welch's t-test.
    """

    mean: float
    half_width: float
    p: float
    n: int
    paired: bool

    @property
    def test(self) -> str:
        """Name of the test used ('paired t-test' or "Welch's t-test")."""
        return "paired t-test" if self.paired else "Welch's t-test"

    @property
    def significant(self) -> bool | None:
        """Paired: the 95 % interval excludes 0. Welch: p < 0.05. None when not computable."""
        if self.paired:
            if math.isnan(self.half_width):
                return None
            return abs(self.mean) > self.half_width
        return None if math.isnan(self.p) else self.p < ALPHA


def _finite(s: pd.Series) -> pd.Series:
    """The finite values of ``s`` as floats (index kept)."""
    s = pd.to_numeric(s, errors="coerce").astype(float)
    return s[np.isfinite(s.to_numpy())]


def _shared_seeds(a: pd.Series, b: pd.Series) -> list:
    """Seeds (index labels, not missing) present in both, in ``a``'s order; empty when either
    index repeats a seed (pairing would be ambiguous)."""
    if not (a.index.is_unique and b.index.is_unique):
        return []
    in_b = set(b.index[b.index.notna()])
    return [s for s in a.index[a.index.notna()] if s in in_b]


def _degenerate_p(mean: float) -> float:
    """p-value of a test whose standard error is 0: 1 without a difference, else 0."""
    return 1.0 if mean == 0 else 0.0


def _paired(d: np.ndarray, a: np.ndarray, b: np.ndarray) -> Difference:
    """Paired t statistics of the per-seed differences ``d = a - b`` (shape (n,), n >= 2)."""
    n = int(d.size)
    mean = float(d.mean())
    se = float(d.std(ddof=1)) / math.sqrt(n)
    half = t_quantile_975(n - 1) * se
    if se == 0:
        p = _degenerate_p(mean)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # near-identical data
            p = float(_st.ttest_rel(a, b).pvalue)
    return Difference(mean=mean, half_width=half, p=p, n=n, paired=True)


def _welch(a: np.ndarray, b: np.ndarray) -> Difference:
    """Welch's t statistics of ``mean(a) - mean(b)`` (shapes (n_a,), (n_b,))."""
    n = min(a.size, b.size)
    mean = float(a.mean() - b.mean()) if n else math.nan
    if n < 2:
        return Difference(mean=mean, half_width=math.nan, p=math.nan, n=int(n), paired=False)
    va, vb = float(a.var(ddof=1)) / a.size, float(b.var(ddof=1)) / b.size
    se = math.sqrt(va + vb)
    if se == 0:
        return Difference(mean=mean, half_width=0.0, p=_degenerate_p(mean), n=n, paired=False)
    df = (va + vb) ** 2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = float(_st.ttest_ind(a, b, equal_var=False).pvalue)
    return Difference(mean=mean, half_width=t_quantile_975(df) * se, p=p, n=n, paired=False)


def paired_difference(a: pd.Series, b: pd.Series) -> Difference:
    """Difference ``a - b`` of one metric between two groups of episodes, paired by seed.

    Args:
        a, b: one metric value per episode (metric unit), indexed by seed. Non-finite values
            are dropped.

    With at least :data:`MIN_PAIRS` seeds present in both (and no seed repeated within a group)
    the per-seed differences on the shared seeds give the mean, its 95 % t-interval and the
    paired t-test (``scipy.stats.ttest_rel``); seeds present in one group only are left out.
    Otherwise all values enter Welch's t-test (``scipy.stats.ttest_ind(equal_var=False)``) with
    the Welch-Satterthwaite interval. With fewer than two values in a group the half-width and
    p are NaN (:attr:`Difference.significant` is None).
    """
    a, b = _finite(a), _finite(b)
    seeds = _shared_seeds(a, b)
    if len(seeds) >= MIN_PAIRS:
        x, y = a.loc[seeds].to_numpy(), b.loc[seeds].to_numpy()
        return _paired(x - y, x, y)
    return _welch(a.to_numpy(), b.to_numpy())


__all__ = [
    "ALPHA",
    "MIN_PAIRS",
    "Difference",
    "log_interval",
    "paired_difference",
    "t_quantile_975",
]
