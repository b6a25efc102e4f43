"""SigLIP ViT image encoder as pi0-FAST uses it: one output token per patch, no pooling, linear head to the LLM width.

Params follow upstream's `PaliGemma/img` tree (big_vision names, encoder blocks stacked on a leading depth axis).
Dtypes follow upstream: the patch embedding and position embedding in float32, everything after in `dtype`
(matmuls in `dtype`, LayerNorm statistics in float32).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from openpi_cam.model.config import SiglipConfig

LN_EPS = 1e-6


def layer_norm(x: jax.Array, p: dict, dtype) -> jax.Array:
    """flax LayerNorm (use_fast_variance): statistics in float32, result cast to the compute dtype."""
    xf = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    mean = jnp.mean(xf, -1, keepdims=True)
    var = jnp.maximum(jnp.mean(jnp.square(xf), -1, keepdims=True) - jnp.square(mean), 0.0)
    y = (xf - mean) * (jax.lax.rsqrt(var + LN_EPS) * p["scale"]) + p["bias"]
    return y.astype(dtype)


def _dense(x: jax.Array, p: dict, eq: str) -> jax.Array:
    return jnp.einsum(eq, x, p["kernel"].astype(x.dtype)) + p["bias"].astype(x.dtype)


def _encoder_block(x: jax.Array, p: dict, num_heads: int) -> jax.Array:
    dtype = x.dtype
    y = layer_norm(x, p["LayerNorm_0"], dtype)
    att = p["MultiHeadDotProductAttention_0"]
    q = _dense(y, att["query"], "btw,wnh->btnh")
    k = _dense(y, att["key"], "btw,wnh->btnh")
    v = _dense(y, att["value"], "btw,wnh->btnh")
    q = q / jnp.sqrt(q.shape[-1]).astype(dtype)
    probs = jax.nn.softmax(jnp.einsum("btnh,bsnh->bnts", q, k), axis=-1).astype(dtype)
    y = _dense(jnp.einsum("bnts,bsnh->btnh", probs, v), att["out"], "btnh,nhw->btw")
    x = x + y
    y = layer_norm(x, p["LayerNorm_1"], dtype)
    mlp = p["MlpBlock_0"]
    y = jax.nn.gelu(_dense(y, mlp["Dense_0"], "btw,wm->btm"), approximate=True)
    return x + _dense(y, mlp["Dense_1"], "btm,mw->btw")


def encode_images(params: dict, images: jax.Array, cfg: SiglipConfig, dtype) -> jax.Array:
    """images [B, H, W, 3] in [-1, 1] -> tokens [B, (H/p)*(W/p), out_dim], row-major over the patch grid."""
    x = jax.lax.conv_general_dilated(
        images.astype(jnp.float32),
        params["embedding"]["kernel"].astype(jnp.float32),  # [p, p, 3, w]
        window_strides=(cfg.patch_size, cfg.patch_size),
        padding="VALID",
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
    ) + params["embedding"]["bias"].astype(jnp.float32)
    b, gh, gw, w = x.shape
    x = x.reshape(b, gh * gw, w) + params["pos_embedding"].astype(jnp.float32)
    x = x.astype(dtype)

    def body(h, layer_params):
        return _encoder_block(h, layer_params, cfg.num_heads), None

    x, _ = jax.lax.scan(body, x, params["Transformer"]["encoderblock"], unroll=not cfg.scan)
    x = layer_norm(x, params["Transformer"]["encoder_norm"], dtype)
    return _dense(x, params["head"], "btw,wo->bto")
