"""Model hyperparameters (the defaults are upstream's full-size architecture), and read-back from a checkpoint's
shapes."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, Literal

# Upstream's PaliGemma tokenizer id that ends a generation.
EOS_TOKEN = 1
# Upstream's default decoding budget (`Pi0FAST.sample_actions(max_decoding_steps=256)`).
MAX_DECODING_STEPS = 256
# The cameras upstream's pi0 / pi0.5 read, in token order (upstream `IMAGE_KEYS`).
PI0_IMAGE_KEYS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
# How a layer stack's backward pass treats its non-linear operations (`model.lrp`): "gradient" differentiates them,
# "lrp" applies AttnLRP's rules so that input x gradient is relevance. The forward pass is the same under both.
Rules = Literal["gradient", "lrp"]
RULES: tuple[str, ...] = ("gradient", "lrp")


def remat_by_default(width: int) -> bool:
    """Read-back rule for the `remat` field: full-size stacks (Gemma 2B: width 2048; the 300M action expert: 1024)
    recompute their layers in the backward pass, because a full-size explanation's stored activations need more than
    a CPU host's memory (docs/DESIGN_NOTES.md); small models keep their activations, which is faster. A device with
    room drops remat per program (`remat.backward_layout`)."""
    return width >= 1024


def scan_by_default(depth: int) -> bool:
    """Read-back rule for the `scan` field: deep stacks (real checkpoints, 18 / 27 layers) run as one scanned layer,
    which keeps compilation cheap; stacks of at most 2 layers are unrolled, because differentiating a scan on
    XLA:CPU slices and transposes every stacked activation (docs/DESIGN_NOTES.md)."""
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
    # Recompute each layer in the backward pass instead of storing its activations (`jax.checkpoint`): explanations
    # of full-size models trade a second forward for memory. No effect on a forward pass.
    remat: bool = False
    rules: Rules = "gradient"  # the backward pass's rules (`RULES`); no effect on a forward pass


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
    rules: Rules = "gradient"  # the backward pass's rules (`RULES`); no effect on a forward pass

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


@dataclasses.dataclass(frozen=True)
class Pi0Config:
    """pi0 / pi0.5: the PaliGemma backbone (`gemma`, `siglip`) plus a flow-matching action expert (`expert`, the
    `_1` weights). pi0.5 (`pi05`) conditions the expert's norms on the time (adaRMS) and reads the state as prompt
    text; pi0 feeds the state as one token through `state_proj`.

    `image_keys` are the cameras the model reads, in token order (upstream's three; a LeRobot policy's are its
    config's image features). `flow_time` is how the Euler integration's times and their sine-cosine embedding are
    evaluated: "openpi" accumulates t += dt and embeds t in float32 (upstream's JAX model); "lerobot" rounds
    t = 1 + k dt once and embeds it in float64 before rounding to float32 (LeRobot's PyTorch port), so that its
    chunks are reproduced to float32 rounding rather than to the float32 error of the embedding."""

    gemma: GemmaConfig = GemmaConfig()
    expert: GemmaConfig = GemmaConfig(width=1024, mlp_dim=4096, vocab_size=0)
    siglip: SiglipConfig = SiglipConfig()
    pi05: bool = False
    action_dim: int = 32
    action_horizon: int = 50
    max_token_len: int = 48  # upstream: 48 for pi0, 200 for pi0.5
    dtype: str = "bfloat16"
    num_steps: int = 10  # Euler steps of `sample_actions`, upstream's default
    image_keys: tuple[str, ...] = PI0_IMAGE_KEYS
    flow_time: Literal["openpi", "lerobot"] = "openpi"

    @property
    def image_resolution(self) -> tuple[int, int]:
        return (self.siglip.image_size, self.siglip.image_size)


def _leaf(flat: Mapping[str, Any], path: str) -> tuple[int, ...]:
    if path not in flat:
        raise ValueError(f"checkpoint has no parameter {path!r}: not an OpenPI PaliGemma params tree")
    value = flat[path]
    return tuple(value) if isinstance(value, tuple) else tuple(value.shape)


LLM = "PaliGemma/llm/"
IMG = "PaliGemma/img/"


def family_of(flat: Mapping[str, Any]) -> str:
    """ "pi0_fast", "pi0" or "pi05", from which leaves the tree has (the action expert's projections, its
    time MLP)."""
    if "action_in_proj/kernel" not in flat:
        return "pi0_fast"
    return "pi05" if "time_mlp_in/kernel" in flat else "pi0"


def _gemma_from(flat: Mapping[str, Any], suffix: str, vocab: int, scan: bool | None) -> GemmaConfig:
    """One Gemma stack's sizes from its weights (`suffix` "" for the PaliGemma LLM, "_1" for the action expert)."""
    depth, num_heads, width, head_dim = _leaf(flat, LLM + f"layers/attn/q_einsum{suffix}/w")
    num_kv_heads = _leaf(flat, LLM + f"layers/attn/kv_einsum{suffix}/w")[2]
    mlp_dim = _leaf(flat, LLM + f"layers/mlp{suffix}/linear")[1]
    lora_key = LLM + f"layers/attn/q_einsum{suffix}/lora_a"
    # A checkpoint does not store LoRA's alpha: upstream's variants all use alpha = rank.
    lora_rank = _leaf(flat, lora_key)[-1] if lora_key in flat else 0
    scan = scan_by_default(depth) if scan is None else scan
    return GemmaConfig(
        width,
        depth,
        mlp_dim,
        num_heads,
        num_kv_heads,
        head_dim,
        vocab,
        lora_rank,
        lora_rank,
        scan,
        remat_by_default(width),
    )


def _siglip_from(flat: Mapping[str, Any], scan: bool | None) -> SiglipConfig:
    patch, _, _, width = _leaf(flat, IMG + "embedding/kernel")
    depth = _leaf(flat, IMG + "Transformer/encoderblock/LayerNorm_0/scale")[0]
    heads = _leaf(flat, IMG + "Transformer/encoderblock/MultiHeadDotProductAttention_0/query/kernel")[2]
    mlp = _leaf(flat, IMG + "Transformer/encoderblock/MlpBlock_0/Dense_0/kernel")[-1]
    n_tokens = _leaf(flat, IMG + "pos_embedding")[1]
    side = math.isqrt(n_tokens)
    if side * side != n_tokens:
        raise ValueError(f"SigLIP pos_embedding has {n_tokens} tokens: not a square patch grid")
    out_dim = _leaf(flat, IMG + "head/kernel")[1]
    scan = scan_by_default(depth) if scan is None else scan
    return SiglipConfig(width, depth, mlp, heads, patch, side * patch, out_dim, scan)


def architecture_from_params(flat: Mapping[str, Any], *, scan: bool | None = None) -> tuple[GemmaConfig, SiglipConfig]:
    """Reads every size of the PaliGemma backbone from the parameter shapes, so a tiny test checkpoint and the 3B one
    load the same way.

    `flat` maps '/'-joined upstream paths (e.g. 'PaliGemma/llm/embedder/input_embedding') to arrays or shape tuples.
    `scan` sets both stacks' layout; None applies `scan_by_default` to each stack's depth.
    """
    vocab = _leaf(flat, LLM + "embedder/input_embedding")[0]
    return _gemma_from(flat, "", vocab, scan), _siglip_from(flat, scan)


def pi0_architecture_from_params(
    flat: Mapping[str, Any], *, scan: bool | None = None
) -> tuple[GemmaConfig, GemmaConfig, SiglipConfig, bool]:
    """(LLM, action expert, SigLIP, pi05) of a pi0 / pi0.5 tree, from its parameter shapes."""
    gemma, siglip = architecture_from_params(flat, scan=scan)
    return gemma, _gemma_from(flat, "_1", 0, scan), siglip, family_of(flat) == "pi05"


def _siglip_shapes(siglip: SiglipConfig) -> dict[str, tuple[int, ...]]:
    d, w, m, n, p = siglip.depth, siglip.width, siglip.mlp_dim, siglip.num_heads, siglip.patch_size
    hd = w // n
    blk = IMG + "Transformer/encoderblock/"
    shapes = {
        IMG + "embedding/kernel": (p, p, 3, w),
        IMG + "embedding/bias": (w,),
        IMG + "pos_embedding": (1, siglip.num_tokens, w),
        IMG + "Transformer/encoder_norm/scale": (w,),
        IMG + "Transformer/encoder_norm/bias": (w,),
        IMG + "head/kernel": (w, siglip.out_dim),
        IMG + "head/bias": (siglip.out_dim,),
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
    return shapes


def _gemma_shapes(gemma: GemmaConfig, suffix: str = "", *, adarms: bool = False) -> dict[str, tuple[int, ...]]:
    """One Gemma stack's layer and final-norm leaves under `suffix`; adaRMS norms carry a `Dense_0` instead of a
    scale (pi0.5's action expert)."""
    D, W, M, N, K, H = gemma.depth, gemma.width, gemma.mlp_dim, gemma.num_heads, gemma.num_kv_heads, gemma.head_dim
    a, mlp = LLM + "layers/attn/", LLM + f"layers/mlp{suffix}/"
    shapes = {
        a + f"q_einsum{suffix}/w": (D, N, W, H),
        a + f"kv_einsum{suffix}/w": (D, 2, K, W, H),
        a + f"attn_vec_einsum{suffix}/w": (D, N, H, W),
        mlp + "gating_einsum": (D, 2, W, M),
        mlp + "linear": (D, M, W),
    }
    for norm in ("pre_attention_norm", "pre_ffw_norm"):
        if adarms:
            shapes[LLM + f"layers/{norm}{suffix}/Dense_0/kernel"] = (D, W, 3 * W)
            shapes[LLM + f"layers/{norm}{suffix}/Dense_0/bias"] = (D, 3 * W)
        else:
            shapes[LLM + f"layers/{norm}{suffix}/scale"] = (D, W)
    if adarms:
        shapes[LLM + f"final_norm{suffix}/Dense_0/kernel"] = (W, 3 * W)
        shapes[LLM + f"final_norm{suffix}/Dense_0/bias"] = (3 * W,)
    else:
        shapes[LLM + f"final_norm{suffix}/scale"] = (W,)
    if r := gemma.lora_rank:
        shapes |= {
            a + f"q_einsum{suffix}/lora_a": (D, N, W, r),
            a + f"q_einsum{suffix}/lora_b": (D, N, r, H),
            a + f"kv_einsum{suffix}/lora_a": (D, 2, K, W, r),
            a + f"kv_einsum{suffix}/lora_b": (D, 2, K, r, H),
            a + f"attn_vec_einsum{suffix}/lora_a": (D, N, H, r),
            a + f"attn_vec_einsum{suffix}/lora_b": (D, N, r, W),
            mlp + "gating_einsum_lora_a": (D, 2, W, r),
            mlp + "gating_einsum_lora_b": (D, 2, r, M),
            mlp + "linear_lora_a": (D, M, r),
            mlp + "linear_lora_b": (D, r, W),
        }
    return shapes


def param_shapes(gemma: GemmaConfig, siglip: SiglipConfig) -> dict[str, tuple[int, ...]]:
    """The parameter tree (paths and shapes) upstream's Pi0FAST has for this architecture."""
    shapes = _siglip_shapes(siglip) | _gemma_shapes(gemma)
    shapes[LLM + "embedder/input_embedding"] = (gemma.vocab_size, gemma.width)
    return dict(sorted(shapes.items()))


def pi0_param_shapes(cfg: Pi0Config) -> dict[str, tuple[int, ...]]:
    """The parameter tree upstream's Pi0 (pi05 False / True) has for this architecture."""
    shapes = param_shapes(cfg.gemma, cfg.siglip) | _gemma_shapes(cfg.expert, "_1", adarms=cfg.pi05)
    we, a = cfg.expert.width, cfg.action_dim
    linears = {"action_in_proj": (a, we), "action_out_proj": (we, a)}
    if cfg.pi05:
        linears |= {"time_mlp_in": (we, we), "time_mlp_out": (we, we)}
    else:
        linears |= {"state_proj": (a, we), "action_time_mlp_in": (2 * we, we), "action_time_mlp_out": (we, we)}
    for name, (fan_in, fan_out) in linears.items():
        shapes[f"{name}/kernel"] = (fan_in, fan_out)
        shapes[f"{name}/bias"] = (fan_out,)
    return dict(sorted(shapes.items()))


def expected_param_shapes(flat: Mapping[str, Any]) -> dict[str, tuple[int, ...]]:
    """The tree upstream builds for the family and architecture that `flat`'s shapes describe."""
    if family_of(flat) == "pi0_fast":
        return param_shapes(*architecture_from_params(flat))
    gemma, expert, siglip, pi05 = pi0_architecture_from_params(flat)
    action_dim = _leaf(flat, "action_in_proj/kernel")[0]
    return pi0_param_shapes(Pi0Config(gemma, expert, siglip, pi05, action_dim=action_dim))


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
