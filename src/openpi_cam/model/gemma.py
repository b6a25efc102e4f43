"""Gemma decoder as upstream's `gemma_fast` uses it for pi0-FAST: RMSNorm(1 + scale), RoPE, multi-query attention,
gated-GELU MLP, tied input/output embedding, and a KV cache that decoding appends to.

Params follow upstream's `PaliGemma/llm` tree with the layers stacked on a leading depth axis. Einsum letters:
B batch, T query tokens, S cache slots, D width, N query heads, K kv heads, G = N / K, H head dim, F mlp dim.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from openpi_cam.model import lrp
from openpi_cam.model.config import GemmaConfig

# Upstream masks attention logits with this constant rather than -inf, so fully masked rows get a uniform softmax.
BIG_NEG = -2.3819763e38


class KVCache(NamedTuple):
    k: jax.Array  # [L, B, S, K, H] in the compute dtype
    v: jax.Array  # [L, B, S, K, H]
    idx: jax.Array  # int32 [], the next slot to write


def rms_norm(x: jax.Array, scale: jax.Array, rules: str = "gradient") -> jax.Array:
    var = jnp.mean(jnp.square(x.astype(jnp.float32)), axis=-1, keepdims=True)
    normed = x * lrp.constant(jnp.reciprocal(jnp.sqrt(var + 1e-6)), rules)
    return (normed * (1 + scale)).astype(x.dtype)


def embed_tokens(params: dict, tokens: jax.Array, dtype) -> jax.Array:
    table = params["embedder"]["input_embedding"]
    x = table[(tokens,)]
    return (x * jnp.sqrt(table.shape[1]).astype(x.dtype)).astype(dtype)


def logits_from_prelogits(params: dict, pre_logits: jax.Array) -> jax.Array:
    """Tied output projection: pre_logits [..., D] @ input_embedding.T -> [..., V]."""
    return jnp.dot(pre_logits, params["embedder"]["input_embedding"].T.astype(pre_logits.dtype))


def apply_rope(x: jax.Array, positions: jax.Array, max_wavelength: float = 10_000.0) -> jax.Array:
    """x [B, T, N, H], positions [B, T] -> float32, rotating the two halves of the head dim."""
    half = x.shape[-1] // 2
    timescale = max_wavelength ** ((2.0 / x.shape[-1]) * jnp.arange(half, dtype=jnp.float32))
    radians = (positions[..., None] / timescale)[..., None, :]  # [B, T, 1, H/2]
    sin, cos = jnp.sin(radians), jnp.cos(radians)
    x1, x2 = jnp.split(x, 2, axis=-1)
    return jnp.concatenate([x1 * cos - x2 * sin, x2 * cos + x1 * sin], axis=-1)


def einsum_lora(eq: str, x: jax.Array, p: dict, name: str, lora_scale: float) -> jax.Array:
    """`x @ w` plus, for a LoRA checkpoint, the low-rank update `x @ a @ b * alpha / rank` (upstream's lora.Einsum)."""
    y = jnp.einsum(eq, x, p[name]["w"].astype(x.dtype))
    if "lora_a" in p[name]:
        lhs, rhs, out = eq.replace("->", ",").split(",")
        r_in, r_out = rhs[-2], rhs[-1]  # LoRA factorises the last two weight axes through a rank axis 'L'
        a_out = out.replace(r_out, "L")
        u = jnp.einsum(f"{lhs},{rhs.replace(r_out, 'L')}->{a_out}", x, p[name]["lora_a"].astype(x.dtype))
        y = (
            y
            + jnp.einsum(f"{a_out},{rhs.replace(r_in, 'L')}->{out}", u, p[name]["lora_b"].astype(x.dtype)) * lora_scale
        )
    return y


def feed_forward(x: jax.Array, p: dict, rules: str = "gradient") -> jax.Array:
    def dot(h, name, idx=None):
        w = p[name] if idx is None else p[name][idx]
        y = jnp.dot(h, w.astype(h.dtype))
        if name + "_lora_a" in p:  # upstream's FFN LoRA carries no alpha/rank scaling
            a, b = p[name + "_lora_a"], p[name + "_lora_b"]
            a, b = (a, b) if idx is None else (a[idx], b[idx])
            y = y + jnp.dot(jnp.dot(h, a.astype(h.dtype)), b.astype(h.dtype))
        return y

    gate = lrp.gelu(dot(x, "gating_einsum", 0), rules)
    return dot(lrp.split(gate * dot(x, "gating_einsum", 1), rules), "linear")


def _attention(x, p, positions, mask, k_cache, v_cache, idx, cfg: GemmaConfig, rows: slice, hidden_slots: int):
    """One layer's attention. Every new token's K/V is written into the cache at `idx`; the queries `rows` of them
    attend to every cache slot allowed by `mask` [B, T, S].

    `hidden_slots`: zero-filled slots past the cache's end that the mask hides (a replay that stops short of the
    decode length). They change nothing for a query that sees some slot, but a fully masked query softmaxes uniformly
    over all slots, so its weights are 1 / (S + hidden_slots), as with the full-length cache."""
    scale = cfg.lora_alpha / cfg.lora_rank if cfg.lora_rank else 1.0
    q = einsum_lora("BTD,NDH->BTNH", x[:, rows], p, "q_einsum", scale)
    k, v = einsum_lora("BSD,CKDH->CBSKH", x, p, "kv_einsum", scale)
    q = apply_rope(q, positions[:, rows]) * cfg.head_dim**-0.5  # float32 from here on, as upstream
    k = apply_rope(k, positions)
    k_cache = jax.lax.dynamic_update_slice(k_cache, k.astype(k_cache.dtype), (0, idx, 0, 0))
    v_cache = jax.lax.dynamic_update_slice(v_cache, v.astype(v_cache.dtype), (0, idx, 0, 0))

    b, t, n, h = q.shape
    q = q.reshape(b, t, cfg.num_kv_heads, n // cfg.num_kv_heads, h)
    q, k_att, v_att = lrp.attention_operands(q, k_cache, v_cache, cfg.rules)
    encoded = attend(q, k_att, v_att, mask[:, rows], hidden_slots).reshape(b, t, n, h)
    return einsum_lora("BTNH,NHD->BTD", encoded, p, "attn_vec_einsum", scale), k_cache, v_cache


def _masked_softmax_attention(q, k, v, mask, hidden_slots):
    """-> (values [B, T, K, G, H] in v's dtype, probs float32 [B, K, G, T, S]); see `attend`."""
    logits = jnp.einsum("BTKGH,BSKH->BKGTS", q, k, preferred_element_type=jnp.float32)
    probs = jax.nn.softmax(jnp.where(mask[:, None, None], logits, BIG_NEG), axis=-1)
    if hidden_slots:
        blind = ~jnp.any(mask, axis=-1)[:, None, None, :, None]  # [B, 1, 1, T, 1]
        probs = jnp.where(blind, jnp.float32(1.0 / (mask.shape[-1] + hidden_slots)), probs)
    return jnp.einsum("BKGTS,BSKH->BTKGH", probs.astype(v.dtype), v), probs


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def attend(q: jax.Array, k: jax.Array, v: jax.Array, mask: jax.Array, hidden_slots: int) -> jax.Array:
    """Masked softmax attention: q [B, T, K, G, H] (scaled), k, v [B, S, K, H], mask [B, T, S] ->
    [B, T, K, G, H] in v's dtype. Masked logits are BIG_NEG, not -inf, as upstream; `hidden_slots`: see `_attention`.

    The forward pass is the plain computation (inference runs nothing else). The backward pass is written out,
    because the differentiated `where` + softmax made XLA:CPU pass over the float32 [B, K, G, T, S] arrays several
    times more, at a cost above the backward pass's matmuls (docs/DESIGN_NOTES.md)."""
    return _masked_softmax_attention(q, k, v, mask, hidden_slots)[0]


def _attend_fwd(q, k, v, mask, hidden_slots):
    out, probs = _masked_softmax_attention(q, k, v, mask, hidden_slots)
    return out, (q, k, v, mask, probs)


def _attend_bwd(hidden_slots, res, d_out):
    del hidden_slots  # the uniform rows it sets are constants: no gradient reaches their logits
    q, k, v, mask, probs = res
    d_probs = jnp.einsum("BTKGH,BSKH->BKGTS", d_out, v, preferred_element_type=jnp.float32)
    # Softmax's derivative, kept only where the logit is a real one: masked logits are the constant BIG_NEG.
    d_logits = probs * (d_probs - jnp.sum(probs * d_probs, axis=-1, keepdims=True))
    d_logits = jnp.where(mask[:, None, None], d_logits, 0.0)
    d_q = jnp.einsum("BKGTS,BSKH->BTKGH", d_logits, k, preferred_element_type=jnp.float32).astype(q.dtype)
    d_k = jnp.einsum("BKGTS,BTKGH->BSKH", d_logits, q, preferred_element_type=jnp.float32).astype(k.dtype)
    d_v = jnp.einsum("BKGTS,BTKGH->BSKH", probs.astype(v.dtype), d_out).astype(v.dtype)
    return d_q, d_k, d_v, None


attend.defvjp(_attend_fwd, _attend_bwd)


def forward(
    params: dict,
    x: jax.Array,
    positions: jax.Array,
    mask: jax.Array,
    cfg: GemmaConfig,
    cache: KVCache | None = None,
    *,
    last_only: bool = False,
    hidden_slots: int = 0,
) -> tuple[jax.Array, KVCache]:
    """Runs the decoder on embedded tokens x [B, T, D] and returns (pre_logits [B, T, D], updated cache).

    Without a cache (prefill) a cache of `mask.shape[-1]` zero-filled slots is created and the T tokens fill its
    first T slots; with a cache the T tokens are appended at `cache.idx`. Either way every query attends over the
    whole cache under `mask` [B, T, S], exactly as upstream's decode=True path.

    `last_only` (a prefill whose only output used is its last token's): the top layer computes every token's K/V,
    which the cache needs, but the queries, attention and MLP of the last token alone; pre_logits is [B, 1, D].
    `hidden_slots`: see `_attention`.
    """
    pre, cache, _ = _forward(params, x, positions, mask, cfg, cache, last_only, False, hidden_slots)
    return pre, cache


def forward_with_outputs(
    params: dict, x: jax.Array, positions: jax.Array, mask: jax.Array, cfg: GemmaConfig, *, hidden_slots: int = 0
) -> tuple[jax.Array, KVCache, jax.Array]:
    """A `last_only` prefill (`forward`) that also returns every token's final-normed output [B, T, D] (a failure
    monitor's features). The last token's pre_logits and the cache are computed by the very operations `forward`
    runs, so decoding from them is unchanged; every token's output costs the top layer's queries, attention and MLP
    over all T tokens once more (its K/V are the same operations as the last-only pass's). Returns (pre_logits
    [B, 1, D], cache, outputs [B, T, D])."""
    pre, cache, outputs = _forward(params, x, positions, mask, cfg, None, True, True, hidden_slots)
    assert outputs is not None
    return pre, cache, outputs


def _forward(
    params: dict,
    x: jax.Array,
    positions: jax.Array,
    mask: jax.Array,
    cfg: GemmaConfig,
    cache: KVCache | None,
    last_only: bool,
    every_output: bool,
    hidden_slots: int,
) -> tuple[jax.Array, KVCache, jax.Array | None]:
    b, t, _ = x.shape
    if cache is None:
        slots = mask.shape[-1]
        shape = (cfg.depth, b, slots, cfg.num_kv_heads, cfg.head_dim)
        cache = KVCache(jnp.zeros(shape, x.dtype), jnp.zeros(shape, x.dtype), jnp.zeros((), jnp.int32))

    def layer(h, p, k_cache, v_cache, top_only):
        rows = slice(-1, None) if top_only else slice(None)
        attn, k_cache, v_cache = _attention(
            rms_norm(h, p["pre_attention_norm"]["scale"], cfg.rules),
            p["attn"],
            positions,
            mask,
            k_cache,
            v_cache,
            cache.idx,
            cfg,
            rows,
            hidden_slots,
        )
        h = h[:, rows] + attn
        h = h + feed_forward(rms_norm(h, p["pre_ffw_norm"]["scale"], cfg.rules), p["mlp"], cfg.rules)
        return h, (k_cache, v_cache)

    if cfg.remat:
        layer = jax.checkpoint(layer, static_argnums=(4,))
    stack = (params["layers"], cache.k, cache.v)
    outputs = None
    if not last_only:
        x, (k, v) = jax.lax.scan(lambda h, xs: layer(h, *xs, False), x, stack, unroll=not cfg.scan)
    else:
        # Layer i read inside the loop: scanning over a slice of the stack would copy all but one layer's weights
        # (the top layer's own slice costs one layer's weights of temporaries).
        def body(h, i):
            return layer(h, *jax.tree.map(lambda a: a[i], stack), False)

        below, (k, v) = jax.lax.scan(body, x, jnp.arange(cfg.depth - 1), unroll=not cfg.scan)
        top = jax.tree.map(lambda a: a[-1], stack)
        x, (k_top, v_top) = layer(below, *top, True)
        k, v = jnp.concatenate([k, k_top[None]]), jnp.concatenate([v, v_top[None]])
        if every_output:
            every, _ = layer(below, *top, False)
            outputs = rms_norm(every, params["final_norm"]["scale"], cfg.rules)
    return rms_norm(x, params["final_norm"]["scale"], cfg.rules), KVCache(k, v, cache.idx + t), outputs
