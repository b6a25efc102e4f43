"""Fitted scorers of a step's inputs and the input basis they share. Each scores many steps at once: x [T, F] -> [T],
a larger score meaning a step that looks more like failure. The fitting lives in `monitor.fit`; these are the fitted
arrays and their arithmetic, which the monitor file stores and the side channel runs.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Basis:
    """Standardised inputs, optionally projected onto principal directions: z = ((x - mean) / scale) @ components.T.

    mean, scale: [F]; components: [k, F] with orthonormal rows, or None (z is the standardised x, k = F). A
    non-finite input (a signal a step lacks, e.g. STAC on an episode's first call) is imputed by its mean, so it
    counts as typical rather than poisoning the score."""

    mean: np.ndarray
    scale: np.ndarray
    components: np.ndarray | None = None

    @property
    def dims(self) -> int:
        return int(self.mean.shape[0] if self.components is None else self.components.shape[0])

    def standardise(self, x: np.ndarray) -> np.ndarray:
        """x: [T, F] -> [T, F], imputed."""
        x = np.asarray(x, np.float64)
        return np.where(np.isfinite(x), (x - self.mean) / self.scale, 0.0)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """x: [T, F] -> z: [T, k]."""
        z = self.standardise(x)
        return z if self.components is None else z @ self.components.T

    def residual_sq(self, x: np.ndarray) -> np.ndarray:
        """The squared norm of what the projection leaves out of each standardised step: [T, F] -> [T] (zeros
        without a projection)."""
        z = self.standardise(x)
        if self.components is None:
            return np.zeros(z.shape[0])
        return np.maximum((z**2).sum(axis=1) - ((z @ self.components.T) ** 2).sum(axis=1), 0.0)


@dataclasses.dataclass(frozen=True)
class MahalanobisScorer:
    """The Mahalanobis distance of each step to the successful steps the scorer was fitted on, under a
    probabilistic-PCA covariance: sqrt((z - center)^T precision (z - center) + residual_sq / residual_variance).
    center: [k]; precision: [k, k], the inverse of the (shrunk) covariance of their basis coordinates z;
    residual_variance: the variance each direction the projection left out had in those steps, on average (0: no
    projection, or nothing left out, and no residual term). Without the residual term, a step departing along a
    direction successful steps barely vary in (where a failure may well show) would score as typical."""

    center: np.ndarray
    precision: np.ndarray
    residual_variance: float = 0.0

    def score(self, z: np.ndarray, residual_sq: np.ndarray | None = None) -> np.ndarray:
        d = np.asarray(z, np.float64) - self.center
        d2 = np.einsum("ti,ij,tj->t", d, self.precision, d)
        if self.residual_variance > 0 and residual_sq is not None:
            d2 = d2 + np.asarray(residual_sq, np.float64) / self.residual_variance
        return np.sqrt(np.maximum(d2, 0.0))


@dataclasses.dataclass(frozen=True)
class ProbeScorer:
    """A logistic probe's log-odds that the step belongs to a failed episode: z @ weights + bias. The log-odds, not
    the probability, because the monitor only ranks and thresholds scores, and the probability rounds to exactly 1.0
    in floating point far from the boundary, where distinct steps would tie. weights: [k]; bias: a float."""

    weights: np.ndarray
    bias: float

    def score(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z, np.float64) @ self.weights + self.bias


def with_running_mean(x: np.ndarray) -> np.ndarray:
    """The temporal input: each step's inputs beside the mean of its episode's inputs so far (itself included), so
    a step is scored with the path that led to it. x: [T, F] -> [T, 2F]. Non-finite entries stay out of the means
    (NaN until one is seen)."""
    x = np.asarray(x, np.float64)
    finite = np.isfinite(x)
    sums = np.cumsum(np.where(finite, x, 0.0), axis=0)
    counts = np.cumsum(finite, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return np.concatenate([x, means], axis=1)
