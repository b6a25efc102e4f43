"""How well a score ranks labelled items: the area under the ROC curve and its stratified bootstrap interval. Pure
NumPy, below every room: the outcome statistics (`cam.outcomes`) and the failure monitor's detection figures
(`monitor.detection`) both rank episodes with it.

Conventions: `failed` is bool [n], True for a failed episode; `scores` is float [n], a larger score flagging an
episode as more likely failed. Episodes whose score is not finite take no part (a figure an episode lacks).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def finite_scores(failed: Sequence[bool], scores: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """(labels bool [m], scores float64 [m]) of the episodes whose score is finite."""
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
    y, s = finite_scores(failed, scores)
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return math.nan
    return _auc(pos, neg)


def _auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Mann-Whitney's U / (failures x successes) of the failures' and the successes' scores, ties counting one half."""
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (pos.size * neg.size))


def bootstrap_auc(
    failed: Sequence[bool], scores: Sequence[float], *, resamples: int = 2000, level: float = 0.95, seed: int = 0
) -> tuple[float, float]:
    """A percentile bootstrap interval of `roc_auc`, resampling failures and successes each with replacement (their
    counts kept, as a stratified bootstrap does). (nan, nan) without both."""
    y, s = finite_scores(failed, scores)
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    values = np.empty(resamples)
    for i in range(resamples):
        values[i] = _auc(pos[rng.integers(0, pos.size, pos.size)], neg[rng.integers(0, neg.size, neg.size)])
    tail = (1 - level) / 2 * 100
    return float(np.percentile(values, tail)), float(np.percentile(values, 100 - tail))
