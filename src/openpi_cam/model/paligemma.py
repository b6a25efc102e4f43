"""The PaliGemma backbone every pi0 family shares: SigLIP tokens of every camera and the embedded prompt as one
bidirectional prefix.

Shapes: B batch, C cameras, N tokens per camera, L prompt length, D LLM width.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import jax
import jax.numpy as jnp

from openpi_cam.model import gemma, siglip
from openpi_cam.model.config import SiglipConfig
from openpi_cam.model.observation import Observation


class VLMConfig(Protocol):
    """What the prefix needs from a family's config."""

    @property
    def siglip(self) -> SiglipConfig: ...

    @property
    def dtype(self) -> str: ...


def make_attn_mask(input_mask: jax.Array, ar_mask: jax.Array) -> jax.Array:
    """big_vision's prefix-LM rule: token i sees valid token j iff cumsum(ar)[j] <= cumsum(ar)[i]. -> [B, T, T]"""
    ar_mask = jnp.broadcast_to(ar_mask, input_mask.shape)
    cumsum = jnp.cumsum(ar_mask, axis=1)
    allowed = cumsum[:, None, :] <= cumsum[:, :, None]
    valid = input_mask[:, None, :] & input_mask[:, :, None]
    return allowed & valid


def embed_images(params: dict, obs: Observation, cfg: VLMConfig) -> jax.Array:
    """SigLIP tokens of every camera, in camera order -> [B, C, N, D] (what the LLM sees; the maps' input)."""
    dtype = jnp.dtype(cfg.dtype)
    img_params = params["PaliGemma"]["img"]
    return jnp.stack([siglip.encode_images(img_params, im, cfg.siglip, dtype) for im in obs.images.values()], axis=1)


def embed_prefix(params: dict, image_tokens: jax.Array, obs: Observation, cfg: VLMConfig):
    """[image tokens of every camera | prompt tokens] with input and AR masks, as upstream's `embed_inputs`."""
    b, c, n, d = image_tokens.shape
    dtype = jnp.dtype(cfg.dtype)
    prompt = gemma.embed_tokens(params["PaliGemma"]["llm"], obs.tokenized_prompt, dtype)
    x = jnp.concatenate([image_tokens.reshape(b, c * n, d).astype(dtype), prompt], axis=1)
    cam_mask = jnp.stack([jnp.asarray(obs.image_masks[k], bool) for k in obs.images], axis=1)  # [B, C]
    input_mask = jnp.concatenate([jnp.repeat(cam_mask, n, axis=1), jnp.asarray(obs.tokenized_prompt_mask, bool)], 1)
    ar = obs.token_ar_mask if obs.token_ar_mask is not None else jnp.zeros_like(obs.tokenized_prompt)
    ar_mask = jnp.concatenate([jnp.zeros((b, c * n), jnp.int32), jnp.asarray(ar, jnp.int32)], axis=1)
    return x, input_mask, ar_mask


def pool_prefix(
    outputs: jax.Array, input_mask: jax.Array, cameras: Sequence[str], tokens_per_camera: int
) -> tuple[dict[str, jax.Array], jax.Array]:
    """The prefix's outputs pooled per span, a failure monitor's features: each camera's image tokens, then the
    prompt's (every token after the images), each the mean of its valid tokens' outputs in float32 (NaN where none
    is valid: a masked camera). outputs [B, P, D] and input_mask [B, P] in prefix order (`embed_prefix`: cameras in
    `cameras` order, `tokens_per_camera` each, then the prompt). Returns (camera -> [B, D], prompt [B, D]).

    The mean, not the max: it summarises hundreds of image tokens, or a prompt of any length, on one scale, where a
    per-dimension max grows with the count and follows the most extreme single token."""
    x = outputs.astype(jnp.float32)
    valid = input_mask.astype(jnp.float32)

    def mean(start: int, stop: int) -> jax.Array:
        w = valid[:, start:stop]
        count = jnp.sum(w, axis=-1, keepdims=True)
        total = jnp.einsum("bt,btd->bd", w, x[:, start:stop])
        return jnp.where(count > 0, total / jnp.maximum(count, 1.0), jnp.nan)

    n = tokens_per_camera
    pooled = {camera: mean(i * n, (i + 1) * n) for i, camera in enumerate(cameras)}
    return pooled, mean(len(cameras) * n, x.shape[1])
