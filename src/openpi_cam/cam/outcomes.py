"""Episode outcomes as statistics: success rates with their confidence intervals, and how well a figure of each
episode finds the failed ones. Pure NumPy functions of labels and scores (no model here).

Conventions: `failed` is bool [n], True for a failed episode; `scores` is float [n], a larger score flagging an
episode as more likely failed. Episodes whose score is not finite take no part (a figure an episode lacks).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

Z95 = 1.959963984540054  # the standard normal's 97.5% quantile: two-sided 95% intervals


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a success rate (95% by default): it stays inside [0, 1] and keeps its coverage at
    rates near 0 or 1, where the normal approximation's does not. (nan, nan) for n = 0."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


def _finite(failed: Sequence[bool], scores: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(failed, bool).reshape(-1)
    s = np.asarray(scores, np.float64).reshape(-1)
    if y.shape != s.shape:
        raise ValueError(f"{y.size} labels for {s.size} scores")
    keep = np.isfinite(s)
    return y[keep], s[keep]


def roc_auc(failed: Sequence[bool], scores: Sequence[float]) -> float:
    """The probability that a failed episode scores higher than a successful one, ties counting one half (the area
    under the ROC curve, Mann-Whitney's U / (failures x successes)). 0.5 is chance, 1 ranks every failure first, 0
    every failure last. NaN without both a failure and a success."""
    y, s = _finite(failed, scores)
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return math.nan
    return _auc(pos, neg)


def _auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Mann-Whitney's U / (failures x successes) of the failures' and the successes' scores, ties counting one half."""
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (pos.size * neg.size))


def precision_at_failures(failed: Sequence[bool], scores: Sequence[float]) -> float:
    """The share of failures among the k highest-scoring episodes, k the number of failures (R-precision: chance is
    the failure rate, 1 flags exactly the failures). Episodes tied with the k-th score share its remaining places in
    proportion, so the figure does not depend on their order. NaN without a failure."""
    y, s = _finite(failed, scores)
    k = int(y.sum())
    if k == 0:
        return math.nan
    kth = np.sort(s)[::-1][k - 1]
    above = s > kth
    at = s == kth
    places = k - int(above.sum())  # places left for the episodes tied at the k-th score
    hits = y[above].sum() + places * y[at].mean()
    return float(hits / k)


def bootstrap_auc(
    failed: Sequence[bool], scores: Sequence[float], *, resamples: int = 2000, level: float = 0.95, seed: int = 0
) -> tuple[float, float]:
    """A percentile bootstrap interval of `roc_auc`, resampling failures and successes each with replacement (their
    counts kept, as a stratified bootstrap does). (nan, nan) without both."""
    y, s = _finite(failed, scores)
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    values = np.empty(resamples)
    for i in range(resamples):
        values[i] = _auc(pos[rng.integers(0, pos.size, pos.size)], neg[rng.integers(0, neg.size, neg.size)])
    tail = (1 - level) / 2 * 100
    return float(np.percentile(values, tail)), float(np.percentile(values, 100 - tail))


def finding(failed: Sequence[bool], scores: Sequence[float], *, seed: int = 0) -> dict[str, Any]:
    """How well `scores` find the failures: ROC AUC with its 95% bootstrap interval and precision at the number of
    failures, next to chance (0.5 and the failure rate), over the episodes with a finite score."""
    y, s = _finite(failed, scores)
    low, high = bootstrap_auc(y, s, seed=seed)
    return {
        "episodes": int(y.size),
        "failures": int(y.sum()),
        "auroc": _nan_none(roc_auc(y, s)),
        "auroc_ci95": [_nan_none(low), _nan_none(high)],
        "precision_at_failures": _nan_none(precision_at_failures(y, s)),
        "chance_precision": _nan_none(float(y.mean()) if y.size else math.nan),
    }


def _nan_none(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)
