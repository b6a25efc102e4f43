"""pi0 and pi0.5 behind the family seam: the flow-matching model, its prompt tokenizer and transforms, its sampler
(which records the noise it used) and its `Explainer`.

The server's noise stream is upstream's: the policy splits its rng once per call and the noise is
`jax.random.normal(split, (1, action_horizon, action_dim))`, unless the caller passes `noise=` to `Policy.infer`.
The explainer re-runs the whole denoising from that same noise, so the explained actions are the returned ones (the
difference is stored per step as `replay_max_abs_diff`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sentencepiece

from openpi_cam.errors import InvalidRequest
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0 import Pi0
from openpi_cam.model.pi0_maps import CHUNK, maps_for_actions, rescore_masks
from openpi_cam.model.safetensors_weights import LEROBOT_HEADS, HeadCounts
from openpi_cam.policies.config import PolicyConfig
from openpi_cam.policies.family import (
    ExplainSkipped,
    Explanation,
    ModelExplainer,
    Sampler,
    baseline_details,
    feature_signals,
    head_details,
    model_kinds,
    request_head,
    requested_maps,
    resolve_target,
)
from openpi_cam.tokenizers.paligemma import load_paligemma_tokenizer
from openpi_cam.tokenizers.pi0 import Pi0PromptTokenizer
from openpi_cam.transforms import PadStatesAndActions, PassActions, TokenizePrompt
from openpi_cam.vocabulary import DEFAULT_TARGETS, ExplainOptions, MapOptions


class FlowExplainer(ModelExplainer):
    """Explains pi0 / pi0.5 action chunks: target `action` (dimension d at horizon step h) or `chunk`."""

    targets = ("action", "chunk")
    default_target = DEFAULT_TARGETS["pi0"]

    def __init__(self, model: Pi0) -> None:
        self.model = model

    def _with_model(self, model: Any) -> FlowExplainer:
        return FlowExplainer(model)

    def explain(
        self,
        observation: Observation,
        outputs: np.ndarray,
        request: ExplainOptions,
        sample_inputs: Mapping[str, np.ndarray] | None = None,
    ) -> list[Explanation | ExplainSkipped]:
        request = dataclasses.replace(request, target=resolve_target(self, request.target))
        if sample_inputs is None or "noise" not in sample_inputs:
            raise ValueError("explaining a flow-matching policy needs the served call's noise")
        cfg = self.model.config
        target = CHUNK
        if request.target == "action":
            target = (request.action_index, request.action_dim_index)
            if not (target[0] < cfg.action_horizon and target[1] < cfg.action_dim):
                reason = f"action {target} requested, the chunk is [{cfg.action_horizon}, {cfg.action_dim}]"
                return [ExplainSkipped("action_index_out_of_range", reason)] * len(outputs)
        head = request_head(self, request)
        kinds = model_kinds(request, head)
        res = maps_for_actions(
            self.model, observation, sample_inputs["noise"], [target], kinds=kinds, options=request.map_options
        )
        replay_diff = np.abs(res.actions - np.asarray(outputs, np.float32)).max(axis=(1, 2))
        grid = list(self.camera_grid)
        return [
            Explanation(
                target=request.target,
                maps=requested_maps(
                    request,
                    head,
                    {k: {c: np.asarray(m[b, 0], np.float32) for c, m in res.by_kind[k].items()} for k in kinds},
                ),
                score=float(res.score[b, 0]),
                cameras={
                    c: {"valid": bool(res.valid[c][b]), "grid": grid, "span": list(res.spans[c])} for c in res.cameras
                },
                details={
                    "action_index": None if target == CHUNK else list(target),
                    "replay_max_abs_diff": float(replay_diff[b]),
                    **baseline_details(res.ig_completeness, res.options, (b, 0)),
                    **head_details(request, head),
                },
            )
            for b in range(len(outputs))
        ]

    def rescore(
        self,
        observation: Observation,
        outputs: np.ndarray,
        sample_inputs: Mapping[str, np.ndarray],
        explained: Mapping[str, Any],
        masks: Mapping[str, np.ndarray],
        options: MapOptions,
    ) -> dict[str, np.ndarray]:
        index = explained.get("action_index")
        target = CHUNK if explained["target"] == "chunk" else tuple(index)
        noise = np.asarray(sample_inputs["noise"], np.float32)
        # the logged chunk weighs the chunk target, so an observation other than the served one (another prompt)
        # is scored by the explained score itself
        chunk = np.asarray(outputs, np.float32)
        scores = rescore_masks(self.model, observation, noise, masks, [target], options=options, explained=chunk)
        return {c: s[:, 0, 0] for c, s in scores.items()}


@dataclasses.dataclass(frozen=True)
class FlowParts:
    """What `create_policy` needs from the family, built from local files only."""

    model: Pi0
    tokenizer: Pi0PromptTokenizer
    tokenize: tuple[TokenizePrompt, PadStatesAndActions]  # the last input transforms
    decoder: PassActions
    explainer: FlowExplainer
    sample: Sampler


def flow_sampler(model: Pi0) -> Sampler:
    """The family's `Sampler`: each row's noise drawn as upstream's `sample_actions` draws it for a batch of one from
    that request's key, or the caller's `noise` [horizon, action dim]; returns the chunk, the noise and, asked, the
    pooled features of the same call."""

    def sample(
        rngs: Sequence[jax.Array], observation: Observation, noise: np.ndarray | None, *, signals: bool = False
    ) -> tuple[np.ndarray, dict, dict]:
        shape = (observation.state.shape[0], model.config.action_horizon, model.config.action_dim)
        if noise is None:
            drawn = jnp.concatenate([jax.random.normal(rng, (1, *shape[1:])) for rng in rngs])
        elif np.size(noise) != np.prod(shape):
            raise InvalidRequest(
                f"noise must have shape {list(shape[1:])} (horizon, action dim), got {np.shape(noise)}"
            )
        else:
            drawn = jnp.asarray(noise, jnp.float32).reshape(shape)
        if not signals:
            actions = jax.block_until_ready(model.sample_actions(rngs[0], observation, noise=drawn))
            return np.asarray(actions), {"noise": np.asarray(drawn)}, {}
        actions, recorded = jax.block_until_ready(model.sample_with_signals(observation, drawn))
        return np.asarray(actions), {"noise": np.asarray(drawn)}, feature_signals(jax.device_get(recorded))

    return sample


def build_pi0(
    config: PolicyConfig,
    weights: Path,
    *,
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None,
    dtype: str,
    heads: HeadCounts = LEROBOT_HEADS,
) -> FlowParts:
    """The model restored from `weights` (an orbax `params` directory, or a PyTorch `model.safetensors` whose head
    counts `heads` gives) and the PaliGemma tokenizer (None: upstream's cache location)."""
    if not isinstance(paligemma_tokenizer, sentencepiece.SentencePieceProcessor):
        paligemma_tokenizer = load_paligemma_tokenizer(paligemma_tokenizer)
    tokenizer = Pi0PromptTokenizer(paligemma_tokenizer, config.max_token_len)
    data_config = {"action_horizon": config.action_horizon, "max_token_len": config.max_token_len, "dtype": dtype}
    if weights.suffix == ".safetensors":
        model = Pi0.from_safetensors(weights, heads=heads, **data_config)
    else:
        model = Pi0.from_checkpoint(weights, **data_config)
    if model.family != config.family:
        raise ValueError(f"config {config.name!r} serves {config.family}, the checkpoint is a {model.family} model")
    if model.config.action_dim != config.action_dim:
        raise ValueError(
            f"config {config.name!r} pads states and actions to {config.action_dim} dims, the checkpoint's "
            f"action projections have {model.config.action_dim}"
        )
    tokenize = (TokenizePrompt(tokenizer, config.discrete_state_input), PadStatesAndActions(config.action_dim))
    return FlowParts(model, tokenizer, tokenize, PassActions(), FlowExplainer(model), flow_sampler(model))
