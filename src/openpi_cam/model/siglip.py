"""SigLIP ViT image encoder as pi0-FAST uses it: one output token per patch, no pooling, linear head to the LLM width.

Params follow upstream's `PaliGemma/img` tree (big_vision names, encoder blocks stacked on a leading depth axis).
Dtypes follow upstream: the patch embedding and position embedding in float32, everything after in `dtype`
(matmuls in `dtype`, LayerNorm statistics in float32).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from openpi_cam.model import lrp
from openpi_cam.model.config import SiglipConfig

LN_EPS = 1e-6


def layer_norm(x: jax.Array, p: dict, dtype, rules: str = "gradient") -> jax.Array:
    """flax LayerNorm (use_fast_variance): statistics in float32, result cast to the compute dtype; `rules`: the
    backward pass's (`model.lrp`)."""
    xf = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    mean = jnp.mean(xf, -1, keepdims=True)
    var = jnp.maximum(jnp.mean(jnp.square(xf), -1, keepdims=True) - jnp.square(mean), 0.0)
    y = (xf - mean) * (lrp.constant(jax.lax.rsqrt(var + LN_EPS), rules) * p["scale"]) + p["bias"]
    return y.astype(dtype)


def _dense(x: jax.Array, p: dict, eq: str) -> jax.Array:
    return jnp.einsum(eq, x, p["kernel"].astype(x.dtype)) + p["bias"].astype(x.dtype)


def attention_weights(logits: jax.Array, dtype) -> jax.Array:
    """Softmax over the keys (the last axis), cast to the compute dtype. Every rule keeps its plain gradient
    (`model.lrp`: AttnLRP's softmax rule is input x gradient)."""
    return jax.nn.softmax(logits, axis=-1).astype(dtype)


def attention_sublayer(x: jax.Array, p: dict, rules: str = "gradient") -> jax.Array:
    """x + multi-head self-attention of LayerNorm_0(x), the first half of an encoder block (its params `p`)."""
    dtype = x.dtype
    y = layer_norm(x, p["LayerNorm_0"], dtype, rules)
    att = p["MultiHeadDotProductAttention_0"]
    q = _dense(y, att["query"], "btw,wnh->btnh")
    k = _dense(y, att["key"], "btw,wnh->btnh")
    v = _dense(y, att["value"], "btw,wnh->btnh")
    q = q / jnp.sqrt(q.shape[-1]).astype(dtype)
    probs = attention_weights(lrp.split(jnp.einsum("btnh,bsnh->bnts", q, k), rules), dtype)
    return x + _dense(lrp.split(jnp.einsum("bnts,bsnh->btnh", probs, v), rules), att["out"], "btnh,nhw->btw")


def mlp_sublayer(x: jax.Array, p: dict, rules: str = "gradient") -> jax.Array:
    """x + the GELU MLP of LayerNorm_1(x), the second half of an encoder block (its params `p`)."""
    y = layer_norm(x, p["LayerNorm_1"], x.dtype, rules)
    mlp = p["MlpBlock_0"]
    y = lrp.gelu(_dense(y, mlp["Dense_0"], "btw,wm->btm"), rules)
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
        return mlp_sublayer(attention_sublayer(h, layer_params, cfg.rules), layer_params, cfg.rules), None

    x, _ = jax.lax.scan(body, x, params["Transformer"]["encoderblock"], unroll=not cfg.scan)
    x = layer_norm(x, params["Transformer"]["encoder_norm"], dtype, cfg.rules)
    return _dense(x, params["head"], "btw,wo->bto")
