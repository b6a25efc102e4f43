"""The seam between a model family and everything above it.

`Policy`, the explanation side channel and offline explanation see a family only through these types: a `Policy` holds
the family's model, its output decoder and its `Explainer`; the side channel hands the explainer the exact model
inputs and outputs of a served call and gets one `Explanation` (or `ExplainSkipped`) per batch row. pi0-FAST is
`policies.pi0_fast_family`; the flow-matching families (pi0, pi0.5) plug in the same way.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, Literal, Protocol

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from openpi_cam.model import occlusion_head
from openpi_cam.model.attribution import IgCompleteness
from openpi_cam.model.init import randomized
from openpi_cam.model.observation import Observation
from openpi_cam.vocabulary import (
    ACTION_FEATURES,
    FEATURES_PREFIX,
    OCCLUSION_HEAD,
    PROMPT_FEATURES,
    ExplainOptions,
    MapOptions,
    Target,
)


@dataclasses.dataclass(frozen=True)
class Explanation:
    """The maps of one explained inference (one batch row), ready to be logged."""

    target: str  # the target actually explained (the fallback for a malformed generation)
    maps: dict[str, dict[str, np.ndarray]]  # kind -> camera -> float32 (Hp, Wp), or (T, Hp, Wp) for T scores
    score: float | list[float]  # the differentiated score(s)
    cameras: dict[str, dict[str, Any]]  # camera -> {"valid", "grid", "span"}, in the model's camera order
    details: dict[str, Any]  # family-specific JSON fields (pi0-FAST: token_ids, decode_steps, positions, ...)


class ExplainSkipped(Exception):
    """This row cannot be explained with the request; `reason` names why (counted, not an error)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


class Explainer(Protocol):
    """Computes maps for a family's inferences from their exact model inputs and outputs."""

    @property
    def camera_grid(self) -> tuple[int, int]: ...

    @property
    def family(self) -> str:
        """The model family explained: "pi0_fast", "pi0" or "pi05"."""
        ...

    @property
    def targets(self) -> tuple[str, ...]:
        """The targets this family explains."""
        ...

    @property
    def default_target(self) -> Target:
        """What a request that names no target explains."""
        ...

    def explain(
        self,
        observation: Observation,
        outputs: np.ndarray,
        request: ExplainOptions,
        sample_inputs: Mapping[str, np.ndarray],
    ) -> list[Explanation | ExplainSkipped]:
        """`observation` [B, ...], `outputs` [B, ...] (the model's raw outputs: generated token ids, or actions) and
        `sample_inputs` (what else the sampler drew, each [B, ...]: pi0's noise) of B inferences -> one result per
        row, in row order."""
        ...

    def on_mesh(self, mesh: Mesh | None) -> Explainer:
        """The same explainer with its parameters placed on every device of `mesh` (itself for None)."""
        ...

    def rescore(
        self,
        observation: Observation,
        outputs: np.ndarray,
        sample_inputs: Mapping[str, np.ndarray],
        explained: Mapping[str, Any],
        masks: Mapping[str, np.ndarray],
        options: MapOptions,
    ) -> dict[str, np.ndarray]:
        """The score a logged explanation explained (`explained`: its step metadata: target, decode steps or action
        index), for one inference (B = 1) with patches painted by the baseline frame of `options`, one camera at a
        time: masks camera -> bool [M, Hp, Wp] -> camera -> scores [M]. Raises `ExplainSkipped` for a target with
        several scores."""
        ...

    def randomized(self, scope: Literal["llm", "all"], seed: int) -> Explainer:
        """The same explainer over freshly initialised weights: the language model's only (`llm`: SigLIP kept), or
        every weight (`all`); for the model randomisation test of a map kind."""
        ...


# How the families are named to people (messages); the seam's `family` strings are the checkpoints' own names.
FAMILY_LABELS = {"pi0_fast": "pi0-FAST", "pi0": "pi0", "pi05": "pi0.5"}


def resolve_target(explainer: Explainer, target: str | None) -> Target:
    """The target a request explains: `target`, or the family's default for None. A target the family cannot explain
    is refused in one line naming those it can (e.g. "action-token: pi0.5 explains action, chunk")."""
    if target is None:
        return explainer.default_target
    if target not in explainer.targets:
        label = FAMILY_LABELS.get(explainer.family, explainer.family)
        raise ValueError(f"{target}: {label} explains {', '.join(explainer.targets)}")
    return target  # type: ignore[return-value]  (one of the family's targets)


def request_head(explainer: Explainer, request: ExplainOptions) -> occlusion_head.OcclusionHead | None:
    """The occlusion head a request applies (None when it does not ask for the `occlusion-head` kind); a request
    without one, or with one fitted for another family or target, is refused in one line. `request.target` must be
    resolved."""
    if OCCLUSION_HEAD not in request.maps:
        return None
    if request.occlusion_head is None:
        raise ValueError(
            f"{OCCLUSION_HEAD} needs a head file: --head FILE (serve: --cam.head FILE); `openpi-cam head fit` fits one"
        )
    head = occlusion_head.load_ref(request.occlusion_head)
    if head.family != explainer.family or head.target != request.target:
        raise ValueError(
            f"{request.occlusion_head.path}: the occlusion head was fitted on {head.target} maps of a "
            f"{FAMILY_LABELS.get(head.family, head.family)} policy; this explains {request.target} of a "
            f"{FAMILY_LABELS.get(explainer.family, explainer.family)} policy"
        )
    return head


def model_kinds(request: ExplainOptions, head: occlusion_head.OcclusionHead | None) -> tuple[str, ...]:
    """The kinds the model computes for a request: those it asks for, `occlusion-head` standing for its head's
    inputs."""
    kinds = (head.inputs if k == OCCLUSION_HEAD and head is not None else (k,) for k in request.maps)
    return tuple(dict.fromkeys(k for group in kinds for k in group))


def requested_maps(
    request: ExplainOptions,
    head: occlusion_head.OcclusionHead | None,
    computed: Mapping[str, dict[str, np.ndarray]],
) -> dict[str, dict[str, np.ndarray]]:
    """The maps a row carries, in the request's order, from the maps the model computed for it (`model_kinds`): an
    input kind of the head only when asked for, and `occlusion-head` as the head applied to the inputs' maps."""
    return {k: head.predict(computed) if k == OCCLUSION_HEAD and head else computed[k] for k in request.maps}


def head_details(request: ExplainOptions, head: occlusion_head.OcclusionHead | None) -> dict[str, Any]:
    """The step metadata of the `occlusion-head` kind: which head (its file's SHA-256) and which kinds it read."""
    if head is None or request.occlusion_head is None:
        return {}
    return {"occlusion_head": {"sha256": request.occlusion_head.sha256, "inputs": list(head.inputs)}}


class OutputDecoder(Protocol):
    """Turns the model's raw output of one inference into a normalised action chunk."""

    def extract(self, output: np.ndarray) -> tuple[np.ndarray, str | None]:
        """(actions [horizon, action_dim], why the output was malformed or None)."""
        ...


class Sampler(Protocol):
    """A family's inference over B requests: (raw output [B, ...], what else was drawn, e.g. {"noise": [B, H, A]},
    and with `signals` what a failure monitor reads of the same call, each [B, ...] under `vocabulary`'s names:
    pooled last-layer features and, for pi0-FAST, the token entropies and action-token flags; {} without). Row i is
    what sampling request i alone with `rngs[i]` gives (B = 1 is upstream's call); `noise` None draws it from the
    rngs as upstream does. The raw output is the same with signals or without."""

    def __call__(
        self, rngs: Sequence[jax.Array], observation: Observation, noise: np.ndarray | None, *, signals: bool = False
    ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]: ...


def feature_signals(pooled: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """A model's pooled features (`cameras`: camera -> [B, D], `prompt` and, where present, `actions` [B, D]) under
    their signal names (`features/<camera>`, `features/prompt`, `features/actions`), float32 on the host."""
    named = {FEATURES_PREFIX + camera: x for camera, x in pooled["cameras"].items()}
    named[PROMPT_FEATURES] = pooled["prompt"]
    if "actions" in pooled:
        named[ACTION_FEATURES] = pooled["actions"]
    return {name: np.asarray(x, np.float32) for name, x in named.items()}


def baseline_details(completeness: IgCompleteness | None, options: MapOptions | None, index: Any) -> dict[str, Any]:
    """The step metadata of the baseline kinds for one explained row (`index` into the [B, ...] arrays): the
    options they ran with and IG's completeness check (sum of attributions = score - baseline score)."""
    details: dict[str, Any] = {}
    if options is not None:
        details["map_options"] = dataclasses.asdict(options)
    if completeness is not None:

        def at(x: np.ndarray) -> float | list[float]:
            value = np.asarray(x, np.float64)[index]
            return float(value) if np.ndim(value) == 0 else [float(v) for v in value]

        details["ig_completeness"] = {
            "score": at(completeness.score),
            "baseline_score": at(completeness.baseline_score),
            "attribution_sum": at(completeness.attribution_sum),
            "relative_error": at(completeness.relative_error),
            "steps": completeness.steps,
        }
    return details


class ModelExplainer:
    """What every family's explainer shares: a model whose `params` can be swapped (placed on a mesh, or randomised)
    while everything else stays; a subclass says how to rebuild itself around another model (`_with_model`)."""

    model: Any  # the family's model: `config`, `params`, `camera_grid`

    def _with_model(self, model: Any) -> Explainer:
        raise NotImplementedError

    def _with_params(self, params: dict) -> Explainer:
        model = copy.copy(self.model)
        model.params = params
        return self._with_model(model)

    @property
    def camera_grid(self) -> tuple[int, int]:
        return self.model.camera_grid

    @property
    def family(self) -> str:
        return self.model.family

    def on_mesh(self, mesh: Mesh | None) -> Explainer:
        if mesh is None:
            return self  # type: ignore[return-value]
        return self._with_params(jax.device_put(self.model.params, NamedSharding(mesh, PartitionSpec())))

    def randomized(self, scope: Literal["llm", "all"], seed: int) -> Explainer:
        return self._with_params(randomized(self.model.params, scope, jax.random.key(seed)))
