"""How early a score finds failed episodes: the AUROC over episodes of each figure's episode score at N source
frames, the maximum of its step scores within the episode's first N frames, for N in FRAMES and the whole episode.

A monitor flags an episode once a step's score exceeds its threshold, so the maximum so far is what it has to go on
at any time, and the AUROC of that maximum at N says how well any threshold separates failures from successes by
then. N counts source frames from the episode's start (not explained steps), so figures explained at different
rates compare at the same time into the episode. An episode that ended before N frames scores over all its steps
(by then it is over); one with no finite score of a figure within the first N frames takes no part in that figure
(STAC at N = 1, which needs a previous call), and `episodes` counts those that did.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.auroc import bootstrap_auc, roc_auc

FRAMES = (1, 4, 8, 16, 32)
WHOLE = "episode"  # the `frames` entry of the whole-episode figures


@dataclasses.dataclass(frozen=True)
class ScoredEpisode:
    """One episode's step scores. frames: [T] int, each scored step's source frame index within the episode (0 at
    its first frame: LeRobot's `frame_index`); scores: figure name -> [T], larger meaning more likely failing (NaN
    where a step lacks the figure); failed: the outcome."""

    frames: np.ndarray
    scores: Mapping[str, np.ndarray]
    failed: bool


def score_within(frames: np.ndarray, scores: np.ndarray, n: int | None) -> float:
    """The maximum finite score among the steps whose source frame is < n (None: every step); NaN if none."""
    f = np.asarray(frames).reshape(-1)
    s = np.asarray(scores, np.float64).reshape(-1)
    if f.shape != s.shape:
        raise ValueError(f"{s.size} scores for {f.size} frame indices")
    kept = s[np.isfinite(s) & (f < n)] if n is not None else s[np.isfinite(s)]
    return float(kept.max()) if kept.size else math.nan


def _none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _figure(failed: np.ndarray, scores: np.ndarray, resamples: int, seed: int) -> dict[str, Any]:
    keep = np.isfinite(scores)
    low, high = bootstrap_auc(failed, scores, resamples=resamples, seed=seed)
    return {
        "auroc": _none(roc_auc(failed, scores)),
        "auroc_ci95": [_none(low), _none(high)],
        "episodes": int(keep.sum()),
        "failures": int(failed[keep].sum()),
    }


def detection(
    episodes: Sequence[ScoredEpisode], frames: Sequence[int] = FRAMES, *, resamples: int = 2000, seed: int = 0
) -> list[dict[str, Any]]:
    """`[{"frames": N or "episode", "figures": {name: {"auroc", "auroc_ci95", "episodes", "failures"}}}]`: for each
    N in `frames` and then the whole episode, each figure's ROC AUC of failure over the episodes' scores at N, with
    its stratified bootstrap 95% interval (`auroc.bootstrap_auc`, `resamples` draws from `seed`). None where a
    figure lacks a failure or a success. Figures are every name any episode scores, sorted."""
    names = sorted({name for e in episodes for name in e.scores})
    for i, e in enumerate(episodes):
        for name, s in e.scores.items():
            if np.shape(s) != np.shape(e.frames):
                raise ValueError(f"episode {i}: figure {name!r} has {np.size(s)} scores for {np.size(e.frames)} frames")
    failed = np.array([bool(e.failed) for e in episodes])
    out = []
    for n in [*frames, None]:
        figures = {}
        for name in names:
            at_n = np.array(
                [score_within(e.frames, e.scores[name], n) if name in e.scores else math.nan for e in episodes]
            )
            figures[name] = _figure(failed, at_n, resamples, seed)
        out.append({"frames": WHOLE if n is None else int(n), "figures": figures})
    return out
