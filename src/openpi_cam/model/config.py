"""Model hyperparameters: named variants for building from scratch, and read-back from a checkpoint's shapes."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

# Upstream's PaliGemma tokenizer id that ends a generation.
EOS_TOKEN = 1
# Upstream's default decoding budget (`Pi0FAST.sample_actions(max_decoding_steps=256)`).
MAX_DECODING_STEPS = 256


def scan_by_default(depth: int) -> bool:
    """Read-back rule for the `scan` field: deep stacks (real checkpoints, 18 / 27 layers) run as one scanned layer,
    which keeps compilation cheap; stacks of at most 2 layers are unrolled, because differentiating a scan on
    XLA:CPU slices and transposes every stacked activation (`benchmarks/bench_train.py`)."""
    return depth > 2


@dataclasses.dataclass(frozen=True)
class GemmaConfig:
    width: int = 2048
    depth: int = 18
    mlp_dim: int = 16_384
    num_heads: int = 8
    num_kv_heads: int = 1
    head_dim: int = 256
    vocab_size: int = 257_152
    # LoRA adapters (upstream gemma_2b_lora: rank 16, alpha 16 on attention and FFN); rank 0 = none. A checkpoint does
    # not store alpha: read-back assumes upstream's alpha = rank.
    lora_rank: int = 0
    lora_alpha: float = 0.0
    scan: bool = True  # run the layer stack as `lax.scan` (False: unrolled), as upstream's `scan` option


@dataclasses.dataclass(frozen=True)
class SiglipConfig:
    width: int = 1152
    depth: int = 27
    mlp_dim: int = 4304
    num_heads: int = 16
    patch_size: int = 14
    image_size: int = 224  # square images, as upstream's pi0-FAST (224 x 224)
    out_dim: int = 2048  # the linear head projects onto the LLM width
    scan: bool = True  # run the encoder blocks as `lax.scan` (False: unrolled)

    @property
    def grid(self) -> tuple[int, int]:
        n = self.image_size // self.patch_size
        return (n, n)

    @property
    def num_tokens(self) -> int:
        h, w = self.grid
        return h * w


@dataclasses.dataclass(frozen=True)
class Pi0FASTConfig:
    gemma: GemmaConfig = GemmaConfig()
    siglip: SiglipConfig = SiglipConfig()
    action_dim: int = 32
    action_horizon: int = 32
    max_token_len: int = 250
    # Compute dtype. Upstream serves released checkpoints in bfloat16; the goldens are float32.
    dtype: str = "bfloat16"

    @property
    def image_resolution(self) -> tuple[int, int]:
        return (self.siglip.image_size, self.siglip.image_size)


GEMMA_VARIANTS: dict[str, GemmaConfig] = {
    "gemma_2b": GemmaConfig(),
    "gemma_2b_lora": GemmaConfig(lora_rank=16, lora_alpha=16.0),
}

# Widths/depths/mlp/heads of big_vision's ViT family that PaliGemma uses; "/N" gives the patch size.
_SIGLIP_FAMILY: dict[str, tuple[int, int, int, int]] = {
    "mu": (32, 1, 128, 2),
    "Ti": (192, 12, 768, 3),
    "S": (384, 12, 1536, 6),
    "B": (768, 12, 3072, 12),
    "L": (1024, 24, 4096, 16),
    "So400m": (1152, 27, 4304, 16),
}


def siglip_variant(name: str, *, out_dim: int, image_size: int = 224, **overrides: Any) -> SiglipConfig:
    """`siglip_variant("So400m/14", out_dim=2048)` -> the SigLIP config upstream builds for pi0-FAST."""
    family, _, patch = name.partition("/")
    if family not in _SIGLIP_FAMILY or not patch.isdigit():
        raise ValueError(f"unknown SigLIP variant {name!r}; expected one of {sorted(_SIGLIP_FAMILY)} + '/<patch>'")
    width, depth, mlp_dim, heads = _SIGLIP_FAMILY[family]
    base = SiglipConfig(width, depth, mlp_dim, heads, int(patch), image_size, out_dim)
    return dataclasses.replace(base, **overrides)


def pi0_fast_config(paligemma_variant: str = "gemma_2b", siglip: str = "So400m/14", **kwargs: Any) -> Pi0FASTConfig:
    """Upstream's `Pi0FASTConfig(paligemma_variant=...)` architecture, with the data-side sizes as keywords."""
    gemma = GEMMA_VARIANTS[paligemma_variant]
    return Pi0FASTConfig(gemma=gemma, siglip=siglip_variant(siglip, out_dim=gemma.width), **kwargs)


def _leaf(flat: Mapping[str, Any], path: str) -> tuple[int, ...]:
    if path not in flat:
        raise ValueError(f"checkpoint has no parameter {path!r}: not a pi0-FAST (PaliGemma) params tree")
    value = flat[path]
    return tuple(value) if isinstance(value, tuple) else tuple(value.shape)


def architecture_from_params(flat: Mapping[str, Any], *, scan: bool | None = None) -> tuple[GemmaConfig, SiglipConfig]:
    """Reads every size from the parameter shapes, so a tiny test checkpoint and the 3B one load the same way.

    `flat` maps '/'-joined upstream paths (e.g. 'PaliGemma/llm/embedder/input_embedding') to arrays or shape tuples.
    `scan` sets both stacks' layout; None applies `scan_by_default` to each stack's depth.
    """
    llm, img = "PaliGemma/llm/", "PaliGemma/img/"
    vocab, width = _leaf(flat, llm + "embedder/input_embedding")
    depth, num_heads, _, head_dim = _leaf(flat, llm + "layers/attn/q_einsum/w")
    num_kv_heads = _leaf(flat, llm + "layers/attn/kv_einsum/w")[2]
    mlp_dim = _leaf(flat, llm + "layers/mlp/linear")[1]
    lora_key = llm + "layers/attn/q_einsum/lora_a"
    lora_rank = _leaf(flat, lora_key)[-1] if lora_key in flat else 0
    gemma_scan = scan_by_default(depth) if scan is None else scan
    gemma = GemmaConfig(
        width, depth, mlp_dim, num_heads, num_kv_heads, head_dim, vocab, lora_rank, float(lora_rank), gemma_scan
    )

    patch, _, _, v_width = _leaf(flat, img + "embedding/kernel")
    v_depth = _leaf(flat, img + "Transformer/encoderblock/LayerNorm_0/scale")[0]
    v_heads = _leaf(flat, img + "Transformer/encoderblock/MultiHeadDotProductAttention_0/query/kernel")[2]
    v_mlp = _leaf(flat, img + "Transformer/encoderblock/MlpBlock_0/Dense_0/kernel")[-1]
    n_tokens = _leaf(flat, img + "pos_embedding")[1]
    side = math.isqrt(n_tokens)
    if side * side != n_tokens:
        raise ValueError(f"SigLIP pos_embedding has {n_tokens} tokens: not a square patch grid")
    out_dim = _leaf(flat, img + "head/kernel")[1]
    siglip_scan = scan_by_default(v_depth) if scan is None else scan
    siglip = SiglipConfig(v_width, v_depth, v_mlp, v_heads, patch, side * patch, out_dim, siglip_scan)
    return gemma, siglip


def param_shapes(gemma: GemmaConfig, siglip: SiglipConfig) -> dict[str, tuple[int, ...]]:
    """The parameter tree (paths and shapes) upstream's Pi0FAST has for this architecture."""
    D, W, M, N, K, H = gemma.depth, gemma.width, gemma.mlp_dim, gemma.num_heads, gemma.num_kv_heads, gemma.head_dim
    d, w, m, n, p = siglip.depth, siglip.width, siglip.mlp_dim, siglip.num_heads, siglip.patch_size
    hd = w // n
    llm, blk = "PaliGemma/llm/", "PaliGemma/img/Transformer/encoderblock/"
    shapes = {
        llm + "embedder/input_embedding": (gemma.vocab_size, W),
        llm + "final_norm/scale": (W,),
        llm + "layers/pre_attention_norm/scale": (D, W),
        llm + "layers/pre_ffw_norm/scale": (D, W),
        llm + "layers/attn/q_einsum/w": (D, N, W, H),
        llm + "layers/attn/kv_einsum/w": (D, 2, K, W, H),
        llm + "layers/attn/attn_vec_einsum/w": (D, N, H, W),
        llm + "layers/mlp/gating_einsum": (D, 2, W, M),
        llm + "layers/mlp/linear": (D, M, W),
        "PaliGemma/img/embedding/kernel": (p, p, 3, w),
        "PaliGemma/img/embedding/bias": (w,),
        "PaliGemma/img/pos_embedding": (1, siglip.num_tokens, w),
        "PaliGemma/img/Transformer/encoder_norm/scale": (w,),
        "PaliGemma/img/Transformer/encoder_norm/bias": (w,),
        "PaliGemma/img/head/kernel": (w, siglip.out_dim),
        "PaliGemma/img/head/bias": (siglip.out_dim,),
    }
    for ln in ("LayerNorm_0", "LayerNorm_1"):
        shapes[blk + f"{ln}/scale"] = shapes[blk + f"{ln}/bias"] = (d, w)
    att = blk + "MultiHeadDotProductAttention_0/"
    for proj in ("query", "key", "value"):
        shapes[att + f"{proj}/kernel"] = (d, w, n, hd)
        shapes[att + f"{proj}/bias"] = (d, n, hd)
    shapes[att + "out/kernel"] = (d, n, hd, w)
    shapes[att + "out/bias"] = (d, w)
    shapes[blk + "MlpBlock_0/Dense_0/kernel"] = (d, w, m)
    shapes[blk + "MlpBlock_0/Dense_0/bias"] = (d, m)
    shapes[blk + "MlpBlock_0/Dense_1/kernel"] = (d, m, w)
    shapes[blk + "MlpBlock_0/Dense_1/bias"] = (d, w)
    if r := gemma.lora_rank:
        a = llm + "layers/attn/"
        shapes |= {
            a + "q_einsum/lora_a": (D, N, W, r),
            a + "q_einsum/lora_b": (D, N, r, H),
            a + "kv_einsum/lora_a": (D, 2, K, W, r),
            a + "kv_einsum/lora_b": (D, 2, K, r, H),
            a + "attn_vec_einsum/lora_a": (D, N, H, r),
            a + "attn_vec_einsum/lora_b": (D, N, r, W),
            llm + "layers/mlp/gating_einsum_lora_a": (D, 2, W, r),
            llm + "layers/mlp/gating_einsum_lora_b": (D, 2, r, M),
            llm + "layers/mlp/linear_lora_a": (D, M, r),
            llm + "layers/mlp/linear_lora_b": (D, r, W),
        }
    return dict(sorted(shapes.items()))


def check_param_tree(flat_shapes: Mapping[str, tuple[int, ...]], expected: Mapping[str, tuple[int, ...]]) -> None:
    """Raises ValueError naming the first missing / unexpected / mis-shaped path."""
    for path in sorted(expected):
        if path not in flat_shapes:
            raise ValueError(f"checkpoint is missing parameter {path!r} (expected shape {list(expected[path])})")
    for path in sorted(flat_shapes):
        if path not in expected:
            raise ValueError(f"checkpoint has unexpected parameter {path!r} (shape {list(flat_shapes[path])})")
    for path in sorted(expected):
        if tuple(flat_shapes[path]) != tuple(expected[path]):
            raise ValueError(f"parameter {path!r} has shape {list(flat_shapes[path])}, expected {list(expected[path])}")
