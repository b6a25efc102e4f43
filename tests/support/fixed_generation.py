"""A real policy whose traces carry a chosen well-formed generation.

The tiny upstream DROID model has random weights and never writes `Action: `, so a trace of it has no FAST action
token to explain. Everything else stays real (transforms, model inputs, inference, actions); only the trace's
model output (`InferenceTrace.output`, the generated ids) is swapped for e.g. upstream's hand-made
`hand/generated_tokens`, the way a trained checkpoint's output looks, and its `malformed_reason` is the one the
policy's tokenizer gives that generation. Grad-CAM of those tokens on the real inputs is then a real computation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from openpi_cam.policies.pi0_fast_family import FastExplainer


class FixedGeneration:
    """`policy` with every trace's output replaced by `tokens`; with `model`, its explainer runs on that model
    (e.g. a wrapper that blocks or fails; it needs `params`, `config` and `camera_grid` like `Pi0FAST`) and the
    policy's tokenizer."""

    def __init__(self, policy: Any, tokens: np.ndarray, model: Any = None):
        self.inner = policy
        self.tokens = np.asarray(tokens, np.int32)
        self.model = model if model is not None else policy.model
        tokenizer = policy.explainer.tokenizer
        self._explainer = policy.explainer if model is None else FastExplainer(model, tokenizer)
        cfg = policy.model.config
        self._reason = tokenizer.extract_actions_checked(self.tokens, cfg.action_horizon, cfg.action_dim)[1]

    metadata = property(lambda self: self.inner.metadata)
    explainer = property(lambda self: self._explainer)
    tokenizer = property(lambda self: self._explainer.tokenizer)  # shorthand: `Policy` itself has no `.tokenizer` now

    def infer(self, obs, context=None):
        return self.inner.infer(obs, context)

    def infer_traced(self, obs):
        response, trace = self.inner.infer_traced(obs)
        return response, dataclasses.replace(trace, output=self.tokens, malformed_reason=self._reason)

    def stats(self):
        return self.inner.stats()

    def close(self, timeout=None):
        pass
