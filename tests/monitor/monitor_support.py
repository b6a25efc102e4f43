"""Synthetic labelled rollouts for the monitor's tests: each step has a pooled feature and a STAC value; a failed
episode drifts away from the successful steps' distribution from its `onset` step on."""

from __future__ import annotations

import numpy as np

from openpi_cam.monitor.fit import Episode

FEATURE = "features/base_0_rgb"
DIM = 6
# A fixed correlated covariance for every step's feature (its square root), and the direction failures drift along.
_ROOT = np.linalg.cholesky(np.eye(DIM) + 0.6 * np.ones((DIM, DIM)))
DRIFT = np.array([1.0, -1.0, 0.5, 0.0, 0.0, 0.0]) / 1.5


def episode(
    rng: np.random.Generator, success: bool, *, steps: int = 16, onset: int = 5, drift: float = 2.0, noise_dims: int = 0
) -> Episode:
    """One episode; `noise_dims` appends that many independent unit-variance inputs to the feature (width without
    signal, as a pooled layer has)."""
    features = np.concatenate([rng.normal(size=(steps, DIM)) @ _ROOT.T, rng.normal(size=(steps, noise_dims))], axis=1)
    stac = np.abs(rng.normal(scale=0.3, size=steps))
    if not success:
        features[onset:, :DIM] += drift * DRIFT
        stac[onset:] += 0.5
    stac[0] = np.nan  # the first call has no previous chunk
    return Episode({FEATURE: features, "stac": stac}, success)


def episodes(seed: int, successes: int, failures: int, **kwargs) -> list[Episode]:
    rng = np.random.default_rng(seed)
    return [episode(rng, i < successes, **kwargs) for i in range(successes + failures)]
