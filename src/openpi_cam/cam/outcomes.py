"""Episode outcomes as statistics: success rates with their confidence intervals, and how well a figure of each
episode finds the failed ones. Pure NumPy functions of labels and scores (no model here); the ROC AUC and its
interval live in `openpi_cam.auroc` (the failure monitor ranks with them too) and are this module's names as well.

Conventions: `failed` is bool [n], True for a failed episode; `scores` is float [n], a larger score flagging an
episode as more likely failed. Episodes whose score is not finite take no part (a figure an episode lacks).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from openpi_cam.auroc import bootstrap_auc, finite_scores, roc_auc

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


def precision_at_failures(failed: Sequence[bool], scores: Sequence[float]) -> float:
    """The share of failures among the k highest-scoring episodes, k the number of failures (R-precision: chance is
    the failure rate, 1 flags exactly the failures). Episodes tied with the k-th score share its remaining places in
    proportion, so the figure does not depend on their order. NaN without a failure."""
    y, s = finite_scores(failed, scores)
    k = int(y.sum())
    if k == 0:
        return math.nan
    kth = np.sort(s)[::-1][k - 1]
    above = s > kth
    at = s == kth
    places = k - int(above.sum())  # places left for the episodes tied at the k-th score
    hits = y[above].sum() + places * y[at].mean()
    return float(hits / k)


def finding(failed: Sequence[bool], scores: Sequence[float], *, seed: int = 0) -> dict[str, Any]:
    """How well `scores` find the failures: ROC AUC with its 95% bootstrap interval and precision at the number of
    failures, next to chance (0.5 and the failure rate), over the episodes with a finite score."""
    y, s = finite_scores(failed, scores)
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
