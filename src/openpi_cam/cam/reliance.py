"""Reliance: how much an explained inference depends on each camera and on its prompt, measured by intervention.

For each camera the model saw, the whole camera is replaced by the baseline frame its maps use (`MapOptions`: the
frame's mean colour or a blurred copy) and the model run again; for the prompt, the prompt is emptied (its state
tokens kept) and the model run again. Each reports two changes against the served call:

- `score_drop`: the explained score minus the score of the same output under the intervention (the score the maps
  explain, re-run by `Explainer.rescore`; a camera's is the spot check's re-scoring with every patch painted);
- `action_change`: the root mean square, over the chunk, of the difference between the actions the policy returns
  under the intervention and the served actions, in the robot's action units (`Policy.resample`: the served call's
  noise and state, the same sampler and output transforms).

A camera the model masks (pi0.5's blank right wrist) has none. A score drop needs one explained score: for a target
with a score per token (`all-action-tokens`) only the action change is measured. Best effort like the spot check: a
failure is recorded as `Reliance(skipped="failed_<Error>")` and the step keeps its maps.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Protocol

import jax
import numpy as np
from jax.sharding import Mesh

from openpi_cam.cam.run_format import Dependence, Reliance
from openpi_cam.model.attribution import baseline_images
from openpi_cam.model.observation import Observation
from openpi_cam.policies.family import Explainer, ExplainSkipped, Explanation
from openpi_cam.policies.policy import InferenceTrace
from openpi_cam.vocabulary import MapOptions

EMPTY_PROMPT = ""


class Resampler(Protocol):
    """What reliance needs of the policy (`policies.policy.Policy`)."""

    def resample(self, trace: InferenceTrace, observation: Observation) -> np.ndarray: ...

    def served_actions(self, trace: InferenceTrace) -> np.ndarray: ...

    def with_prompt(self, trace: InferenceTrace, prompt: str) -> Observation: ...


def without_camera(observation: Observation, camera: str, options: MapOptions) -> Observation:
    """The observation with one camera's image replaced by its baseline frame (`attribution.baseline_images`)."""
    image = observation.images[camera]
    valid = np.ones(np.shape(image)[:1], bool)
    replaced = np.asarray(baseline_images(np.asarray(image, np.float32), valid, options))
    return dataclasses.replace(observation, images={**observation.images, camera: replaced})


def action_change(actions: np.ndarray, served: np.ndarray) -> float:
    """Root mean square over the chunk of the difference, in the actions' units."""
    a, b = np.asarray(actions, np.float64), np.asarray(served, np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def reliance(
    policy: Resampler,
    explainer: Explainer,
    trace: InferenceTrace,
    explanation: Explanation,
    options: MapOptions,
    *,
    mesh: Mesh | None = None,
) -> Reliance:
    """The reliance of one traced, explained inference (module docstring), stored as `StepMeta.reliance`: a score
    drop is None where the target has several scores. With a `mesh`, `explainer` is placed on it."""
    try:
        cameras = [c for c, info in explanation.cameras.items() if info.get("valid", True)]
        output = np.asarray(trace.output)[None]
        drawn = {k: np.asarray(v)[None] for k, v in trace.sample_inputs.items()}
        meta = {"target": explanation.target, **explanation.details}
        emptied = policy.with_prompt(trace, EMPTY_PROMPT)
        served_actions = policy.served_actions(trace)
        with jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext():
            try:
                grid = tuple(explanation.cameras[cameras[0]]["grid"]) if cameras else ()
                masks = {c: np.stack([np.zeros(grid, bool), np.ones(grid, bool)]) for c in cameras}
                painted = explainer.rescore(trace.observation, output, drawn, meta, masks, options) if cameras else {}
                nothing = {c: np.zeros((1, *grid), bool) for c in cameras[:1]}
                prompted = explainer.rescore(emptied, output, drawn, meta, nothing, options) if cameras else {}
            except ExplainSkipped:
                painted, prompted = {}, {}
        scores = {c: np.asarray(s, np.float64) for c, s in painted.items()}
        score = float(scores[cameras[0]][0]) if scores else None
        relied = {}
        for c in cameras:
            changed = policy.resample(trace, without_camera(trace.observation, c, options))
            drop = None if c not in scores else float(scores[c][0] - scores[c][1])
            relied[c] = Dependence(drop, action_change(changed, served_actions))
        changed = policy.resample(trace, emptied)
        drop = None if score is None else score - float(np.asarray(next(iter(prompted.values())))[0])
        return Reliance(score, relied, Dependence(drop, action_change(changed, served_actions)))
    except Exception as e:
        return Reliance(skipped=f"failed_{type(e).__name__}", error=str(e)[:200])
