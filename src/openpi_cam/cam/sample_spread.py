"""The action-sample spread of a served call (SAFE's sample-based uncertainty, for flow-matching policies): how far
chunks drawn for the same input from other noises stray from one another, served chunk included.

It costs samples - 1 more denoisings of the call's input, so it is computed only where a monitor reads it or a dataset
job is asked for it, and never before a response is sent. The extra noises are drawn from the served noise itself (its
bytes seed them): the same call gives the same spread live and offline, whoever computes it and in whatever order.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from openpi_cam.monitor.signals import SAMPLE_SPREAD, sample_spread
from openpi_cam.policies.policy import InferenceTrace
from openpi_cam.vocabulary import NORMALIZED_CHUNK


class Resampling(Protocol):
    def normalized_chunks(self, trace: InferenceTrace, noises: np.ndarray) -> np.ndarray: ...


def check_samples(samples: int) -> None:
    if samples < 2:
        raise ValueError(f"the sample spread compares >= 2 action samples per call, got {samples}")


def extra_noises(noise: np.ndarray, samples: int) -> np.ndarray:
    """The samples - 1 noises beside a served one [horizon, action dim], drawn from its bytes."""
    served = np.ascontiguousarray(noise, np.float32)
    rng = np.random.default_rng(np.frombuffer(served.tobytes(), np.uint32))
    return rng.standard_normal((samples - 1, *served.shape[-2:])).astype(np.float32)


def with_sample_spread(policy: Resampling, trace: InferenceTrace, samples: int) -> dict[str, np.ndarray]:
    """The call's signals with `sample_spread` beside them: the spread (`monitor.signals.sample_spread`) of its
    served normalised chunk and samples - 1 more from `extra_noises`. ValueError (one line) for a policy that draws
    no noise (pi0-FAST) or a call served without signals (`Policy.normalized_chunks`)."""
    check_samples(samples)
    noise = trace.sample_inputs.get("noise")
    if noise is None:
        raise ValueError(f"{SAMPLE_SPREAD}: the policy draws no noise (pi0-FAST decodes greedily); pi0 / pi0.5 only")
    chunks = policy.normalized_chunks(trace, extra_noises(noise, samples))
    served = np.asarray(trace.signals[NORMALIZED_CHUNK], np.float64)[None]
    return {**trace.signals, SAMPLE_SPREAD: np.float64(sample_spread(np.concatenate([served, chunks])))}
