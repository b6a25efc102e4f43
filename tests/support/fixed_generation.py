"""A real policy whose traces carry a chosen well-formed generation.

The tiny upstream DROID model has random weights and never writes `Action: `, so a trace of it has no FAST action
token to explain. Everything else stays real (transforms, model inputs, inference, actions); only the trace's
generated tokens are swapped for e.g. upstream's hand-made `hand/generated_tokens`, the way a trained checkpoint's
output looks. Grad-CAM of those tokens on the real inputs is then a real computation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


class FixedGeneration:
    def __init__(self, policy: Any, tokens: np.ndarray, model: Any = None):
        self.inner = policy
        self.tokens = np.asarray(tokens, np.int32)
        self.model = model if model is not None else policy.model

    tokenizer = property(lambda self: self.inner.tokenizer)
    metadata = property(lambda self: self.inner.metadata)

    def infer(self, obs, context=None):
        return self.inner.infer(obs, context)

    def infer_traced(self, obs):
        response, trace = self.inner.infer_traced(obs)
        return response, dataclasses.replace(trace, generated_tokens=self.tokens)

    def stats(self):
        return self.inner.stats()

    def close(self, timeout=None):
        pass
