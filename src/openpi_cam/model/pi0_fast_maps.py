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

Two more kinds compare the frame with a *baseline frame* a robot could see (`vocabulary.MapOptions.baseline`: the
frame blurred, or its mean colour), and are signed (positive = supports the explained score):
  ig         integrated gradients over E along the straight path E0 -> E, E0 = SigLIP tokens of the baseline frame
             (no gradient through SigLIP); its completeness terms come with the result (`IgCompleteness`).
  occlusion  the drop of the score when a region's pixels are replaced by the baseline's and the whole model re-run,
             one camera at a time; every region once ("regions") or random Bernoulli masks (ISS, "random").
Scores: a token's logit at its decode step, or a weighted sum of log-probabilities over decode steps (the chunk and
any per-row list of steps, `maps_for_weights`). The re-scoring functions (`rescore_masks`, `rescore_images`) return the
same scores for image variants, for faithfulness metrics (`openpi_cam.cam.faithfulness`).

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

from openpi_cam.model import baseline_maps, gemma, remat
from openpi_cam.model.attribution import IgCompleteness, gradcam_reduce
from openpi_cam.model.config import MAX_DECODING_STEPS, Pi0FASTConfig
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits
from openpi_cam.vocabulary import BASELINE_KINDS, DEFAULT_KINDS, GRADIENT_KINDS, MapOptions, check_kinds


@dataclasses.dataclass(frozen=True)
class GradCamResult:
    """Raw (unnormalised) maps per camera. Leading axis B (batch rows); multi-token targets add an axis T.

    `maps`, `alphas`, `grad_norms` and `gradnorm_maps` come from the gradient pass and are empty when neither
    "gradcam" nor "gradnorm" was requested; `by_kind` holds every requested kind (signed for ig and occlusion)."""

    target: str  # "token" | "tokens" | "chunk" | "weights"
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
    # float32 [B, V] or [B, T, V]: the full logit vector at that output (token targets asked for it with logits=True)
    logits: np.ndarray | None
    by_kind: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)  # kind -> camera -> like maps
    ig_completeness: IgCompleteness | None = None  # with "ig"
    options: MapOptions | None = None  # the options of the baseline kinds, when any was requested


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


def _replay(fed: jax.Array, last_step: int) -> tuple[jax.Array, int]:
    """(fed cut to `replay_length`, the decode length S that sized the cache: static for the compiled cores)."""
    return fed[:, : replay_length(last_step, fed.shape[1])], int(fed.shape[1])


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "logits"))
def _token_cams(params, obs, fed, targets, steps, *, cfg: Pi0FASTConfig, decode_len: int, logits: bool):
    """steps int32 [T, B]: one VJP per explained step, all sharing one forward pass over fed [B, L] (`_replay`).

    Only the explained outputs [T, B, D] meet the vocabulary: the score is their dot product with the explained
    token's embedding row, and with `logits` the full logit vector is projected for those T rows alone (None
    without: the projection reads the whole [V, D] table, which the maps do not need).

    The backward passes run as a `lax.map` over cotangents, not `vmap`: under jax 0.10.2 on CPU, `vmap` of this
    VJP returned wrong gradients for all but the first cotangent at real prefix lengths (B=2, 816 tokens), while
    `lax.map` and single VJPs agree (tests/test_gradcam.py compares the stack with the per-token loop)."""
    E = embed_images(params, obs, cfg)
    rows = jnp.arange(fed.shape[0])[None, :]

    def scores_fn(image_tokens):
        explained = replay_prelogits(params, image_tokens, obs, fed, cfg, decode_len)[rows, steps]  # [T, B, D]
        return _gathered_logits(params, explained, targets[rows, steps]), explained  # [T, B]

    scores, vjp_fn, explained = jax.vjp(scores_fn, E, has_aux=True)
    t = steps.shape[0]
    cotangents = jnp.broadcast_to(jnp.eye(t, dtype=scores.dtype)[:, :, None], (t, *scores.shape))  # [T, T, B]
    G = jax.lax.map(lambda cot: vjp_fn(cot)[0], cotangents)  # [T, B, C, N, D]
    alpha, cam, token_norm = gradcam_reduce(E, G)
    full = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], explained).astype(jnp.float32) if logits else None
    return scores.astype(jnp.float32), alpha, cam, token_norm, full


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len"))
def _chunk_cam(params, obs, fed, target, *, cfg: Pi0FASTConfig, decode_len: int):
    """Score = sum_k weights[b, k] * log_softmax(logits_k)[g_k] over a `_weights_target`; one backward pass."""
    E = embed_images(params, obs, cfg)
    score_fn = _score_fn(params, obs, fed, target, cfg, decode_len)
    score, vjp_fn = jax.vjp(lambda e: score_fn(e)[0], E)  # [B]
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


def _score_fn(params, obs, fed, target, cfg, decode_len) -> Callable[[jax.Array], jax.Array]:
    """The explained scores as a function of the image tokens E [B, C, N, D] -> [T, B]: a token target's logits
    (`_token_target`), or a weights target's weighted log-prob sum as one row [1, B] (`_weights_target`), over the
    replay of fed [B, L] in a decode of `decode_len` steps."""
    llm = params["PaliGemma"]["llm"]
    rows = jnp.arange(fed.shape[0])[None, :]

    def fn(image_tokens):
        pre = replay_prelogits(params, image_tokens, obs, fed, cfg, decode_len)
        if "steps" in target:
            steps = target["steps"]
            return _gathered_logits(params, pre[rows, steps], target["ids"][rows, steps]).astype(jnp.float32)
        positions = target["positions"]
        logits = gemma.logits_from_prelogits(llm, pre[:, positions]).astype(jnp.float32)  # [B, K, V]
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits, -1), fed[:, positions, None], -1)[..., 0]
        return jnp.sum(target["weights"] * logp, axis=-1)[None]

    return fn


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "kinds", "options", "base_outputs", "logits"))
def _baseline_kinds(
    params, obs, fed, target, cams, masks, *, cfg: Pi0FASTConfig, decode_len: int, kinds, options, base_outputs, logits
):
    """The kinds that compare with a baseline frame, for one target (token steps [T, B], or weights as T = 1): see
    `baseline_maps.baseline_kinds`. With `base_outputs` (no gradient pass ran) also "score" [T, B] and, for token
    targets with `logits`, "logits" [T, B, V]."""
    E = embed_images(params, obs, cfg)
    score_fn = _score_fn(params, obs, fed, target, cfg, decode_len)
    out = baseline_maps.baseline_kinds(params, obs, cfg, score_fn, E, cams, masks, kinds, options)
    if base_outputs:
        out["score"] = score_fn(E)
        if "steps" in target and logits:
            rows = jnp.arange(fed.shape[0])[None, :]
            pre = replay_prelogits(params, E, obs, fed, cfg, decode_len)[rows, target["steps"]]  # [T, B, D]
            out["logits"] = gemma.logits_from_prelogits(params["PaliGemma"]["llm"], pre).astype(jnp.float32)
    return out


@functools.partial(jax.jit, static_argnames=("cfg", "decode_len", "chunk"))
def _variant_scores(params, obs, fed, target, variants, *, cfg: Pi0FASTConfig, decode_len: int, chunk: int):
    """Scores with the cameras in `variants` (camera -> [K, B, H, W, 3], camera order, K a multiple of `chunk`)
    replaced jointly per variant and re-encoded; the other cameras' tokens kept. -> [K, T, B]"""
    E = embed_images(params, obs, cfg)
    score_fn = _score_fn(params, obs, fed, target, cfg, decode_len)
    index = jnp.asarray([list(obs.images).index(c) for c in variants])

    def one(images):
        return score_fn(E.at[:, index].set(embed_images(params, baseline_maps.with_images(obs, images), cfg)))

    k = next(iter(variants.values())).shape[0]
    chunks = {c: v.reshape(k // chunk, chunk, *v.shape[1:]) for c, v in variants.items()}
    scores = jax.lax.map(lambda x: jax.vmap(one)(x), chunks)
    return scores.reshape(k, *scores.shape[2:])


occlusion_masks = baseline_maps.occlusion_masks


def backward_config(cfg: Pi0FASTConfig, tokens: int) -> Pi0FASTConfig:
    """The layout a token explanation of `tokens` (padded) steps differentiates with. One token: the Gemma stack
    unrolled over the same stacked parameters, unless it is rematerialised; XLA:CPU differentiates one token through
    the unrolled stack faster (bench_model's medium model, side by side: 0.82-0.87x the scanned backward pass in three
    runs). Inference keeps the served layout, and so do multi-token explanations (not measured faster) and stacks
    with `remat`. Whether remat stays is the device's question (`remat.backward_layout`, which applies this rule to
    the remat-free config too)."""
    if tokens != 1 or cfg.gemma.remat:
        return cfg
    return dataclasses.replace(cfg, gemma=dataclasses.replace(cfg.gemma, scan=False))


_baseline_frames = jax.jit(baseline_maps.frames, static_argnames=("options",))


def _baseline_maps(model, obs, fed, decode_len, target, kinds, options, base_outputs, logits=False) -> dict[str, Any]:
    """`baseline_maps.collect` over this family's program (replaying fed [B, L] of a decode of `decode_len` steps);
    with `base_outputs` also "score" [T, B] and with `logits` "logits" [T, B, V] (token targets)."""

    def run(kinds, options, cams, masks, first):
        return _baseline_kinds(
            model.params,
            obs,
            fed,
            target,
            cams,
            masks,
            cfg=model.config,
            decode_len=decode_len,
            kinds=kinds,
            options=options,
            base_outputs=base_outputs and first,
            logits=logits and base_outputs and first,
        )

    return baseline_maps.collect(run, tuple(obs.images), model.config.siglip.grid, kinds, options)


def _camera_maps(x: np.ndarray, cams: Sequence[str], grid: tuple[int, int]) -> dict[str, np.ndarray]:
    """[..., C, N] -> camera -> [..., Hp, Wp] (row-major patch grid)."""
    return {c: x[..., i, :].reshape(*x.shape[:-2], *grid) for i, c in enumerate(cams)}


def _result(model, obs, target, kinds, grad, score, logits, extra, ig_steps, token_ids, steps, positions, options):
    """grad: (alpha, cam, token_norm) batch-first or None; extra: `_baseline_maps` output made batch-first."""
    cams = tuple(obs.images)
    n = model.config.siglip.num_tokens
    grid = model.config.siglip.grid
    maps, alphas, grad_norms, gradnorm_maps, by_kind = {}, {}, {}, {}, {}
    if grad is not None:
        alpha, cam, token_norm = (np.asarray(x) for x in grad)
        grad_norm = np.sqrt(np.sum(np.square(token_norm.astype(np.float64)), axis=-1)).astype(np.float32)  # [..., C]
        maps, gradnorm_maps = _camera_maps(cam, cams, grid), _camera_maps(token_norm, cams, grid)
        alphas = {c: alpha[..., i, :] for i, c in enumerate(cams)}
        grad_norms = {c: grad_norm[..., i] for i, c in enumerate(cams)}
        by_kind.update({k: m for k, m in (("gradcam", maps), ("gradnorm", gradnorm_maps)) if k in kinds})
    by_kind.update({k: extra[k] for k in BASELINE_KINDS if k in extra})
    completeness = IgCompleteness(*extra["ig_check"], steps=ig_steps) if "ig_check" in extra else None
    return GradCamResult(
        target=target,
        cameras=cams,
        maps=maps,
        alphas=alphas,
        grad_norms=grad_norms,
        gradnorm_maps=gradnorm_maps,
        spans={c: (i * n, (i + 1) * n) for i, c in enumerate(cams)},
        valid={c: np.asarray(obs.image_masks[c], bool).reshape(-1) for c in cams},
        score=np.asarray(score),
        token_ids=np.asarray(token_ids, np.int32),
        decode_steps=np.asarray(steps, np.int32),
        positions=positions,
        logits=None if logits is None else np.asarray(logits),
        by_kind=by_kind,
        ig_completeness=completeness,
        options=options if any(k in BASELINE_KINDS for k in kinds) else None,
    )


def _map_tree(fn: Callable[[np.ndarray], np.ndarray], tree: Any) -> Any:
    return jax.tree.map(fn, tree, is_leaf=lambda x: isinstance(x, np.ndarray))


def gradcam_for_steps(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    steps: ArrayLike,
    *,
    kinds: Sequence[str] = DEFAULT_KINDS,
    options: MapOptions | None = None,
    logits: bool = True,
) -> GradCamResult:
    """Explains the generated tokens at `steps` ([T] for every row, or [B, T] per row; one map stack per camera),
    with one forward pass shared by all of them (per kind). `logits=False` leaves `GradCamResult.logits` None and
    skips projecting the explained outputs onto the whole vocabulary (the side channel's choice)."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    return _explain_tokens(model, obs, fed, fed, steps, prefill_len, False, kinds, options, logits)


def gradcam_for_action_token(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    step: int,
    *,
    kinds: Sequence[str] = DEFAULT_KINDS,
    options: MapOptions | None = None,
    logits: bool = True,
) -> GradCamResult:
    """Explains the generated token at decode `step` (one map per camera, no token axis); `logits` as in
    `gradcam_for_steps`."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    return _explain_tokens(model, obs, fed, fed, [int(step)], prefill_len, True, kinds, options, logits)


def gradcam_for_token(
    model: Pi0FAST,
    obs: Observation,
    *,
    token_id: int | Sequence[int],
    step: int | None = None,
    position: int | None = None,
    generated_prefix: ArrayLike | None = None,
    max_decoding_steps: int = MAX_DECODING_STEPS,
    kinds: Sequence[str] = DEFAULT_KINDS,
    options: MapOptions | None = None,
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
    return _explain_tokens(model, obs, fed_j, jnp.asarray(targets), [step], prefill_len, True, kinds, options, True)


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
    model, obs, fed, targets, steps, prefill_len, squeeze, kinds, options, with_logits
) -> GradCamResult:
    kinds, options = check_kinds(kinds), options or MapOptions()
    batch = fed.shape[0]
    steps, shared, steps_tb = _token_steps(steps, batch, fed.shape[1])
    t = steps.shape[1]
    fed, decode_len = _replay(fed, steps.max())
    targets = targets[:, : fed.shape[1]]

    def batch_first(x):  # [T_pad, B, ...] -> [B, T, ...] (or [B, ...] for one token)
        x = np.moveaxis(np.asarray(x)[:t], 0, 1)
        return x[:, 0] if squeeze else x

    grad = score = logits = None
    if any(k in GRADIENT_KINDS for k in kinds):
        args = (model.params, obs, fed, targets, jnp.asarray(steps_tb))
        static = {"decode_len": decode_len, "logits": with_logits}
        tokens = steps_tb.shape[0]
        cfg = remat.backward_layout(_token_cams, model.config, args, static, lambda c: backward_config(c, tokens))
        score, alpha, cam, token_norm, logits = _token_cams(*args, cfg=cfg, **static)
        grad = tuple(batch_first(x) for x in (alpha, cam, token_norm))
        score = batch_first(score)
        logits = None if logits is None else batch_first(logits)
    extra, ig_steps = {}, None
    if any(k in BASELINE_KINDS for k in kinds):
        target_spec = _token_target(targets, steps_tb)
        extra = _baseline_maps(
            model, obs, fed, decode_len, target_spec, kinds, options, base_outputs=grad is None, logits=with_logits
        )
        ig_steps = extra.pop("ig_steps", None)
        extra = _map_tree(batch_first, extra)
        if grad is None:
            score, logits = extra["score"], extra.get("logits")
    token_ids = np.take_along_axis(np.asarray(targets), steps, axis=1)
    return _result(
        model,
        obs,
        "token" if squeeze else "tokens",
        kinds,
        grad,
        score,
        logits,
        extra,
        ig_steps,
        token_ids,
        steps[0] if shared else steps,
        _positions(prefill_len, steps),
        options,
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


def gradcam_for_chunk(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    steps: ArrayLike,
    *,
    kinds: Sequence[str] = DEFAULT_KINDS,
    options: MapOptions | None = None,
) -> GradCamResult:
    """Whole-chunk target: score = sum over `steps` of log p(g_k); one backward pass, one map per camera.

    `steps` is one list for every row, or one list per row (lengths may differ: per-row `token_ids`,
    `decode_steps` and `positions` are then padded with -1)."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    weights, rows, shared = chunk_weights(steps, fed.shape[0], fed.shape[1])
    return _explain_weights(model, obs, fed, weights, rows, shared, prefill_len, "chunk", kinds, options)


def maps_for_weights(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    weights: ArrayLike,
    *,
    kinds: Sequence[str] = DEFAULT_KINDS,
    options: MapOptions | None = None,
) -> GradCamResult:
    """Sequence target with arbitrary per-row weights: score = sum_k weights[b, k] log p(g_k), weights [S] or [B, S]
    (e.g. the generated tokens of each row, or a decayed chunk). One map per camera; the explained steps are those
    with a non-zero weight (per row, padded with -1)."""
    obs, fed, prefill_len = _prepare(model, obs, generated_ids)
    weights = np.broadcast_to(np.asarray(weights, np.float32), fed.shape).copy()
    rows = [np.flatnonzero(w).astype(np.int32) for w in weights]
    if any(r.size == 0 for r in rows):
        raise ValueError("every row needs at least one decode step with a non-zero weight")
    return _explain_weights(model, obs, fed, weights, rows, False, prefill_len, "weights", kinds, options)


def _explain_weights(model, obs, fed, weights, rows, shared, prefill_len, target, kinds, options) -> GradCamResult:
    kinds, options = check_kinds(kinds), options or MapOptions()
    batch = fed.shape[0]
    padded = np.full((batch, max(r.size for r in rows)), -1, np.int32)
    for b, r in enumerate(rows):
        padded[b, : r.size] = r
    fed, decode_len = _replay(fed, max(r.max() for r in rows))
    target_spec = _weights_target(np.asarray(weights)[:, : fed.shape[1]])
    grad = score = None
    if any(k in GRADIENT_KINDS for k in kinds):
        args, static = (model.params, obs, fed, target_spec), {"decode_len": decode_len}
        cfg = remat.backward_layout(_chunk_cam, model.config, args, static)
        score, alpha, cam, token_norm = _chunk_cam(*args, cfg=cfg, **static)
        grad = (alpha, cam, token_norm)
    extra, ig_steps = {}, None
    if any(k in BASELINE_KINDS for k in kinds):
        extra = _baseline_maps(model, obs, fed, decode_len, target_spec, kinds, options, base_outputs=grad is None)
        ig_steps = extra.pop("ig_steps", None)
        extra = _map_tree(lambda x: x[0], extra)  # the one score row
        score = extra["score"] if grad is None else score
    valid = padded >= 0
    token_ids = np.where(valid, np.take_along_axis(np.asarray(fed), np.maximum(padded, 0), axis=1), -1)
    positions = np.where(valid, _positions(prefill_len, np.maximum(padded, 0)), -1)
    steps = rows[0] if shared else padded
    return _result(model, obs, target, kinds, grad, score, None, extra, ig_steps, token_ids, steps, positions, options)


# ----------------------------------------------------------------------------------------------------------------
# What faithfulness metrics need: the baseline frames, and the explained score of image variants.


def baseline_frames(model: Pi0FAST, obs: Observation, options: MapOptions | None = None) -> dict[str, np.ndarray]:
    """camera -> the baseline frame [B, H, W, 3] at the model resolution that IG and occlusion compare with (a masked
    camera's row is its own image), so deletion curves paint with exactly the same pixels."""
    obs = preprocess_observation(obs, model.config.image_resolution)
    base = np.asarray(_baseline_frames(obs, options=baseline_maps.compiled_options(options or MapOptions(), ())))
    return dict(zip(obs.images, base, strict=True))


def _rescore_target(
    fed: jax.Array, steps: ArrayLike, weights: ArrayLike
) -> tuple[dict[str, jax.Array], int | None, jax.Array, int]:
    """(target for the rescoring cores, T for token targets or None for weights, fed cut to the replay, the decode
    length)."""
    if (steps is None) == (weights is None):
        raise ValueError("give exactly one of steps= (token logits) or weights= (weighted log-prob sum)")
    if steps is not None:
        steps, _, steps_tb = _token_steps(np.atleast_1d(np.asarray(steps, np.int32)), fed.shape[0], fed.shape[1])
        cut, decode_len = _replay(fed, steps.max())
        return _token_target(cut, steps_tb), steps.shape[1], cut, decode_len
    weights = np.broadcast_to(np.asarray(weights, np.float32), fed.shape)
    cut, decode_len = _replay(fed, np.flatnonzero(np.any(weights != 0, axis=0)).max(initial=0))
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
    obs, fed, _ = _prepare(model, obs, generated_ids)
    target, t, fed, decode_len = _rescore_target(fed, steps, weights)
    cams = tuple(obs.images)
    per_camera = baseline_maps.checked_masks(masks, cams, model.config.siglip.grid)
    variant_cams, variant_masks, where = baseline_maps.variants(per_camera, options.mask_chunk)
    out = _baseline_kinds(
        model.params,
        obs,
        fed,
        target,
        variant_cams,
        variant_masks,
        cfg=model.config,
        decode_len=decode_len,
        kinds=("occlusion",),
        options=baseline_maps.compiled_options(options, ("occlusion",)),
        base_outputs=False,
        logits=False,
    )
    scores = _scores_out(out["occlusion_scores"], t)
    return {c: scores[s] for c, s in zip(cams, where, strict=True) if c in masks}


def rescore_images(
    model: Pi0FAST,
    obs: Observation,
    generated_ids: ArrayLike,
    images: Mapping[str, ArrayLike],
    *,
    steps: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    mask_chunk: int = MapOptions().mask_chunk,
) -> np.ndarray:
    """The explained score for image variants: images camera -> [M, B, H, W, 3] (float32 in [-1, 1], at the model
    resolution); variant m replaces those cameras jointly, re-encodes them, keeps the other cameras' tokens.
    Target as `rescore_masks`. -> [M, B, T] (steps) or [M, B] (weights)."""
    obs, fed, _ = _prepare(model, obs, generated_ids)
    target, t, fed, decode_len = _rescore_target(fed, steps, weights)
    cams = tuple(obs.images)
    if not images or set(images) - set(cams):
        raise ValueError(f"image variants must name some of the model's cameras {cams}, got {sorted(images)}")
    variants = {c: np.asarray(images[c], np.float32) for c in cams if c in images}
    m = {v.shape[0] for v in variants.values()}
    expected = (fed.shape[0], *model.config.image_resolution, 3)
    if len(m) != 1 or any(v.shape[1:] != expected for v in variants.values()):
        raise ValueError(f"every camera needs [M, {', '.join(map(str, expected))}] variants with the same M")
    m = m.pop()
    pad = -m % mask_chunk
    variants = {c: jnp.asarray(np.concatenate([v, np.repeat(v[:1], pad, axis=0)])) for c, v in variants.items()}
    scores = _variant_scores(
        model.params, obs, fed, target, variants, cfg=model.config, decode_len=decode_len, chunk=mask_chunk
    )
    return _scores_out(scores, t)[:m]
