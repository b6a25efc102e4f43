"""Maps over pi0-FAST's SigLIP tokens, explaining the logits upstream's decoding really used.

Definition (README, "Grad-CAM"): to explain generated step k the score is the pre-softmax logit of the explained
token at the output that predicted step k in the *decoding* computation (`pi0_fast.replay_prelogits`: upstream's
prefill, its RoPE positions and its contiguous decode window, g_0..g_{k-1} fed back). G = dScore/dE where E [B, C, N, D]
are the image tokens after SigLIP's head (no gradient through SigLIP). Per camera c:
alpha_c = mean over its N tokens of G_c [D];  map_c = ReLU(E_c @ alpha_c) reshaped to the patch grid (row-major).

The same backward pass also gives a gradient-norm map per camera, ||G_c[n]|| per token (a token-level saliency map,
Simonyan et al. 2014): Grad-CAM's mean over tokens assumes, as in a CNN's last conv layer, that a channel means the
same thing at every position and that activations are non-negative; neither holds for transformer tokens, and on the
bundled demo model Grad-CAM peaks on the named block at chance while the gradient norm finds it (README).

Every entry point takes the generated sequence at its full decode length S (which sizes upstream's KV cache) and the
steps to explain as traced values, so explaining step 0, 5 or 9 of a request reuses one compilation.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from openpi_cam.model import gemma
from openpi_cam.model.attribution import gradcam_reduce
from openpi_cam.model.config import MAX_DECODING_STEPS, Pi0FASTConfig
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits


@dataclasses.dataclass(frozen=True)
class GradCamResult:
    """Raw (unnormalised) maps per camera. Leading axis B (batch rows); multi-token targets add an axis T."""

    target: str  # "token" | "tokens" | "chunk"
    cameras: tuple[str, ...]
    maps: dict[str, np.ndarray]  # camera -> float32 [B, Hp, Wp] or [B, T, Hp, Wp]
    alphas: dict[str, np.ndarray]  # camera -> float32 [B, D] or [B, T, D]
    grad_norms: dict[str, np.ndarray]  # camera -> float32 [B] or [B, T] (Frobenius norm of G over N x D)
    gradnorm_maps: dict[str, np.ndarray]  # camera -> like `maps`: ||G[n]|| per token (its squares sum to grad_norm**2)
    spans: dict[str, tuple[int, int]]  # camera -> [start, end) of its tokens in the (unaligned) prefix
    valid: dict[str, np.ndarray]  # camera -> bool [B]; a masked camera is invalid (its map is still reported)
    score: np.ndarray  # [B] or [B, T]
    token_ids: np.ndarray  # int32 [B, T]: the explained tokens
    decode_steps: np.ndarray  # int32 [T] (or [B, T] when rows explain different steps): the decode steps explained
    positions: np.ndarray  # int32 [B, T]: RoPE position of the output that predicted each explained token
    logits: np.ndarray | None  # float32 [B, V] or [B, T, V]: the full logit vector at that output (token targets)


def _gathered_logits(params: dict, pre: jax.Array, targets: jax.Array) -> jax.Array:
    """logit of targets[b, s] at output [b, s] without materialising [B, S, V]. -> [B, S]"""
    table = params["PaliGemma"]["llm"]["embedder"]["input_embedding"]
    return jnp.einsum("bsd,bsd->bs", pre, table[targets].astype(pre.dtype))


@functools.partial(jax.jit, static_argnames=("cfg",))
def _token_cams(params, obs, fed, targets, steps, *, cfg: Pi0FASTConfig):
    """steps int32 [T, B]: one VJP per explained step, all sharing one forward pass.

    The backward passes run as a `lax.map` over cotangents, not `vmap`: under jax 0.10.2 on CPU, `vmap` of this
    VJP returned wrong gradients for all but the first cotangent at real prefix lengths (B=2, 816 tokens), while
    `lax.map` and single VJPs agree (tests/test_gradcam.py compares the stack with the per-token loop)."""
    E = embed_images(params, obs, cfg)

    def scores_fn(image_tokens):
        pre = replay_prelogits(params, image_tokens, obs, fed, cfg)
        return _gathered_logits(params, pre, targets), pre

    scores, vjp_fn, pre = jax.vjp(scores_fn, E, has_aux=True)
    cotangents = jax.nn.one_hot(steps, fed.shape[1], dtype=scores.dtype)  # [T, B, S]
    G = jax.lax.map(lambda cot: vjp_fn(cot)[0], cotangents)  # [T, B, C, N, D]
    alpha, cam, token_norm = gradcam_reduce(E, G)
    rows = jnp.arange(fed.shape[0])
    explained_pre = pre[rows[None, :], steps]  # [T, B, D]
    logits = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], explained_pre).astype(jnp.float32)
    score = scores[rows[None, :], steps]  # [T, B]
    return score.astype(jnp.float32), alpha, cam, token_norm, logits


@functools.partial(jax.jit, static_argnames=("cfg",))
def _chunk_cam(params, obs, fed, weights, *, cfg: Pi0FASTConfig):
    """Score = sum_k weights[b, k] * log_softmax(logits_k)[g_k]; one backward pass."""
    E = embed_images(params, obs, cfg)

    def score_fn(image_tokens):
        pre = replay_prelogits(params, image_tokens, obs, fed, cfg)
        logits = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], pre).astype(jnp.float32)
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits, -1), fed[..., None], -1)[..., 0]
        return jnp.sum(weights * logp, axis=-1)  # [B]

    score, vjp_fn = jax.vjp(score_fn, E)
    (G,) = vjp_fn(jnp.ones_like(score))
    alpha, cam, token_norm = gradcam_reduce(E, G)
    return score, alpha, cam, token_norm


def _prepare(model: Pi0FAST, obs: Observation, generated: ArrayLike) -> tuple[Observation, jax.Array, np.ndarray]:
    obs = preprocess_observation(obs, model.config.image_resolution)
    fed = np.asarray(generated).astype(np.int32)
    if fed.ndim == 1:
        fed = fed[None]
    batch = obs.state.shape[0]
    if fed.shape[0] != batch:
        raise ValueError(f"generated ids have {fed.shape[0]} rows, the observation has {batch}")
    n = model.config.siglip.num_tokens
    cam_valid = np.stack([np.asarray(obs.image_masks[c], bool) for c in obs.images], axis=1)  # [B, C]
    prefill_len = cam_valid.sum(1) * n + np.asarray(obs.tokenized_prompt_mask, bool).sum(1)
    return obs, jnp.asarray(fed), prefill_len


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


def _result(model, obs, target, alpha, cam, token_norm, score, token_ids, steps, positions, logits) -> GradCamResult:
    cams = tuple(obs.images)
    n = model.config.siglip.num_tokens
    grid = model.config.siglip.grid
    cam, token_norm = np.asarray(cam), np.asarray(token_norm)
    grad_norm = np.sqrt(np.sum(np.square(token_norm.astype(np.float64)), axis=-1)).astype(np.float32)  # [..., C]
    return GradCamResult(
        target=target,
        cameras=cams,
        maps={c: cam[..., i, :].reshape(*cam.shape[:-2], *grid) for i, c in enumerate(cams)},
        alphas={c: np.asarray(alpha)[..., i, :] for i, c in enumerate(cams)},
        grad_norms={c: grad_norm[..., i] for i, c in enumerate(cams)},
        gradnorm_maps={c: token_norm[..., i, :].reshape(*token_norm.shape[:-2], *grid) for i, c in enumerate(cams)},
        spans={c: (i * n, (i + 1) * n) for i, c in enumerate(cams)},
        valid={c: np.asarray(obs.image_masks[c], bool).reshape(-1) for c in cams},
        score=np.asarray(score),
        token_ids=np.asarray(token_ids, np.int32),
        decode_steps=np.asarray(steps, np.int32),
        positions=positions,
        logits=None if logits is None else np.asarray(logits),
    )


def gradcam_for_steps(model: Pi0FAST, obs: Observation, generated_ids: ArrayLike, steps: ArrayLike) -> GradCamResult:
    """Explains the generated tokens at `steps` ([T] for every row, or [B, T] per row; one map stack per camera),
    with one forward pass shared by all of them."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    return _explain_tokens(model, obs, fed, fed, steps, prefill_len, False)


def gradcam_for_action_token(model: Pi0FAST, obs: Observation, generated_ids: ArrayLike, step: int) -> GradCamResult:
    """Explains the generated token at decode `step` (one map per camera, no token axis)."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    return _explain_tokens(model, obs, fed, fed, [int(step)], prefill_len, True)


def gradcam_for_token(
    model: Pi0FAST,
    obs: Observation,
    *,
    token_id: int | Sequence[int],
    step: int | None = None,
    position: int | None = None,
    generated_prefix: ArrayLike | None = None,
    max_decoding_steps: int = MAX_DECODING_STEPS,
) -> GradCamResult:
    """Explains the logit of `token_id` at decode step `step` (or at the output with RoPE `position`), with
    `generated_prefix` = g_0 .. g_{step-1} fed back. `token_id` need not be the generated token (counterfactuals).
    `max_decoding_steps` must be the decode's setting: it sizes the KV cache that masked prefix rows attend over."""
    prefix = np.zeros((0,), np.int32) if generated_prefix is None else np.asarray(generated_prefix, np.int32)
    batch = obs.state.shape[0]
    prefix = np.broadcast_to(prefix, (batch, prefix.shape[-1])) if prefix.ndim == 1 else prefix
    fed = np.zeros((batch, max_decoding_steps), np.int32)
    fed[:, : prefix.shape[1]] = prefix
    obs, fed_j, prefill_len = _prepare(model, obs, fed)
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
    targets = fed.copy()
    targets[:, step] = np.broadcast_to(np.asarray(token_id, np.int32), (batch,))
    return _explain_tokens(model, obs, fed_j, jnp.asarray(targets), [step], prefill_len, True)


def _explain_tokens(model, obs, fed, targets, steps, prefill_len, squeeze) -> GradCamResult:
    batch = fed.shape[0]
    steps, shared = _per_row(steps, batch)
    if steps.size == 0:
        raise ValueError("no decode steps to explain")
    if steps.min() < 0 or steps.max() >= fed.shape[1]:
        raise ValueError(f"decode steps {steps.tolist()} outside [0, {fed.shape[1]})")
    t = steps.shape[1]
    padded = np.concatenate([steps, np.repeat(steps[:, :1], _bucket(t) - t, axis=1)], axis=1)  # [B, T_pad]
    score, alpha, cam, token_norm, logits = _token_cams(
        model.params, obs, fed, targets, jnp.asarray(padded.T), cfg=model.config
    )

    def batch_first(x):  # [T_pad, B, ...] -> [B, T, ...] (or [B, ...] for one token)
        x = np.moveaxis(np.asarray(x)[:t], 0, 1)
        return x[:, 0] if squeeze else x

    token_ids = np.take_along_axis(np.asarray(targets), steps, axis=1)
    return _result(
        model,
        obs,
        "token" if squeeze else "tokens",
        batch_first(alpha),
        batch_first(cam),
        batch_first(token_norm),
        batch_first(score),
        token_ids,
        steps[0] if shared else steps,
        _positions(prefill_len, steps),
        batch_first(logits),
    )


def gradcam_for_chunk(
    model: Pi0FAST, obs: Observation, generated_ids: ArrayLike, steps: ArrayLike | Sequence[ArrayLike]
) -> GradCamResult:
    """Whole-chunk target: score = sum over `steps` of log p(g_k); one backward pass, one map per camera.

    `steps` is one list for every row, or one list per row (lengths may differ: per-row `token_ids`,
    `decode_steps` and `positions` are then padded with -1)."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    batch = fed.shape[0]
    shared = all(np.ndim(s) == 0 for s in steps)
    rows = [np.asarray(steps, np.int32)] * batch if shared else [np.asarray(r, np.int32) for r in steps]
    if len(rows) != batch or any(r.size == 0 for r in rows):
        raise ValueError(f"give one non-empty list of decode steps, or one per row (batch {batch})")
    width = max(r.size for r in rows)
    padded = np.full((batch, width), -1, np.int32)
    weights = np.zeros(fed.shape, np.float32)
    for b, r in enumerate(rows):
        padded[b, : r.size] = r
        weights[b, r] = 1.0
    score, alpha, cam, token_norm = _chunk_cam(model.params, obs, fed, jnp.asarray(weights), cfg=model.config)
    valid = padded >= 0
    token_ids = np.where(valid, np.take_along_axis(np.asarray(fed), np.maximum(padded, 0), axis=1), -1)
    positions = np.where(valid, _positions(prefill_len, np.maximum(padded, 0)), -1)
    return _result(
        model, obs, "chunk", alpha, cam, token_norm, score, token_ids, rows[0] if shared else padded, positions, None
    )
