"""Maps over pi0 / pi0.5's SigLIP tokens, explaining the actions the served call returned.

The explained function is the whole flow-matching integration (`pi0.denoise`): x_0 as a function of the image tokens
E [B, C, N, D] the LLM sees, from the call's own noise (no gradient through SigLIP). A target is a fixed weighting W of
the chunk, score = sum(W * x_0): one action dimension at one horizon step (W one-hot at (h, d)), or the whole chunk
(W = stop_gradient(x_0), the goldens' `gc_chunk`: its gradient is sum_hd x_0[h, d] * dx_0[h, d] / dE). Several targets
share one forward pass and take one backward pass each. Each Euler step is rematerialised (`pi0.denoise`), so the
backward keeps one step's activations at a time. The `lrp` kind runs its own backward pass per target with AttnLRP's
rules (`model.lrp`) through SigLIP too, to the pixels (`lrp_maps`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from openpi_cam.model import baseline_maps, gradient_maps, lrp, lrp_maps, remat
from openpi_cam.model.attribution import IgCompleteness
from openpi_cam.model.config import Pi0Config
from openpi_cam.model.observation import Observation
from openpi_cam.model.paligemma import embed_images
from openpi_cam.model.pi0 import Pi0, denoise, preprocess
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

CHUNK = (-1, -1)  # the (h, d) that stands for the whole-chunk target


@dataclasses.dataclass(frozen=True)
class FlowMaps:
    """Raw maps per camera; leading axes [B, T] (T explained targets)."""

    cameras: tuple[str, ...]
    by_kind: dict[str, dict[str, np.ndarray]]  # kind -> camera -> float32 [B, T, Hp, Wp]
    alphas: dict[str, np.ndarray]  # camera -> float32 [B, T, D]: Grad-CAM's channel weights
    grad_norms: dict[str, np.ndarray]  # camera -> float32 [B, T]: Frobenius norm of the gradient
    spans: dict[str, tuple[int, int]]  # camera -> [start, end) of its tokens in the prefix
    valid: dict[str, np.ndarray]  # camera -> bool [B]
    score: np.ndarray  # float32 [B, T]
    targets: tuple[tuple[int, int], ...]  # (h, d) per explained target; CHUNK for the whole chunk
    actions: np.ndarray  # float32 [B, H, A]: x_0, the explained actions (equal to the served ones)
    ig_completeness: IgCompleteness | None = None  # with "ig"; arrays [B, T]
    options: MapOptions | None = None  # the map options, when a kind that depends on them was requested


def _weights(x_0: jax.Array, targets: tuple[tuple[int, int], ...]) -> jax.Array:
    """The fixed weighting of each target [T, B, H, A] (CHUNK: the explained chunk itself, held constant)."""
    weights = []
    for h, d in targets:
        if (h, d) == CHUNK:
            weights.append(jax.lax.stop_gradient(x_0))
        else:
            weights.append(jnp.zeros_like(x_0).at[:, h, d].set(1.0))
    return jnp.stack(weights)


@functools.partial(jax.jit, static_argnames=("cfg", "targets", "program", "options"))
def _flow_gradient_maps(
    params,
    obs,
    noise,
    inputs=None,
    *,
    cfg: Pi0Config,
    targets: tuple[tuple[int, int], ...],
    program=gradient_maps.TOKEN_PASS,
    options=gradient_maps.COMPILED_DEFAULTS,
):
    """The gradient kinds of the targets (`gradient_maps.gradient_kinds` with passes `program`): one backward pass per
    target from its weighting of x_0 through the Euler integration. -> score [B, T], x_0 [B, H, A], maps [B, T, ...]."""

    def output_fn(image_tokens):
        return denoise(params, image_tokens, obs, noise, cfg), None

    x_0, _, grad = gradient_maps.gradient_kinds(
        params, obs, cfg, output_fn, lambda x: _weights(x, targets), program, options, inputs
    )
    score = jnp.einsum("tbha,bha->bt", _weights(x_0, targets), x_0)
    return score, x_0, {k: jnp.moveaxis(v, 0, 1) for k, v in grad.items()}


@functools.partial(jax.jit, static_argnames=("cfg", "targets"))
def _flow_relevance_maps(params, obs, noise, *, cfg: Pi0Config, targets: tuple[tuple[int, int], ...]):
    """The lrp kind of the targets (`cfg` with rules "lrp", `lrp_maps.pixel_relevance`): one modified backward pass
    per target from its weighting of x_0 through the Euler integration, the LLM and SigLIP to the pixels. -> score
    [B, T], x_0 [B, H, A], relevance [B, T, C, N]."""

    def output_fn(image_tokens):
        return denoise(params, image_tokens, obs, noise, cfg), None

    x_0, _, relevance = lrp_maps.pixel_relevance(params, obs, cfg, output_fn, lambda x: _weights(x, targets))
    score = jnp.einsum("tbha,bha->bt", _weights(x_0, targets), x_0)
    return score, x_0, jnp.moveaxis(relevance, 0, 1)


@functools.partial(jax.jit, static_argnames=("cfg", "targets", "kinds", "options", "base_outputs"))
def _flow_baseline_kinds(
    params, obs, noise, inputs, explained=None, *, cfg: Pi0Config, targets, kinds, options, base_outputs
):
    """IG / occlusion of the targets' scores, each a fixed weighting of x_0 from the same noise (see
    `baseline_maps.baseline_kinds`); the CHUNK weighting is the `explained` chunk [B, H, A] when given, else this
    observation's x_0. With `base_outputs` also "score" [T, B] and "actions" [B, H, A]."""
    E = embed_images(params, obs, cfg)
    x_0 = denoise(params, E, obs, noise, cfg)
    weights = _weights(x_0 if explained is None else explained, targets)

    def score_fn(image_tokens):
        return jnp.einsum("tbha,bha->tb", weights, denoise(params, image_tokens, obs, noise, cfg).astype(jnp.float32))

    out = baseline_maps.baseline_kinds(params, obs, cfg, score_fn, E, inputs, kinds, options)
    if base_outputs:
        out["score"], out["actions"] = jnp.einsum("tbha,bha->tb", weights, x_0), x_0
    return out


def _checked_targets(cfg: Pi0Config, targets: Sequence[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
    targets = tuple((int(h), int(d)) for h, d in targets)
    for h, d in targets:
        if (h, d) != CHUNK and not (0 <= h < cfg.action_horizon and 0 <= d < cfg.action_dim):
            raise ValueError(f"action ({h}, {d}) outside the chunk [{cfg.action_horizon}, {cfg.action_dim}]")
    if not targets:
        raise ValueError("no targets to explain")
    return targets


def maps_for_actions(
    model: Pi0,
    obs: Observation,
    noise: ArrayLike,
    targets: Sequence[tuple[int, int]],
    *,
    kinds: Sequence[str] = ONE_PASS_KINDS,
    options: MapOptions | None = None,
) -> FlowMaps:
    """The requested map kinds of each target ((h, d), or `CHUNK`) for the actions sampled from `noise` [B, H, A]
    (the served call's noise: the explained x_0 is the returned one). Grad-CAM, the gradient norm and gradient x
    input share one backward pass per target, which taylor continues through SigLIP; smoothgrad repeats it at noisy
    tokens; taylor, IG, occlusion and rise compare with the baseline frame of `options`; lrp runs a modified backward
    pass of its own per target."""
    cfg = model.config
    targets = _checked_targets(cfg, targets)
    kinds, options = check_kinds(kinds, MODEL_KINDS), options or MapOptions()
    obs = preprocess(obs, cfg)
    noise = jnp.asarray(noise, jnp.float32)
    cams, grid, n = tuple(obs.images), cfg.siglip.grid, cfg.siglip.num_tokens

    def per_camera(x: np.ndarray) -> dict[str, np.ndarray]:  # [B, T, C, N] -> camera -> [B, T, Hp, Wp]
        return {c: x[:, :, i].reshape(*x.shape[:2], *grid) for i, c in enumerate(cams)}

    by_kind, alphas, grad_norms, completeness = {}, {}, {}, None
    score = actions = None
    if any(k in GRADIENT_KINDS for k in kinds):
        inputs, static = gradient_maps.program_arguments(kinds, options)
        args, static = (model.params, obs, noise, inputs), static | {"targets": targets}
        flow_cfg = remat.backward_layout(_flow_gradient_maps, cfg, args, static)
        score, actions, grad = _flow_gradient_maps(*args, cfg=flow_cfg, **static)
        grad = {k: np.asarray(v) for k, v in grad.items()}  # [B, T, C, ...]
        by_kind.update({k: per_camera(grad[k]) for k in GRADIENT_KINDS if k in kinds})
        if "alpha" in grad:  # the token pass ran
            grad_norm = np.sqrt(np.sum(np.square(grad["gradnorm"].astype(np.float64)), axis=-1)).astype(np.float32)
            alphas = {c: grad["alpha"][:, :, i] for i, c in enumerate(cams)}
            grad_norms = {c: grad_norm[:, :, i] for i, c in enumerate(cams)}
    if any(k in RELEVANCE_KINDS for k in kinds):
        args, static = (model.params, obs, noise), {"targets": targets}
        lrp_cfg = remat.backward_layout(_flow_relevance_maps, lrp.with_rules(cfg, "lrp"), args, static)
        lrp_score, lrp_actions, relevance = _flow_relevance_maps(*args, cfg=lrp_cfg, **static)
        by_kind["lrp"] = per_camera(np.asarray(relevance))
        if score is None:
            score, actions = lrp_score, lrp_actions
    if any(k in BASELINE_KINDS for k in kinds):
        first_outputs = score is None

        def run(kinds, options, inputs, first):
            return _flow_baseline_kinds(
                model.params,
                obs,
                noise,
                inputs,
                cfg=cfg,
                targets=targets,
                kinds=kinds,
                options=options,
                base_outputs=first_outputs and first,
            )

        extra = baseline_maps.collect(run, cams, grid, kinds, options, baseline_maps.camera_validity(obs))
        batch_first = {k: {c: np.moveaxis(m, 0, 1) for c, m in extra[k].items()} for k in BASELINE_KINDS if k in extra}
        by_kind.update(batch_first)
        if "ig_check" in extra:
            completeness = IgCompleteness(*(np.moveaxis(x, 0, 1) for x in extra["ig_check"]), steps=extra["ig_steps"])
        if first_outputs:
            score, actions = np.moveaxis(extra["score"], 0, 1), extra["actions"]
    return FlowMaps(
        cameras=cams,
        by_kind=by_kind,
        alphas=alphas,
        grad_norms=grad_norms,
        spans={c: (i * n, (i + 1) * n) for i, c in enumerate(cams)},
        valid={c: np.asarray(obs.image_masks[c], bool).reshape(-1) for c in cams},
        score=np.asarray(score),
        targets=targets,
        actions=np.asarray(actions),
        ig_completeness=completeness,
        options=options if any(k in OPTION_KINDS for k in kinds) else None,
    )


def rescore_masks(
    model: Pi0,
    obs: Observation,
    noise: ArrayLike,
    masks: Mapping[str, ArrayLike],
    targets: Sequence[tuple[int, int]],
    *,
    options: MapOptions | None = None,
    explained: ArrayLike | None = None,
) -> dict[str, np.ndarray]:
    """The targets' scores with patches painted by the baseline frame, one camera at a time, the whole denoising
    re-run from the same noise; the weighting stays that of the explained call (CHUNK: `explained`, its chunk x_0
    [B, H, A]; by default this observation's unpainted x_0, the same for the served observation). masks: camera ->
    bool [M, Hp, Wp] (an all-False mask gives the unmodified score). -> camera -> [M, B, T]."""
    cfg = model.config
    targets = _checked_targets(cfg, targets)
    options = options or MapOptions()
    obs = preprocess(obs, cfg)
    cams = tuple(obs.images)
    per_camera = baseline_maps.checked_masks(masks, cams, cfg.siglip.grid)
    inputs, where = baseline_maps.variants(per_camera, options.mask_chunk)
    out = _flow_baseline_kinds(
        model.params,
        obs,
        jnp.asarray(noise, jnp.float32),
        inputs,
        None if explained is None else jnp.asarray(explained, jnp.float32),
        cfg=cfg,
        targets=targets,
        kinds=("occlusion",),
        options=baseline_maps.compiled_options(options, ("occlusion",)),
        base_outputs=False,
    )
    scores = np.moveaxis(np.asarray(out["occlusion_scores"]), 1, 2)  # [K, B, T]
    return {c: scores[s] for c, s in zip(cams, where, strict=True) if c in masks}
