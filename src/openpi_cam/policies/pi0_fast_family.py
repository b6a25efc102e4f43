"""pi0-FAST behind the family seam: its model, tokenizer, input/output transforms, and its `Explainer`.

Targets map onto decode steps of the generation: the FAST action tokens are the generated tokens after `Action: `
and before `|` / EOS (found by the tokenizer). A generation without action tokens (upstream then returns zero
actions) is explained with the `generated-tokens` target instead of being skipped: score = sum of the
log-probabilities of every token the model emitted, up to and including EOS.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
import sentencepiece

from openpi_cam.errors import InvalidRequest
from openpi_cam.model import pi0_fast_maps
from openpi_cam.model.config import EOS_TOKEN
from openpi_cam.model.observation import Observation
from openpi_cam.model.occlusion_head import OcclusionHead
from openpi_cam.model.pi0_fast import Pi0FAST
from openpi_cam.model.pi0_fast_maps import MapResult
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
from openpi_cam.tokenizers.fast import FastActionTokenizer, resolve_fast_tokenizer_dir
from openpi_cam.tokenizers.paligemma import load_paligemma_tokenizer
from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer
from openpi_cam.transforms import ExtractFASTActions, TokenizeFASTInputs
from openpi_cam.vocabulary import (
    ACTION_TOKENS,
    DEFAULT_TARGETS,
    FALLBACK_TARGET,
    TOKEN_ENTROPIES,
    ExplainOptions,
    MapOptions,
)

TOKEN_TARGETS = ("action-token", "all-action-tokens")  # one score per explained token
SEQUENCE_TARGETS = ("chunk", FALLBACK_TARGET)  # one score: a sum of log-probabilities


def generated_steps(tokens: np.ndarray) -> np.ndarray:
    """Decode steps of every token the model emitted: up to and including the first EOS (all steps without one)."""
    tokens = np.asarray(tokens).reshape(-1)
    eos = np.flatnonzero(tokens == EOS_TOKEN)
    return np.arange(eos[0] + 1 if eos.size else tokens.size, dtype=np.int32)


@dataclasses.dataclass(frozen=True)
class _RowPlan:
    target: str  # the target this row is explained with
    steps: np.ndarray  # int32 decode steps of its score(s)
    action_indices: list[int] | None  # which action tokens, when the target is made of them


def _plan(tokenizer: Pi0FastTokenizer, tokens: np.ndarray, request: ExplainOptions) -> _RowPlan | ExplainSkipped:
    """What one row's request explains, or why it cannot."""
    if request.target == FALLBACK_TARGET:
        return _RowPlan(FALLBACK_TARGET, generated_steps(tokens), None)
    steps = np.asarray(tokenizer.action_token_steps(tokens), np.int32)
    if steps.size == 0:
        return _RowPlan(FALLBACK_TARGET, generated_steps(tokens), None)
    if request.target == "action-token":
        if request.action_index >= steps.size:
            return ExplainSkipped(
                "action_index_out_of_range",
                f"action token {request.action_index} requested, generation has {steps.size}",
            )
        return _RowPlan("action-token", steps[[request.action_index]], [request.action_index])
    return _RowPlan(request.target, steps, list(range(steps.size)))


class FastExplainer(ModelExplainer):
    """Explains pi0-FAST generations; every call explains a whole batch (a single inference is a batch of one)."""

    targets = (*TOKEN_TARGETS, *SEQUENCE_TARGETS)
    default_target = DEFAULT_TARGETS["pi0_fast"]

    def __init__(self, model: Pi0FAST, tokenizer: Pi0FastTokenizer) -> None:
        self.model = model
        self.tokenizer = tokenizer

    def _with_model(self, model: Any) -> FastExplainer:
        return FastExplainer(model, self.tokenizer)

    def explain(
        self,
        observation: Observation,
        outputs: np.ndarray,
        request: ExplainOptions,
        sample_inputs: Mapping[str, np.ndarray] | None = None,
    ) -> list[Explanation | ExplainSkipped]:
        request = dataclasses.replace(request, target=resolve_target(self, request.target))
        generated = np.asarray(outputs, np.int32)
        rows = int(np.shape(observation.state)[0])
        if generated.ndim != 2 or generated.shape[0] != rows:
            raise ValueError(f"outputs must be generated token ids [B, S] with B = {rows}, got {generated.shape}")
        plans = [_plan(self.tokenizer, row, request) for row in generated]
        results: list[Explanation | ExplainSkipped | None] = [
            p if isinstance(p, ExplainSkipped) else None for p in plans
        ]
        head = request_head(self, request)
        maps_args = {"kinds": model_kinds(request, head), "options": request.map_options}
        token_rows = [b for b, p in enumerate(plans) if isinstance(p, _RowPlan) and p.target in TOKEN_TARGETS]
        sequence_rows = [b for b, p in enumerate(plans) if isinstance(p, _RowPlan) and p.target in SEQUENCE_TARGETS]
        # Each group is one model call over the whole batch (rows outside it ride along on a harmless step), so that
        # every batch of one size shares one compilation per group.
        if token_rows:
            res = pi0_fast_maps.maps_for_steps(
                self.model, observation, generated, _step_matrix(plans, token_rows), **maps_args, logits=False
            )
            for b in token_rows:
                results[b] = self._row(res, b, plans[b], request, head)  # type: ignore[arg-type]
        if sequence_rows:
            lists = [p.steps if b in sequence_rows else np.zeros(1, np.int32) for b, p in enumerate(plans)]
            res = pi0_fast_maps.maps_for_chunk(self.model, observation, generated, lists, **maps_args)
            for b in sequence_rows:
                results[b] = self._row(res, b, plans[b], request, head)  # type: ignore[arg-type]
        return [r for r in results if r is not None]

    def _row(
        self, res: MapResult, b: int, plan: _RowPlan, request: ExplainOptions, head: OcclusionHead | None
    ) -> Explanation:
        t = plan.steps.size
        if plan.target in SEQUENCE_TARGETS:
            index: Any = b
            score: float | list[float] = float(res.score[b])
        elif plan.target == "action-token":
            index = (b, 0)
            score = float(res.score[b, 0])
        else:
            index = (b, slice(0, t))
            score = [float(s) for s in res.score[b, :t]]
        grid = list(self.camera_grid)
        details = {
            "token_ids": [int(x) for x in np.asarray(res.token_ids)[b, :t]],
            "decode_steps": [int(s) for s in plan.steps],
            "positions": [int(p) for p in np.asarray(res.positions)[b, :t]],
            "action_indices": plan.action_indices,
        }
        return Explanation(
            target=plan.target,
            maps=requested_maps(
                request,
                head,
                {
                    k: {c: np.asarray(m[index], np.float32) for c, m in per_camera.items()}
                    for k, per_camera in res.by_kind.items()
                },
            ),
            score=score,
            cameras={
                c: {"valid": bool(res.valid[c][b]), "grid": grid, "span": list(res.spans[c])} for c in res.cameras
            },
            details=details | baseline_details(res.ig_completeness, res.options, index) | head_details(request, head),
        )

    def rescore(
        self,
        observation: Observation,
        outputs: np.ndarray,
        sample_inputs: Mapping[str, np.ndarray],
        explained: Mapping[str, Any],
        masks: Mapping[str, np.ndarray],
        options: MapOptions,
    ) -> dict[str, np.ndarray]:
        steps = np.asarray(explained["decode_steps"], np.int32)
        target = explained["target"]
        generated = np.asarray(outputs, np.int32).reshape(1, -1)
        if target in SEQUENCE_TARGETS:
            weights = np.zeros(generated.shape, np.float32)
            weights[0, steps] = 1.0
            scores = pi0_fast_maps.rescore_masks(
                self.model, observation, generated, masks, weights=weights, options=options
            )
            return {c: s[:, 0] for c, s in scores.items()}
        if target == "action-token":
            scores = pi0_fast_maps.rescore_masks(
                self.model, observation, generated, masks, steps=steps[:1], options=options
            )
            return {c: s[:, 0, 0] for c, s in scores.items()}
        raise ExplainSkipped("multi_score_target", f"target {target!r} has one score per token; rescore needs one")


def _step_matrix(plans: Sequence[_RowPlan | ExplainSkipped], rows: Sequence[int]) -> np.ndarray:
    """[B, T] decode steps for a token-target call: a row with fewer steps repeats its first one (the model pads T
    the same way), rows outside `rows` explain step 0."""
    width = max(plans[b].steps.size for b in rows)  # type: ignore[union-attr]
    steps = np.zeros((len(plans), width), np.int32)
    for b in rows:
        own = plans[b].steps  # type: ignore[union-attr]
        steps[b] = np.concatenate([own, np.repeat(own[:1], width - own.size)])
    return steps


def generation_signals(
    tokenizer: Pi0FastTokenizer, generated: np.ndarray, recorded: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """What a failure monitor reads of B generations (`Pi0FAST.sample_with_signals`'s arrays on the host): the
    pooled prefix features, `features/actions` (the mean of the pre-logits that chose each action token, float32 [D];
    NaN for a generation without action tokens), each token's entropy and the flags of the action tokens (the
    tokens `extract_actions` reads, as the explainer's targets find them)."""
    hidden = np.asarray(recorded["hidden"])
    flags = np.zeros(generated.shape, bool)
    pooled = np.full((generated.shape[0], hidden.shape[-1]), np.nan, np.float32)
    for b, row in enumerate(generated):
        steps = np.asarray(tokenizer.action_token_steps(row), np.int64)
        flags[b, steps] = True
        if steps.size:
            pooled[b] = hidden[b, steps].astype(np.float64).mean(axis=0)
    return {
        **feature_signals({**recorded, "actions": pooled}),
        TOKEN_ENTROPIES: np.asarray(recorded["entropy"], np.float32),
        ACTION_TOKENS: flags,
    }


@dataclasses.dataclass(frozen=True)
class FastParts:
    """What `create_policy` needs from the family, built from local files only."""

    model: Pi0FAST
    tokenizer: Pi0FastTokenizer
    tokenize: tuple[TokenizeFASTInputs]  # the last input transform(s)
    decoder: ExtractFASTActions  # the first output step
    explainer: FastExplainer
    sample: Sampler


def build_pi0_fast(
    config: PolicyConfig,
    params_dir: Path,
    *,
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None,
    fast_tokenizer: str | Path | FastActionTokenizer | None,
    dtype: str,
    max_decoding_steps: int,
    stop_at_action_end: bool,
) -> FastParts:
    """The model restored from `params_dir` and both tokenizers (None: upstream's cache locations)."""
    if not isinstance(paligemma_tokenizer, sentencepiece.SentencePieceProcessor):
        paligemma_tokenizer = load_paligemma_tokenizer(paligemma_tokenizer)
    if not isinstance(fast_tokenizer, FastActionTokenizer):
        fast_tokenizer = FastActionTokenizer.load(resolve_fast_tokenizer_dir(fast_tokenizer))
    tokenizer = Pi0FastTokenizer(paligemma_tokenizer, fast_tokenizer, config.max_token_len)
    model = Pi0FAST.from_checkpoint(
        params_dir,
        action_dim=config.action_dim,
        action_horizon=config.action_horizon,
        max_token_len=config.max_token_len,
        dtype=dtype,
    )
    stop_ids = tuple(tokenizer.end_of_action_token_ids) if stop_at_action_end else ()

    def sample(
        rngs: Sequence[jax.Array], observation: Observation, noise: np.ndarray | None, *, signals: bool = False
    ) -> tuple[np.ndarray, dict, dict]:
        if noise is not None:
            raise InvalidRequest("pi0-FAST decodes tokens: it takes no noise")
        # Greedy decoding draws nothing from the rng; `rows_alone` ends each row at its own EOS, as if served alone
        # (for one row it is upstream's loop).
        decoding = {"max_decoding_steps": max_decoding_steps, "stop_token_ids": stop_ids, "rows_alone": True}
        if not signals:
            tokens = model.sample_actions(rngs[0], observation, **decoding)
            return np.asarray(jax.block_until_ready(tokens)).astype(np.int32), {}, {}
        tokens, recorded = model.sample_with_signals(rngs[0], observation, **decoding)
        generated = np.asarray(jax.block_until_ready(tokens)).astype(np.int32)
        return generated, {}, generation_signals(tokenizer, generated, jax.device_get(recorded))

    decoder = ExtractFASTActions(tokenizer, action_horizon=config.action_horizon, action_dim=config.action_dim)
    return FastParts(
        model, tokenizer, (TokenizeFASTInputs(tokenizer),), decoder, FastExplainer(model, tokenizer), sample
    )
