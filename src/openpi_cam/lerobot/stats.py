"""Statistics of a LeRobot dataset's features as LeRobot 0.6.1 computes them (its `compute_stats`), so that its
normalisers read the numbers they expect: per episode, min / max / mean / std and the 1, 10, 50, 90, 99 % quantiles
from a 5000-bin histogram (cameras: per channel over a sample of the episode's frames, in [0, 1]); across episodes,
count-weighted means and variances, and quantiles averaged with the counts as weights."""

from __future__ import annotations

from typing import Any

import numpy as np

QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
HISTOGRAM_BINS = 5000

Stats = dict[str, np.ndarray]


def _quantile(histogram: np.ndarray, edges: np.ndarray, target: float) -> Any:
    """Where the cumulative histogram reaches `target` counts, interpolated inside the bin (LeRobot's estimate:
    a target in the first bin reads as the lowest edge)."""
    cumulative = np.cumsum(histogram)
    i = int(np.searchsorted(cumulative, target))
    if i == 0:
        return edges[0]
    if i >= len(cumulative):
        return edges[-1]
    below = cumulative[i - 1]
    inside = cumulative[i] - below
    if inside == 0:
        return edges[i]
    return edges[i] + (target - below) / inside * (edges[i + 1] - edges[i])


def feature_stats(values: np.ndarray, count: int) -> Stats:
    """Statistics per column of `values` [rows, columns]; `count` is what the rows stand for (frames)."""
    values = values.astype(np.result_type(values.dtype, np.float32), copy=False)
    if values.shape[0] < 2:
        mean = np.mean(values, axis=0)
        stats = {"min": values.min(axis=0), "max": values.max(axis=0), "mean": mean, "std": np.std(values, axis=0)}
        return {**stats, "count": np.array([count])} | {_quantile_key(q): mean.copy() for q in QUANTILES}
    low, high = values.min(axis=0), values.max(axis=0)
    mean = np.mean(values, axis=0)
    variance = np.mean(values**2, axis=0) - mean**2
    quantiles: list[list[Any]] = [[] for _ in QUANTILES]
    for column in range(values.shape[1]):
        # the edges carry the data's dtype, as LeRobot's do; 1e-10 keeps the extremes inside the outer bins
        edges = np.linspace(low[column] - 1e-10, high[column] + 1e-10, HISTOGRAM_BINS + 1)
        histogram = np.histogram(values[:, column], bins=edges)[0].astype(np.float64)
        for q, out in zip(QUANTILES, quantiles, strict=True):
            out.append(_quantile(histogram, edges, q * values.shape[0]))
    return {
        "min": low,
        "max": high,
        "mean": mean,
        "std": np.sqrt(np.maximum(0, variance)),
        "count": np.array([count]),
    } | {_quantile_key(q): np.array(out) for q, out in zip(QUANTILES, quantiles, strict=True)}


def _quantile_key(q: float) -> str:
    return f"q{int(q * 100):02d}"


def _sampled(n: int) -> list[int]:
    """The frames of an n-frame episode whose pixels enter a camera's statistics: all of them up to 100, then
    n^0.75 spread evenly (at most 10,000)."""
    count = max(min(n, 100), min(int(n**0.75), 10_000))
    return np.round(np.linspace(0, n - 1, count)).astype(int).tolist()


def camera_stats(frames: list[np.ndarray]) -> Stats:
    """Per-channel statistics in [0, 1], shape [3, 1, 1], over a sample of the frames (every k-th pixel of frames
    300 px or larger, k bringing the long side near 150 px)."""
    sample = np.stack([frames[i] for i in _sampled(len(frames))])
    height, width = sample.shape[1:3]
    if max(height, width) >= 300:
        step = int(width / 150) if width > height else int(height / 150)
        sample = sample[:, ::step, ::step]
    stats = feature_stats(sample.reshape(-1, sample.shape[-1]), len(sample))
    return {key: value if key == "count" else value.reshape(-1, 1, 1) / 255.0 for key, value in stats.items()}


def merge_stats(a: Stats, b: Stats) -> Stats:
    """Statistics of the union of two sets of frames from the statistics of each."""
    means, counts = np.stack([a["mean"], b["mean"]]), np.stack([a["count"], b["count"]])
    total = counts.sum(axis=0)
    weights = counts.reshape(counts.shape + (1,) * (means.ndim - counts.ndim))
    mean = (means * weights).sum(axis=0) / total
    # each std squared in its own dtype before the two are stacked, as LeRobot does it: the float32 of an episode's
    # camera statistics is then kept
    variances = np.stack([a["std"] ** 2, b["std"] ** 2])
    variance = ((variances + (means - mean) ** 2) * weights).sum(axis=0) / total
    merged = {
        "min": np.minimum(a["min"], b["min"]),
        "max": np.maximum(a["max"], b["max"]),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": total,
    }
    for key in map(_quantile_key, QUANTILES):
        merged[key] = (np.stack([a[key], b[key]]) * weights).sum(axis=0) / total
    return merged
