"""Maps over pi0-FAST's SigLIP tokens, explaining the logits upstream's decoding really used.

Definitions (docs/MAP_KINDS.md): to explain generated step k the score is the pre-softmax logit of the explained
token at the output that predicted step k in the *decoding* computation (`pi0_fast.replay_prelogits`: upstream's
prefill, its RoPE positions and its contiguous decode window, g_0..g_{k-1} fed back). G = dScore/dE where E [B, C, N, D]
are the image tokens after SigLIP's head (no gradient through SigLIP). Grad-CAM, per camera c:
alpha_c = mean over its N tokens of G_c [D];  map_c = ReLU(E_c @ alpha_c) reshaped to the patch grid (row-major).

The same backward pass also gives a gradient-norm map per camera, ||G_c[n]|| per token (a token-level saliency map,
Simonyan et al. 2014): Grad-CAM's mean over tokens assumes, as in a CNN's last conv layer, that a channel means the
same thing at every position and that activations are non-negative; neither holds for transformer tokens, which is
why the gradient norm is computed beside it (docs/MAP_KINDS.md compares the kinds). It gives gradient x input too,
sum_d E_c[n, d] G_c[n, d] per token; continued through SigLIP to the pixels it gives occlusion's first-order estimate
(`taylor`), and repeated at noisy copies of E, SmoothGrad (`smoothgrad`): `gradient_maps`.

Three more kinds compare the frame with a *baseline frame* a robot could see (`vocabulary.MapOptions.baseline`: the
frame blurred, or its mean colour), and are signed (positive = supports the explained score):
  ig         integrated gradients over E along the straight path E0 -> E, E0 = SigLIP tokens of the baseline frame
             (no gradient through SigLIP); its completeness terms come with the result (`IgCompleteness`).
  occlusion  the drop of the score when a region's pixels are replaced by the baseline's and the whole model re-run,
             one camera at a time; every region once ("regions") or random Bernoulli masks (ISS, "random").
  rise       the same re-runs under random patch masks of its own (RISE), beside occlusion's in one compiled call.
One more kind propagates the score back to the pixels with AttnLRP's rules (`model.lrp`), one modified backward pass
through the replay and SigLIP per explained score, in a program of its own:
  lrp        relevance = input x modified gradient at the model's input pixels, summed per patch; signed.
Scores: a token's logit at its decode step (`maps_for_steps`), or a sum of log-probabilities over decode steps (the
chunk, or any per-row list of steps: `maps_for_chunk`). `rescore_masks` returns the same scores with patches painted,
for the spot checks and faithfulness metrics. `gradcam_for_token` and `gradcam_for_action_token` are the Grad-CAM API
of one token (a counterfactual token too), over the same machinery.

Every entry point takes the generated sequence at its full decode length S (which sizes upstream's KV cache) and the
steps to explain as traced values. The replay runs the sequence only up to the last explained step, its length
bucketed (`replay_length`: powers of two from 16, capped at S), so the steps of a request share a few compilations
(explaining step 0, 5 or 9 shares one) and an early step does not pay for all S slots.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from openpi_cam.model import baseline_maps, gemma, gradient_maps, lrp, lrp_maps, remat
from openpi_cam.model.attribution import IgCompleteness
from openpi_cam.model.config import MAX_DECODING_STEPS, Pi0FASTConfig
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits
from openpi_cam.vocabulary import (
    BASELINE_KINDS,
    GRADIENT_KINDS,
    MODEL_KINDS,
    ONE_PASS_KINDS,
    OPTION_KINDS,
    RELEVANCE_KINDS,
    MapOptions,
    check_kinds,
)


@dataclasses.dataclass(frozen=True)
class MapResult:
    """Raw (unnormalised) maps per camera of every requested kind. Leading axis B (batch rows); multi-token targets
    add an axis T.

    `by_kind` holds each requested kind (camera -> float32 [B, Hp, Wp] or [B, T, Hp, Wp]; signed for ig, occlusion,
    gradxinput, taylor, rise and lrp; gradnorm's squares sum to `grad_norms`**2). `alphas` and `grad_norms` come
    from the gradient program's token pass and are empty when it did not run (none of gradcam, gradnorm, gradxinput,
    taylor was requested)."""

    target: str  # "token" | "tokens" | "chunk"
    cameras: tuple[str, ...]
    by_kind: dict[str, dict[str, np.ndarray]]  # kind -> camera -> map
    alphas: dict[str, np.ndarray]  # camera -> float32 [B, D] or [B, T, D]: Grad-CAM's channel weights
    grad_norms: dict[str, np.ndarray]  # camera -> float32 [B] or [B, T] (Frobenius norm of G over N x D)
    spans: dict[str, tuple[int, int]]  # camera -> [start, end) of its tokens in the (unaligned) prefix
    valid: dict[str, np.ndarray]  # camera -> bool [B]; a masked camera is invalid (its map is still reported)
    score: np.ndarray  # [B] or [B, T]
    token_ids: np.ndarray  # int32 [B, T]: the explained tokens
    decode_steps: np.ndarray  # int32 [T] (or [B, T] when rows explain different steps): the decode steps explained
    positions: np.ndarray  # int32 [B, T]: RoPE position of the output that predicted each explained token
    # float32 [B, V] or [B, T, V]: the full logit vector at that output (token targets asked for it with logits=True)
    logits: np.ndarray | None
    ig_completeness: IgCompleteness | None = None  # with "ig"
    options: MapOptions | None = None  # the map options, when a kind that depends on them was requested


def _gathered_logits(params: dict, pre: jax.Array, targets: jax.Array) -> jax.Array:
    """logit of targets[..., s] at output [..., s, :] without materialising [..., V]. pre [..., D] -> [...]"""
    table = params["PaliGemma"]["llm"]["embedder"]["input_embedding"]
    return jnp.einsum("...d,...d->...", pre, table[targets].astype(pre.dtype))


# The replay runs the generated sequence only as far as the last explained step, its length rounded up to a power of
# two (at least MIN_REPLAY, at most the decode length): a request's steps share at most log2(S / MIN_REPLAY) + 1
# compilations (5 for upstream's 256), and the shortest replay is barely longer than the prefix.
MIN_REPLAY = 16


def replay_length(last_step: int, decode_len: int) -> int:
    """Tokens of the generated sequence the replay feeds to explain steps up to `last_step`."""
    return min(decode_len, max(MIN_REPLAY, 1 << int(last_step).bit_length()))


def _replay(generated: jax.Array, last_step: int) -> tuple[jax.Array, int]:
    """(generated [B, S] cut to `replay_length`, the decode length S that sized the cache: static for the compiled
    cores)."""
    return generated[:, : replay_length(last_step, generated.shape[1])], int(generated.shape[1])


def _one_hot_rows(scores: jax.Array) -> jax.Array:
    """One cotangent per score row of scores [T, B]: [T, T, B], ones over the batch (rows are independent)."""
    t = scores.shape[0]
    return jnp.broadcast_to(jnp.eye(t, dtype=scores.dtype)[:, :, None], (t, *scores.shape))


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "logits", "program", "options"))
def _token_gradient_maps(
    params,
    obs,
    generated,
    targets,
    steps,
    inputs=None,
    *,
    cfg: Pi0FASTConfig,
    decode_len: int,
    logits: bool,
    program=gradient_maps.TOKEN_PASS,
    options=gradient_maps.COMPILED_DEFAULTS,
):
    """The gradient kinds of token targets (`gradient_maps.gradient_kinds` with passes `program`). steps int32 [T, B]:
    one VJP per explained step, all sharing one forward pass over generated [B, L] (`_replay`).

    Only the explained outputs [T, B, D] meet the vocabulary: the score is their dot product with the explained
    token's embedding row, and with `logits` the full logit vector is projected for those T rows alone (None
    without: the projection reads the whole [V, D] table, which the maps do not need)."""
    rows = jnp.arange(generated.shape[0])[None, :]

    def output_fn(image_tokens):
        explained = replay_prelogits(params, image_tokens, obs, generated, cfg, decode_len)[rows, steps]  # [T, B, D]
        return _gathered_logits(params, explained, targets[rows, steps]), explained  # [T, B]

    scores, explained, grad = gradient_maps.gradient_kinds(
        params, obs, cfg, output_fn, _one_hot_rows, program, options, inputs
    )
    full = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], explained).astype(jnp.float32) if logits else None
    return scores.astype(jnp.float32), grad, full


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "program", "options"))
def _chunk_gradient_maps(
    params,
    obs,
    generated,
    target,
    inputs=None,
    *,
    cfg: Pi0FASTConfig,
    decode_len: int,
    program=gradient_maps.TOKEN_PASS,
    options=gradient_maps.COMPILED_DEFAULTS,
):
    """The gradient kinds of a chunk target: score = sum_k weights[b, k] * log_softmax(logits_k)[g_k] over a
    `_weights_target`; one backward pass (per pass of `program`). -> score [B], maps [B, C, ...]."""
    score_fn = _score_fn(params, obs, generated, target, cfg, decode_len)
    score, _, grad = gradient_maps.gradient_kinds(
        params, obs, cfg, lambda e: (score_fn(e), None), _one_hot_rows, program, options, inputs
    )
    return score[0], {k: v[0] for k, v in grad.items()}


def _prepare(model: Pi0FAST, obs: Observation, generated: ArrayLike) -> tuple[Observation, jax.Array, np.ndarray]:
    obs = preprocess_observation(obs, model.config.image_resolution)
    tokens = np.asarray(generated).astype(np.int32)
    if tokens.ndim == 1:
        tokens = tokens[None]
    batch = obs.state.shape[0]
    if tokens.shape[0] != batch:
        raise ValueError(f"generated ids have {tokens.shape[0]} rows, the observation has {batch}")
    n = model.config.siglip.num_tokens
    cam_valid = np.stack([np.asarray(obs.image_masks[c], bool) for c in obs.images], axis=1)  # [B, C]
    prefill_len = cam_valid.sum(1) * n + np.asarray(obs.tokenized_prompt_mask, bool).sum(1)
    return obs, jnp.asarray(tokens), prefill_len


def _positions(prefill_len: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """RoPE position of the output predicting step k: the last prefix token for k = 0, else g_{k-1}'s slot.
    steps [B, T] -> [B, T]"""
    return np.where(steps == 0, prefill_len[:, None] - 1, prefill_len[:, None] + steps).astype(np.int32)


def _per_row(steps: ArrayLike, batch: int) -> tuple[np.ndarray, bool]:
    """Steps shared by every row ([T]) or given per row ([B, T]) -> ([B, T], whether they were shared)."""
    steps = np.asarray(steps, np.int32)
    if steps.ndim == 1:
        return np.broadcast_to(steps, (batch, steps.shape[0])), True
    if steps.ndim != 2 or steps.shape[0] != batch:
        raise ValueError(f"steps must be [T] or [B={batch}, T], got shape {steps.shape}")
    return steps, False


def _bucket(n: int) -> int:
    """Pads the number of explained tokens to a power of two so varying counts share a few compilations."""
    return 1 << max(0, (n - 1).bit_length())


def _token_target(ids: ArrayLike, steps_tb: np.ndarray) -> dict[str, jax.Array]:
    """The logits of ids [B, S] at decode steps steps_tb [T, B]."""
    return {"ids": jnp.asarray(ids), "steps": jnp.asarray(steps_tb)}


def _weights_target(weights: np.ndarray) -> dict[str, jax.Array]:
    """sum_k weights[b, k] log p(g_k), kept only at the K decode steps some row weights (padded with zero weights to
    a power of two, at least MIN_REPLAY, at most the replay's length), so the vocabulary projection is [B, K, V], not
    [B, S, V]: S is 256 on real checkpoints and V 257152. `weights` [B, L] (cut to the replay)."""
    cols = np.flatnonzero(np.any(weights != 0, axis=0))
    positions = np.zeros(min(weights.shape[1], max(MIN_REPLAY, _bucket(max(cols.size, 1)))), np.int32)
    positions[: cols.size] = cols
    w = np.zeros((weights.shape[0], positions.size), np.float32)
    w[:, : cols.size] = weights[:, cols]
    return {"weights": jnp.asarray(w), "positions": jnp.asarray(positions)}


def _scores_of(params: dict, pre: jax.Array, generated: jax.Array, target: dict[str, jax.Array]) -> jax.Array:
    """The explained scores [T, B] from the replay's pre-logits pre [B, L, D]: a token target's logits
    (`_token_target`), or a weights target's weighted log-prob sum as one row [1, B] (`_weights_target`)."""
    if "steps" in target:
        rows, steps = jnp.arange(generated.shape[0])[None, :], target["steps"]
        return _gathered_logits(params, pre[rows, steps], target["ids"][rows, steps]).astype(jnp.float32)
    positions = target["positions"]
    logits = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], pre[:, positions]).astype(jnp.float32)
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits, -1), generated[:, positions, None], -1)[..., 0]  # [B, K]
    return jnp.sum(target["weights"] * logp, axis=-1)[None]


def _score_fn(params, obs, generated, target, cfg, decode_len) -> Callable[[jax.Array], jax.Array]:
    """The explained scores (`_scores_of`) as a function of the image tokens E [B, C, N, D] -> [T, B], over the
    replay of generated [B, L] in a decode of `decode_len` steps."""

    def fn(image_tokens):
        pre = replay_prelogits(params, image_tokens, obs, generated, cfg, decode_len)
        return _scores_of(params, pre, generated, target)

    return fn


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "logits"))
def _relevance_maps(params, obs, generated, target, *, cfg: Pi0FASTConfig, decode_len: int, logits: bool):
    """The lrp kind of a token or weights target (`cfg` with rules "lrp", `lrp_maps.pixel_relevance`): one modified
    backward pass per score, through the replay and SigLIP to the pixels. Returns scores [T, B], relevance
    [T, B, C, N] and, for a token target with `logits`, the full logit vectors of the explained outputs [T, B, V]
    (else None)."""
    full = logits and "steps" in target

    def output_fn(image_tokens):
        pre = replay_prelogits(params, image_tokens, obs, generated, cfg, decode_len)
        explained = pre[jnp.arange(generated.shape[0])[None, :], target["steps"]] if full else None  # [T, B, D]
        return _scores_of(params, pre, generated, target), explained

    scores, explained, relevance = lrp_maps.pixel_relevance(params, obs, cfg, output_fn, _one_hot_rows)
    if full:
        explained = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], explained).astype(jnp.float32)
    return scores, relevance, explained


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "kinds", "options", "base_outputs", "logits"))
def _baseline_kinds(
    params,
    obs,
    generated,
    target,
    inputs,
    *,
    cfg: Pi0FASTConfig,
    decode_len: int,
    kinds,
    options,
    base_outputs,
    logits,
):
    """The kinds that compare with a baseline frame, for one target (token steps [T, B], or weights as T = 1): see
    `baseline_maps.baseline_kinds`. With `base_outputs` (no gradient pass ran) also "score" [T, B] and, for token
    targets with `logits`, "logits" [T, B, V]."""
    E = embed_images(params, obs, cfg)
    score_fn = _score_fn(params, obs, generated, target, cfg, decode_len)
    out = baseline_maps.baseline_kinds(params, obs, cfg, score_fn, E, inputs, kinds, options)
    if base_outputs:
        out["score"] = score_fn(E)
        if "steps" in target and logits:
            rows = jnp.arange(generated.shape[0])[None, :]
            pre = replay_prelogits(params, E, obs, generated, cfg, decode_len)[rows, target["steps"]]  # [T, B, D]
            out["logits"] = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], pre).astype(jnp.float32)
    return out


def backward_config(cfg: Pi0FASTConfig, tokens: int) -> Pi0FASTConfig:
    """The layout a token explanation of `tokens` (padded) steps differentiates with. One token: the Gemma stack
    unrolled over the same stacked parameters, unless it is rematerialised, because XLA:CPU differentiates one token
    through the unrolled stack faster (chosen by measurement, docs/DESIGN_NOTES.md). Inference keeps the served
    layout, and so do multi-token explanations and stacks with `remat`. Whether remat stays is the device's question
    (`remat.backward_layout`, which applies this rule to the remat-free config too)."""
    if tokens != 1 or cfg.gemma.remat:
        return cfg
    return dataclasses.replace(cfg, gemma=dataclasses.replace(cfg.gemma, scan=False))


def _baseline_outputs(
    model, obs, generated, target, *, decode_len, kinds, options, base_outputs, rows, logits=False
) -> tuple[dict[str, Any], int | None]:
    """`baseline_maps.collect` over this family's program (replaying generated [B, L] of a decode of `decode_len`
    steps) for the requested baseline kinds, nothing when there are none; with `base_outputs` also "score" [T, B] and
    with `logits` "logits" [T, B, V] (token targets). Every array is re-laid by `rows` and the IG step count taken
    out: (outputs, ig_steps)."""
    if not any(k in BASELINE_KINDS for k in kinds):
        return {}, None

    def run(kinds, options, inputs, first):
        return _baseline_kinds(
            model.params,
            obs,
            generated,
            target,
            inputs,
            cfg=model.config,
            decode_len=decode_len,
            kinds=kinds,
            options=options,
            base_outputs=base_outputs and first,
            logits=logits and base_outputs and first,
        )

    valid = baseline_maps.camera_validity(obs)
    extra = baseline_maps.collect(run, tuple(obs.images), model.config.siglip.grid, kinds, options, valid)
    ig_steps = extra.pop("ig_steps", None)
    return _map_tree(rows, extra), ig_steps


def _relevance_outputs(
    model, obs, generated, target, decode_len, logits, layout=lambda c: c
) -> tuple[jax.Array, jax.Array, jax.Array | None]:
    """`_relevance_maps` of one target in the model's config with rules "lrp", laid out by `layout` (the family's
    backward layout) and without remat where it fits the device (`remat.backward_layout`)."""
    args, static = (model.params, obs, generated, target), {"decode_len": decode_len, "logits": logits}
    cfg = remat.backward_layout(_relevance_maps, lrp.with_rules(model.config, "lrp"), args, static, layout)
    return _relevance_maps(*args, cfg=cfg, **static)


def _camera_maps(x: np.ndarray, cams: Sequence[str], grid: tuple[int, int]) -> dict[str, np.ndarray]:
    """[..., C, N] -> camera -> [..., Hp, Wp] (row-major patch grid)."""
    return {c: x[..., i, :].reshape(*x.shape[:-2], *grid) for i, c in enumerate(cams)}


def _result(
    model, obs, *, target, kinds, grad, relevance, score, logits, extra, ig_steps, token_ids, steps, positions, options
) -> MapResult:
    """grad: the gradient program's maps (`gradient_maps.gradient_kinds`) batch-first or None; relevance: the lrp
    kind's [..., C, N] batch-first or None; extra: `_baseline_outputs` made batch-first."""
    cams = tuple(obs.images)
    n = model.config.siglip.num_tokens
    grid = model.config.siglip.grid
    alphas, grad_norms, by_kind = {}, {}, {}
    if grad is not None:
        grad = {k: np.asarray(v) for k, v in grad.items()}
        by_kind.update({k: _camera_maps(grad[k], cams, grid) for k in GRADIENT_KINDS if k in kinds})
        if "alpha" in grad:  # the token pass ran
            token_norm = grad["gradnorm"].astype(np.float64)
            grad_norm = np.sqrt(np.sum(np.square(token_norm), axis=-1)).astype(np.float32)  # [..., C]
            alphas = {c: grad["alpha"][..., i, :] for i, c in enumerate(cams)}
            grad_norms = {c: grad_norm[..., i] for i, c in enumerate(cams)}
    if relevance is not None:
        by_kind["lrp"] = _camera_maps(np.asarray(relevance), cams, grid)
    by_kind.update({k: extra[k] for k in BASELINE_KINDS if k in extra})
    completeness = IgCompleteness(*extra["ig_check"], steps=ig_steps) if "ig_check" in extra else None
    return MapResult(
        target=target,
        cameras=cams,
        by_kind=by_kind,
        alphas=alphas,
        grad_norms=grad_norms,
        spans={c: (i * n, (i + 1) * n) for i, c in enumerate(cams)},
        valid={c: np.asarray(obs.image_masks[c], bool).reshape(-1) for c in cams},
        score=np.asarray(score),
        token_ids=np.asarray(token_ids, np.int32),
        decode_steps=np.asarray(steps, np.int32),
        positions=positions,
        logits=None if logits is None else np.asarray(logits),
        ig_completeness=completeness,
        options=options if any(k in OPTION_KINDS for k in kinds) else None,
    )


def _map_tree(fn: Callable[[np.ndarray], np.ndarray], tree: Any) -> Any:
    return jax.tree.map(fn, tree, is_leaf=lambda x: isinstance(x, np.ndarray))


def maps_for_steps(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    steps: ArrayLike,
    *,
    kinds: Sequence[str] = ONE_PASS_KINDS,
    options: MapOptions | None = None,
    logits: bool = True,
) -> MapResult:
    """The `kinds` maps of the generated tokens at `steps` ([T] for every row, or [B, T] per row; one map stack per
    camera), with one forward pass shared by all of them (per kind). `logits=False` leaves `MapResult.logits` None
    and skips projecting the explained outputs onto the whole vocabulary (the side channel's choice)."""
    obs, generated, prefill_len = _prepare(model, obs, generated_ids)
    return _explain_tokens(
        model,
        obs,
        generated,
        targets=generated,
        steps=steps,
        prefill_len=prefill_len,
        squeeze=False,
        kinds=kinds,
        options=options,
        with_logits=logits,
    )


def gradcam_for_action_token(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    step: int,
    *,
    kinds: Sequence[str] = ONE_PASS_KINDS,
    options: MapOptions | None = None,
    logits: bool = True,
) -> MapResult:
    """The seed's Grad-CAM API: Grad-CAM (and by default the gradient norm from the same backward pass; any `kinds`)
    of the generated token at decode `step`, one map per camera, no token axis; `logits` as in `maps_for_steps`."""
    obs, generated, prefill_len = _prepare(model, obs, generated_ids)
    return _explain_tokens(
        model,
        obs,
        generated,
        targets=generated,
        steps=[int(step)],
        prefill_len=prefill_len,
        squeeze=True,
        kinds=kinds,
        options=options,
        with_logits=logits,
    )


def gradcam_for_token(
    model: Pi0FAST,
    obs: Observation,
    *,
    token_id: int | Sequence[int],
    step: int | None = None,
    position: int | None = None,
    generated_prefix: ArrayLike | None = None,
    max_decoding_steps: int = MAX_DECODING_STEPS,
    kinds: Sequence[str] = ONE_PASS_KINDS,
    options: MapOptions | None = None,
) -> MapResult:
    """The seed's Grad-CAM API for any token: Grad-CAM (and by default the gradient norm; any `kinds`) of the logit
    of `token_id` at decode step `step` (or at the output with RoPE `position`), with `generated_prefix` =
    g_0 .. g_{step-1} fed back. `token_id` need not be the generated token (counterfactuals). `max_decoding_steps`
    must be the decode's setting: it sizes the KV cache that masked prefix rows attend over."""
    prefix = np.zeros((0,), np.int32) if generated_prefix is None else np.asarray(generated_prefix, np.int32)
    batch = obs.state.shape[0]
    prefix = np.broadcast_to(prefix, (batch, prefix.shape[-1])) if prefix.ndim == 1 else prefix
    padded = np.zeros((batch, max_decoding_steps), np.int32)
    padded[:, : prefix.shape[1]] = prefix
    obs, generated, prefill_len = _prepare(model, obs, padded)
    if (step is None) == (position is None):
        raise ValueError("give exactly one of step= or position=")
    if step is None:
        steps = {0 if position == p - 1 else position - p for p in prefill_len}
        if len(steps) != 1 or min(steps) < 0:
            raise ValueError(f"position {position} is not a decode output position for every row")
        step = steps.pop()
    if not 0 <= step < max_decoding_steps:
        raise ValueError(f"step {step} outside [0, {max_decoding_steps})")
    if prefix.shape[1] < step:
        raise ValueError(f"explaining step {step} needs the {step} tokens generated before it, got {prefix.shape[1]}")
    targets = padded.copy()
    targets[:, step] = np.broadcast_to(np.asarray(token_id, np.int32), (batch,))
    return _explain_tokens(
        model,
        obs,
        generated,
        targets=jnp.asarray(targets),
        steps=[step],
        prefill_len=prefill_len,
        squeeze=True,
        kinds=kinds,
        options=options,
        with_logits=True,
    )


def _token_steps(steps: ArrayLike, batch: int, length: int) -> tuple[np.ndarray, bool, np.ndarray]:
    """Validated steps ([B, T], shared?) and their padding to a power-of-two count, transposed: [T_pad, B]."""
    steps, shared = _per_row(steps, batch)
    if steps.size == 0:
        raise ValueError("no decode steps to explain")
    if steps.min() < 0 or steps.max() >= length:
        raise ValueError(f"decode steps {steps.tolist()} outside [0, {length})")
    t = steps.shape[1]
    padded = np.concatenate([steps, np.repeat(steps[:, :1], _bucket(t) - t, axis=1)], axis=1)  # [B, T_pad]
    return steps, shared, np.ascontiguousarray(padded.T)


def _explain_tokens(
    model: Pi0FAST,
    obs: Observation,
    generated: jax.Array,
    *,
    targets: jax.Array,
    steps: ArrayLike,
    prefill_len: np.ndarray,
    squeeze: bool,
    kinds: Sequence[str],
    options: MapOptions | None,
    with_logits: bool,
) -> MapResult:
    """Token targets: the logit of targets[b, k] (the generated token, or a counterfactual) at each decode step k of
    `steps`, replaying `generated`; `squeeze` drops the token axis of a single step."""
    kinds, options = check_kinds(kinds, MODEL_KINDS), options or MapOptions()
    batch = generated.shape[0]
    steps, shared, steps_tb = _token_steps(steps, batch, generated.shape[1])
    t = steps.shape[1]
    generated, decode_len = _replay(generated, steps.max())
    targets = targets[:, : generated.shape[1]]

    def batch_first(x):  # [T_pad, B, ...] -> [B, T, ...] (or [B, ...] for one token)
        x = np.moveaxis(np.asarray(x)[:t], 0, 1)
        return x[:, 0] if squeeze else x

    grad = score = logits = None
    if any(k in GRADIENT_KINDS for k in kinds):
        inputs, static = gradient_maps.program_arguments(kinds, options)
        args = (model.params, obs, generated, targets, jnp.asarray(steps_tb), inputs)
        static |= {"decode_len": decode_len, "logits": with_logits}
        tokens = steps_tb.shape[0]
        cfg = remat.backward_layout(
            _token_gradient_maps, model.config, args, static, lambda c: backward_config(c, tokens)
        )
        score, grad, logits = _token_gradient_maps(*args, cfg=cfg, **static)
        grad = {k: batch_first(v) for k, v in grad.items()}
        score = batch_first(score)
        logits = None if logits is None else batch_first(logits)
    target_spec = _token_target(targets, steps_tb)
    relevance = None
    if any(k in RELEVANCE_KINDS for k in kinds):
        tokens = steps_tb.shape[0]
        lrp_score, relevance, lrp_logits = _relevance_outputs(
            model, obs, generated, target_spec, decode_len, with_logits, lambda c: backward_config(c, tokens)
        )
        relevance = batch_first(relevance)
        if score is None:
            score, logits = batch_first(lrp_score), None if lrp_logits is None else batch_first(lrp_logits)
    extra, ig_steps = _baseline_outputs(
        model,
        obs,
        generated,
        target_spec,
        decode_len=decode_len,
        kinds=kinds,
        options=options,
        base_outputs=score is None,
        logits=with_logits,
        rows=batch_first,
    )
    if extra and score is None:
        score, logits = extra["score"], extra.get("logits")
    token_ids = np.take_along_axis(np.asarray(targets), steps, axis=1)
    return _result(
        model,
        obs,
        target="token" if squeeze else "tokens",
        kinds=kinds,
        grad=grad,
        relevance=relevance,
        score=score,
        logits=logits,
        extra=extra,
        ig_steps=ig_steps,
        token_ids=token_ids,
        steps=steps[0] if shared else steps,
        positions=_positions(prefill_len, steps),
        options=options,
    )


def chunk_weights(steps: ArrayLike, batch: int, length: int) -> tuple[np.ndarray, list[np.ndarray], bool]:
    """A chunk target's weights [B, S] (1 on the listed steps): `steps` is one list for every row or one per row.
    Also returns the per-row step arrays and whether they were shared."""
    shared = all(np.ndim(s) == 0 for s in steps)
    rows = [np.asarray(steps, np.int32)] * batch if shared else [np.asarray(r, np.int32) for r in steps]
    if len(rows) != batch or any(r.size == 0 for r in rows):
        raise ValueError(f"give one non-empty list of decode steps, or one per row (batch {batch})")
    if any(r.min() < 0 or r.max() >= length for r in rows):
        raise ValueError(f"decode steps outside [0, {length})")
    weights = np.zeros((batch, length), np.float32)
    for b, r in enumerate(rows):
        weights[b, r] = 1.0
    return weights, rows, shared


def maps_for_chunk(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    steps: ArrayLike,
    *,
    kinds: Sequence[str] = ONE_PASS_KINDS,
    options: MapOptions | None = None,
) -> MapResult:
    """The `kinds` maps of a whole-chunk target: score = sum over `steps` of log p(g_k); one backward pass, one map
    per camera.

    `steps` is one list for every row, or one list per row (lengths may differ: per-row `token_ids`,
    `decode_steps` and `positions` are then padded with -1)."""
    obs, generated, prefill_len = _prepare(model, obs, generated_ids)
    weights, rows, shared = chunk_weights(steps, generated.shape[0], generated.shape[1])
    return _explain_chunk(
        model,
        obs,
        generated,
        weights=weights,
        rows=rows,
        shared=shared,
        prefill_len=prefill_len,
        kinds=kinds,
        options=options,
    )


def _explain_chunk(
    model: Pi0FAST,
    obs: Observation,
    generated: jax.Array,
    *,
    weights: np.ndarray,
    rows: list[np.ndarray],
    shared: bool,
    prefill_len: np.ndarray,
    kinds: Sequence[str],
    options: MapOptions | None,
) -> MapResult:
    """A chunk target given as `chunk_weights` returns it: weights [B, S], the explained steps of each row and
    whether every row explains the same ones."""
    kinds, options = check_kinds(kinds, MODEL_KINDS), options or MapOptions()
    batch = generated.shape[0]
    padded = np.full((batch, max(r.size for r in rows)), -1, np.int32)
    for b, r in enumerate(rows):
        padded[b, : r.size] = r
    generated, decode_len = _replay(generated, max(r.max() for r in rows))
    target_spec = _weights_target(np.asarray(weights)[:, : generated.shape[1]])
    grad = score = None
    if any(k in GRADIENT_KINDS for k in kinds):
        inputs, static = gradient_maps.program_arguments(kinds, options)
        args, static = (model.params, obs, generated, target_spec, inputs), static | {"decode_len": decode_len}
        cfg = remat.backward_layout(_chunk_gradient_maps, model.config, args, static)
        score, grad = _chunk_gradient_maps(*args, cfg=cfg, **static)
    relevance = None
    if any(k in RELEVANCE_KINDS for k in kinds):
        lrp_score, relevance, _ = _relevance_outputs(model, obs, generated, target_spec, decode_len, False)
        relevance = np.asarray(relevance)[0]  # the one score row
        score = np.asarray(lrp_score)[0] if score is None else score
    extra, ig_steps = _baseline_outputs(
        model,
        obs,
        generated,
        target_spec,
        decode_len=decode_len,
        kinds=kinds,
        options=options,
        base_outputs=score is None,
        rows=lambda x: x[0],  # the one score row
    )
    if extra and score is None:
        score = extra["score"]
    valid = padded >= 0
    token_ids = np.where(valid, np.take_along_axis(np.asarray(generated), np.maximum(padded, 0), axis=1), -1)
    return _result(
        model,
        obs,
        target="chunk",
        kinds=kinds,
        grad=grad,
        relevance=relevance,
        score=score,
        logits=None,
        extra=extra,
        ig_steps=ig_steps,
        token_ids=token_ids,
        steps=rows[0] if shared else padded,
        positions=np.where(valid, _positions(prefill_len, np.maximum(padded, 0)), -1),
        options=options,
    )


# ----------------------------------------------------------------------------------------------------------------
# What the spot checks and faithfulness metrics need: the explained score with patches painted.


def _rescore_target(
    generated: jax.Array, steps: ArrayLike, weights: ArrayLike
) -> tuple[dict[str, jax.Array], int | None, jax.Array, int]:
    """(target for the rescoring core, T for token targets or None for weights, generated cut to the replay, the
    decode length)."""
    if (steps is None) == (weights is None):
        raise ValueError("give exactly one of steps= (token logits) or weights= (weighted log-prob sum)")
    if steps is not None:
        batch, length = generated.shape
        steps, _, steps_tb = _token_steps(np.atleast_1d(np.asarray(steps, np.int32)), batch, length)
        cut, decode_len = _replay(generated, steps.max())
        return _token_target(cut, steps_tb), steps.shape[1], cut, decode_len
    weights = np.broadcast_to(np.asarray(weights, np.float32), generated.shape)
    cut, decode_len = _replay(generated, np.flatnonzero(np.any(weights != 0, axis=0)).max(initial=0))
    return _weights_target(weights[:, : cut.shape[1]]), None, cut, decode_len


def _scores_out(scores: np.ndarray, t: int | None) -> np.ndarray:
    """[K, T_pad, B] -> [K, B, T] (token targets) or [K, B] (weights)."""
    scores = np.asarray(scores)
    return scores[:, 0] if t is None else np.moveaxis(scores[:, :t], 1, 2)


def rescore_masks(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    masks: Mapping[str, ArrayLike],
    *,
    steps: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    options: MapOptions | None = None,
) -> dict[str, np.ndarray]:
    """The explained score with patches painted by the baseline frame (`options`), one camera at a time.

    masks: camera -> bool [M, Hp, Wp] (True = painted; an all-False mask gives the unmodified score in the same
    numerics). Target: `steps` ([T] or [B, T]: logits of the generated tokens there) or `weights` ([S] or [B, S]:
    weighted log-prob sum). Every variant of every camera runs in one compiled call, in chunks of
    `options.mask_chunk`. -> camera -> [M, B, T] (steps) or [M, B] (weights)."""
    options = options or MapOptions()
    obs, generated, _ = _prepare(model, obs, generated_ids)
    target, t, generated, decode_len = _rescore_target(generated, steps, weights)
    cams = tuple(obs.images)
    per_camera = baseline_maps.checked_masks(masks, cams, model.config.siglip.grid)
    inputs, where = baseline_maps.variants(per_camera, options.mask_chunk)
    out = _baseline_kinds(
        model.params,
        obs,
        generated,
        target,
        inputs,
        cfg=model.config,
        decode_len=decode_len,
        kinds=("occlusion",),
        options=baseline_maps.compiled_options(options, ("occlusion",)),
        base_outputs=False,
        logits=False,
    )
    scores = _scores_out(out["occlusion_scores"], t)
    return {c: scores[s] for c, s in zip(cams, where, strict=True) if c in masks}
