"""The `lrp` map kind for any PaliGemma-based family: AttnLRP relevance (`model.lrp`) read at the pixels.

A family supplies what it explains as a function of the image tokens (`output_fn`, built with a config whose rules
are "lrp": `lrp.with_rules`) and the explained scores as cotangents of that output (one per score: a one-hot row for
a token's logit, the chunk weighting for pi0's actions). One backward pass per score runs from the output through the
language model and SigLIP to the model's input images; a camera's map is input x modified gradient summed over each
patch's pixels and channels, on the camera's token grid (row-major, as SigLIP's tokens).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from openpi_cam.model.attribution import patchify
from openpi_cam.model.baseline_maps import camera_stack, with_images
from openpi_cam.model.observation import Observation
from openpi_cam.model.paligemma import VLMConfig, embed_images


def pixel_relevance(
    params: dict,
    obs: Observation,
    cfg: VLMConfig,
    output_fn: Callable[[jax.Array], tuple[jax.Array, Any]],
    cotangents: Callable[[jax.Array], jax.Array],
) -> tuple[jax.Array, Any, jax.Array]:
    """Traced core (call inside a jitted program whose `cfg` has rules "lrp").

    output_fn maps image tokens [B, C, N, D] to (an output y, anything else the caller wants from the same forward
    pass); cotangents(y) gives the explained scores as weightings of y, [T, *y.shape] (score_t = sum(cotangents[t] *
    y)). Returns (y, the aux, relevance [T, B, C, N] float32): each score's relevance summed per patch of every
    camera. The cotangents run one after another (`lax.map`), as the gradient kinds' (`attribution.per_score_grads`)."""
    images, _ = camera_stack(obs)  # [C, B, H, W, 3]

    def of_pixels(stack: jax.Array) -> tuple[jax.Array, Any]:
        return output_fn(embed_images(params, with_images(obs, dict(zip(obs.images, stack, strict=True))), cfg))

    y, vjp_fn, aux = jax.vjp(of_pixels, images, has_aux=True)
    patch = cfg.siglip.patch_size

    def one(cotangent: jax.Array) -> jax.Array:
        (grad,) = vjp_fn(cotangent)
        return jnp.sum(patchify(images * grad.astype(jnp.float32), patch), axis=-1)  # [B, C, N]

    return y, aux, jax.lax.map(one, cotangents(y))
