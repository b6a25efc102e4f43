"""Integrated gradients, occlusion and RISE for any PaliGemma-based family, given how the family scores image tokens.

A family supplies `score_fn`: the explained scores [T, B] as a function of the image tokens E [B, C, N, D] (pi0-FAST:
logits or log-probabilities of its generated tokens; pi0 / pi0.5: a weighting of the denoised chunk). Everything
else is shared: the baseline frames (`attribution.baseline_images`), IG along E0 -> E with E0 the baseline frames'
SigLIP tokens, and occlusion and RISE by painting one camera's patches with its baseline frame, re-encoding that
camera and re-scoring (both kinds' masks in one batched call). `baseline_kinds` runs inside the family's jitted
program; `collect` runs on the host around it (the IG step doubling, the reduction of painted scores to maps).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model.attribution import (
    IG_STALL,
    baseline_images,
    completeness_error,
    integrated_gradients,
    iss_map,
    paint,
    patchify,
    quadrature_buffer,
    random_region_masks,
    region_map,
    region_masks,
    unpatchify,
)
from openpi_cam.model.observation import Observation
from openpi_cam.model.paligemma import VLMConfig, embed_images
from openpi_cam.model.sharding import spread
from openpi_cam.vocabulary import BASELINE_KINDS, MapOptions

ScoreFn = Callable[[jax.Array], jax.Array]  # image tokens [B, C, N, D] -> scores [T, B]


class BaselineInputs(NamedTuple):
    """What a baseline-kinds program takes as data rather than compiling in (a field is None when its kind is not
    asked for): the occlusion variants (`variants`) and IG's quadrature points in a buffer of `ig_max_steps`
    (`ig_inputs`), so other masks, rules and step counts reuse one compilation."""

    cams: jax.Array | None = None  # int32 [K]: the camera each variant paints
    masks: jax.Array | None = None  # bool [K, Hp, Wp]
    ig_nodes: jax.Array | None = None  # float32 [ig_max_steps]
    ig_weights: jax.Array | None = None  # float32 [ig_max_steps]
    ig_count: jax.Array | None = None  # int32 []: how many of the points are used


def ig_inputs(options: MapOptions, steps: int) -> BaselineInputs:
    """IG's points for `steps` evaluations of `options.ig_rule`, in the buffer the program is compiled for."""
    nodes, weights = quadrature_buffer(options.ig_rule, steps, options.ig_max_steps)
    return BaselineInputs(ig_nodes=jnp.asarray(nodes), ig_weights=jnp.asarray(weights), ig_count=jnp.int32(steps))


def camera_stack(obs: Observation) -> tuple[jax.Array, jax.Array]:
    """images [C, B, H, W, 3] and validity [C, B] in camera order (every camera is at the model resolution)."""
    images = jnp.stack([jnp.asarray(obs.images[c], jnp.float32) for c in obs.images])
    valid = jnp.stack([jnp.asarray(obs.image_masks[c], bool).reshape(-1) for c in obs.images])
    return images, valid


def with_images(obs: Observation, images: Mapping[str, jax.Array]) -> Observation:
    return dataclasses.replace(obs, images=dict(images))


def balanced_chunk(variants: int, chunk: int) -> int:
    """How many variants run vectorised at once: as few chunks as `chunk` at a time allows, made as even as possible,
    so that padding the variants to whole chunks adds fewer than one variant per chunk (34 variants at 16 at a time
    run as 3 chunks of 12, not 3 of 16 with 14 no-op re-runs)."""
    chunks = -(-variants // chunk)
    return -(-variants // chunks)


def _painted_scores(params, obs, cfg, score_fn, E, images, base, cams, masks, chunk) -> jax.Array:
    """Scores with camera cams[k]'s patches masks[k] replaced by its baseline frame, that camera re-encoded by SigLIP
    and the others' tokens kept. cams int32 [K], masks bool [K, Hp, Wp], K padded by `variants` -> [K, T, B].

    A chunk of variants (`balanced_chunk` of K and `chunk`) runs vectorised (forward only, so `vmap` is safe here);
    the chunks run one after another (`lax.map`), which bounds memory at chunk x B model runs for any number of
    masks."""
    name = next(iter(obs.images))
    select = jnp.arange(E.shape[1])[None, :, None, None]  # [1, C, 1, 1]

    def one(cam, mask):
        image = paint(images[cam], base[cam], mask, cfg.siglip.patch_size)  # [B, H, W, 3]
        tokens = embed_images(params, with_images(obs, {name: image}), cfg)  # [B, 1, N, D]
        return score_fn(jnp.where(select == cam, tokens, E))

    k = cams.shape[0]
    chunk = balanced_chunk(k, chunk)
    # Under a data mesh the variants of each chunk are spread over the devices (they never interact).
    chunked_cams = spread(cams.reshape(k // chunk, chunk), 1)
    chunked_masks = spread(masks.reshape(k // chunk, chunk, *masks.shape[1:]), 1)
    scores = jax.lax.map(lambda chunk_args: jax.vmap(one)(*chunk_args), (chunked_cams, chunked_masks))
    return scores.reshape(k, *scores.shape[2:])


def baseline_kinds(
    params: dict,
    obs: Observation,
    cfg: VLMConfig,
    score_fn: ScoreFn,
    E: jax.Array,
    inputs: BaselineInputs,
    kinds: Sequence[str],
    options: MapOptions,
) -> dict[str, jax.Array]:
    """Traced core (call inside a jitted program). Returns "ig" [T, B, C, N] with "ig_score" / "ig_baseline_score"
    [T, B], over the inputs' quadrature points; with "occlusion" in `kinds`, "occlusion_scores" [K, T, B] for the
    inputs' painted variants (occlusion's and rise's alike: `collect`)."""
    images, valid = camera_stack(obs)
    base = baseline_images(images, valid, options)  # [C, B, H, W, 3]
    out = {}
    if "ig" in kinds and options.ig_space == "pixels":
        patch, hw = cfg.siglip.patch_size, images.shape[2:4]

        def pixel_score(x: jax.Array) -> jax.Array:  # patchified frames [B, C, N, P] -> scores [T, B]
            frames = unpatchify(x, patch, hw)
            return score_fn(embed_images(params, with_images(obs, dict(zip(obs.images, frames, strict=True))), cfg))

        X, X0 = patchify(images, patch), patchify(base, patch)
        X0 = jnp.where(valid.T[:, :, None, None], X0, X)  # a masked camera is its own baseline
        out["ig"], out["ig_score"], out["ig_baseline_score"] = integrated_gradients(
            pixel_score, X, X0, inputs.ig_nodes, inputs.ig_weights, inputs.ig_count
        )
    elif "ig" in kinds:
        E0 = embed_images(params, with_images(obs, dict(zip(obs.images, base, strict=True))), cfg)
        E0 = jnp.where(valid.T[:, :, None, None], E0, E)  # a masked camera is its own baseline
        out["ig"], out["ig_score"], out["ig_baseline_score"] = integrated_gradients(
            score_fn, E, E0, inputs.ig_nodes, inputs.ig_weights, inputs.ig_count
        )
    if "occlusion" in kinds:
        out["occlusion_scores"] = _painted_scores(
            params, obs, cfg, score_fn, E, images, base, inputs.cams, inputs.masks, options.mask_chunk
        )
    return out


def compiled_options(options: MapOptions, kinds: Sequence[str] = BASELINE_KINDS) -> MapOptions:
    """The options the compiled program depends on: which masks occlusion uses and IG's quadrature points are data
    (`BaselineInputs`; their counts shapes), so the fields that choose them are reset and e.g. a new seed or step
    count reuses the compilation; so are the fields of kinds not requested."""
    defaults = MapOptions()
    keep = {"baseline", "blur_sigma"}
    keep |= {"ig_max_steps", "ig_space"} if "ig" in kinds else set()
    keep |= {"mask_chunk"} if "occlusion" in kinds else set()
    reset = {f.name: getattr(defaults, f.name) for f in dataclasses.fields(MapOptions) if f.name not in keep}
    return dataclasses.replace(options, **reset)


def occlusion_masks(grid: tuple[int, int], options: MapOptions) -> np.ndarray:
    """The masks occlusion paints one camera with (bool [M, Hp, Wp], True = painted): every region once, or the
    random ISS masks drawn from the options' seed."""
    if options.occlusion_mode == "regions":
        return region_masks(grid, options.occlusion_region)
    return random_region_masks(grid, options.occlusion_region, options.random_masks, options.keep_prob, options.seed)


def variants(per_camera: Sequence[np.ndarray | None], chunk: int) -> tuple[BaselineInputs, list[slice]]:
    """Flattens per-camera mask stacks into one variant list (the inputs' cams [K] and masks [K, Hp, Wp]) padded
    with no-op variants to whole chunks of `balanced_chunk(variants, chunk)`; slice c selects camera c's variants."""
    cams, masks, where, start = [], [], [], 0
    for c, m in enumerate(per_camera):
        m = np.zeros((0,), bool) if m is None else np.asarray(m, bool)
        if m.size:
            cams.append(np.full(m.shape[0], c, np.int32))
            masks.append(m)
        where.append(slice(start, start + len(m)))
        start += len(m)
    cams, masks = np.concatenate(cams), np.concatenate(masks)
    pad = -len(cams) % balanced_chunk(len(cams), chunk)
    cams = np.concatenate([cams, np.zeros(pad, np.int32)])
    masks = np.concatenate([masks, np.zeros((pad, *masks.shape[1:]), bool)])
    return BaselineInputs(cams=jnp.asarray(cams), masks=jnp.asarray(masks)), where


def checked_masks(masks: Mapping[str, Any], cameras: Sequence[str], grid: tuple[int, int]) -> list[np.ndarray | None]:
    """Masks given per camera name -> one bool [M, Hp, Wp] stack (or None) per camera, in camera order."""
    unknown = set(masks) - set(cameras)
    if unknown:
        raise ValueError(f"unknown cameras {sorted(unknown)}; the model's are {tuple(cameras)}")
    per_camera = [None if c not in masks else np.asarray(masks[c], bool) for c in cameras]
    if not masks or any(m is not None and (m.ndim != 3 or m.shape[1:] != grid or not len(m)) for m in per_camera):
        raise ValueError(f"masks must map cameras to non-empty bool [M, {grid[0]}, {grid[1]}] stacks")
    return per_camera


RunFn = Callable[[tuple[str, ...], MapOptions, BaselineInputs, bool], Mapping[str, Any]]


def painted_masks(grid: tuple[int, int], kinds: Sequence[str], options: MapOptions) -> dict[str, np.ndarray]:
    """The masks each painting kind requested re-runs one camera with: occlusion's (`occlusion_masks`) and rise's
    (`options.rise_masks` random masks over the patch grid, each patch kept with `options.rise_keep_prob`, drawn from
    `options.seed`)."""
    masks = {}
    if "occlusion" in kinds:
        masks["occlusion"] = occlusion_masks(grid, options)
    if "rise" in kinds:
        masks["rise"] = random_region_masks(grid, 1, options.rise_masks, options.rise_keep_prob, options.seed)
    return masks


def camera_validity(obs: Observation) -> np.ndarray:
    """bool [C]: whether each camera (in camera order) is valid in some row of the batch (host-side)."""
    return np.stack([np.asarray(obs.image_masks[c], bool).reshape(-1) for c in obs.images]).any(axis=1)


def collect(
    run: RunFn,
    cameras: Sequence[str],
    grid: tuple[int, int],
    kinds: Sequence[str],
    options: MapOptions,
    valid: Sequence[bool] | None = None,
) -> dict[str, Any]:
    """Runs the family's program `run(program kinds, compiled options, inputs, first_call)` for the requested baseline
    kinds and turns its output into maps; every array keeps the program's leading [T, B] axes. The program knows
    two kinds: "ig" and "occlusion", which re-runs every painted variant of the inputs: occlusion's and rise's masks
    of every camera valid in some row (`valid`, bool per camera; None: all), after one unpainted reference per
    camera, in one call. A camera masked in every row is not re-run: the model does not read it, so painting it
    cannot move the score, and its occlusion and rise maps are zeros. An IG refinement runs the IG-only
    program: the first call's own when it asked for IG alone (its first-call outputs computed again, a forward pass
    beside the refinement's backward ones, rather than a second compilation).

    Returns "ig", "occlusion" and "rise" (camera -> [T, B, Hp, Wp]), "ig_check" (score, baseline score, attribution
    sum, each [T, B]), "ig_steps" (quadrature steps used), and whatever else the first call returned."""
    kinds = tuple(k for k in BASELINE_KINDS if k in kinds)
    inputs, where = BaselineInputs(), None
    masks = painted_masks(grid, kinds, options)
    valid = np.ones(len(cameras), bool) if valid is None else np.asarray(valid, bool)
    painting = bool(masks) and bool(valid.any())
    program = tuple(k for k in ("ig", "occlusion") if k in kinds or (k == "occlusion" and painting))
    if "ig" in kinds:
        inputs = ig_inputs(options, options.ig_steps)
    if painting:
        reference = np.zeros((1, *grid), bool)  # every camera's drops against its own unpainted re-run
        stack = np.concatenate([reference, *masks.values()])
        painted, where = variants([stack if v else None for v in valid], options.mask_chunk)
        inputs = inputs._replace(cams=painted.cams, masks=painted.masks)
    out = run(program, compiled_options(options, program), inputs, True)
    core = ("ig", "ig_score", "ig_baseline_score", "occlusion_scores")
    res: dict[str, Any] = {k: np.asarray(v) for k, v in out.items() if k not in core}
    if painting:
        scores = np.asarray(out["occlusion_scores"], np.float64)  # [K, T, B]
        drops = {c: scores[s][:1] - scores[s][1:] for c, s, v in zip(cameras, where, valid, strict=True) if v}
        start = 0
        for kind, m in masks.items():
            reduce = region_map if kind == "occlusion" and options.occlusion_mode == "regions" else iss_map
            res[kind] = {
                c: reduce(m, drops[c][start : start + len(m)]).astype(np.float32)
                if c in drops
                else np.zeros((*scores.shape[1:], *grid), np.float32)  # not read by the model: no drop
                for c in cameras
            }
            start += len(m)
    if "ig" in out:
        steps, best, last_error = options.ig_steps, None, np.inf
        while True:
            attr = np.asarray(out["ig"])  # [T, B, C, N]
            check = (np.asarray(out["ig_score"]), np.asarray(out["ig_baseline_score"]))
            check += (attr.astype(np.float64).sum(axis=(-2, -1)),)
            error = completeness_error(*check)
            if best is None or error < best[0]:
                best = (error, steps, attr, check)
            met = options.ig_tolerance == 0 or error <= options.ig_tolerance
            if met or error > IG_STALL * last_error or 2 * steps > options.ig_max_steps:
                break
            steps, last_error = 2 * steps, error
            out = run(("ig",), compiled_options(options, ("ig",)), ig_inputs(options, steps), program == ("ig",))
        _, steps, attr, check = best  # a doubling into the arithmetic's noise can come out worse than the one before
        res["ig"] = {c: attr[..., i, :].reshape(*attr.shape[:2], *grid) for i, c in enumerate(cameras)}
        res["ig_check"] = check
        res["ig_steps"] = steps
    return res
