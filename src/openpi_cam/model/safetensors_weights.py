"""pi0 / pi0.5 weights in PyTorch's layout (`model.safetensors` of a LeRobot policy or of OpenPI's PyTorch export)
read into the OpenPI parameter tree, and written back out of it, without torch.

LeRobot stores every key under `model.` (its policy wraps the core module as `self.model`); OpenPI's PyTorch export
stores the same keys without that prefix. One table (`_layout`) pairs every PyTorch tensor with its place in an
OpenPI leaf (`model.config.pi0_param_shapes` names them: layers stacked on a leading depth axis, einsum layouts) and
the reshape between the two, so reading and writing cannot drift apart.

The architecture comes from the tensors' shapes (a LeRobot `config.json` names `gemma_2b` / `gemma_300m` whatever
the sizes), except the attention head counts, which a `[heads x head_dim, width]` projection does not carry:
`HeadCounts` supplies them (LeRobot's defaults, or a folder's record of its sizes).

Memory: the file is opened (memory-mapped by safetensors) once per tensor and closed after the copy, so the pages of
the mapping, which count in the process's RSS while mapped, are released tensor by tensor; each OpenPI leaf is
allocated once and filled in place, then handed to JAX (on a CPU backend without a copy where it can alias).
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import re
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from safetensors import safe_open

from openpi_cam.errors import reading
from openpi_cam.model.config import (
    GemmaConfig,
    Pi0Config,
    SiglipConfig,
    pi0_param_shapes,
    remat_by_default,
    scan_by_default,
)
from openpi_cam.nested import flatten_dict, unflatten_dict

LEROBOT_PREFIX = "model."  # LeRobot's keys; OpenPI's PyTorch export has none
# PaliGemma's SigLIP (So400m): width 1152 in 16 heads. LeRobot builds it from the Hugging Face PaliGemma defaults.
SO400M_WIDTH, SO400M_HEADS = 1152, 16
# LeRobot's joint attention reshapes its output with 8 query heads, the count of both Gemma variants it knows.
LEROBOT_GEMMA_HEADS = 8
_DTYPE_NAMES = {"float32": "F32", "bfloat16": "BF16", "float16": "F16", "float64": "F64"}  # ours -> safetensors'
_FLOAT_DTYPES = {name: ours for ours, name in _DTYPE_NAMES.items()}

PG = "paligemma_with_expert.paligemma."
LM = PG + "model.language_model."
VT = PG + "model.vision_tower.vision_model."
EX = "paligemma_with_expert.gemma_expert."
LLM, IMG = "PaliGemma/llm/", "PaliGemma/img/"


@dataclasses.dataclass(frozen=True)
class HeadCounts:
    """The attention head counts, which PyTorch's fused projections do not show: `gemma` query heads of the PaliGemma
    LLM and the action expert (they attend jointly, so they agree), `siglip` heads of the vision tower (None: 16 for
    the So400m width, refused for any other)."""

    gemma: int = LEROBOT_GEMMA_HEADS
    siglip: int | None = None


LEROBOT_HEADS = HeadCounts()  # LeRobot's defaults: the PaliGemma variants' and the So400m tower's


@dataclasses.dataclass(frozen=True)
class _Conv:
    """How one PyTorch tensor becomes its slice of an OpenPI leaf (`load`) and back (`save`)."""

    load: Callable[[np.ndarray], np.ndarray]
    save: Callable[[np.ndarray], np.ndarray]


SAME = _Conv(lambda x: x, lambda y: y)
LINEAR = _Conv(lambda x: x.T, lambda y: y.T)  # nn.Linear [out, in] <-> kernel [in, out]
CONV = _Conv(lambda x: x.transpose(2, 3, 1, 0), lambda y: y.transpose(3, 2, 0, 1))  # [w, 3, p, p] <-> [p, p, 3, w]
POS = _Conv(lambda x: x[None], lambda y: y[0])  # [T, w] <-> [1, T, w]


def _q_heads(n: int, h: int) -> _Conv:
    """Gemma q/k/v [n*h, D] <-> einsum [n, D, h] (a head's rows are contiguous, as Hugging Face views them)."""
    return _Conv(lambda x: x.reshape(n, h, -1).transpose(0, 2, 1), lambda y: y.transpose(0, 2, 1).reshape(n * h, -1))


def _out_heads(n: int, h: int) -> _Conv:
    """An attention output projection [D, n*h] <-> [n, h, D]: Gemma's o_proj as attn_vec_einsum, SigLIP's out_proj
    as its out kernel."""
    return _Conv(lambda x: x.T.reshape(n, h, -1), lambda y: y.reshape(n * h, -1).T)


def _in_heads(n: int, h: int) -> _Conv:
    """SigLIP q/k/v [n*h, w] <-> kernel [w, n, h]."""
    return _Conv(lambda x: x.T.reshape(-1, n, h), lambda y: y.reshape(-1, n * h).T)


def _bias_heads(n: int, h: int) -> _Conv:
    return _Conv(lambda x: x.reshape(n, h), lambda y: y.reshape(n * h))


@dataclasses.dataclass(frozen=True)
class _Entry:
    key: str  # PyTorch key without the file's prefix
    shape: tuple[int, ...]  # its shape in PyTorch's layout
    target: str  # OpenPI leaf path
    index: tuple[int, ...]  # where in the (stacked) leaf it goes
    conv: _Conv


def _gemma_entries(cfg: GemmaConfig, torch_root: str, sfx: str, *, adarms: bool) -> list[_Entry]:
    """One Gemma stack: the PaliGemma LLM (`sfx` "") or the action expert (`sfx` "_1")."""
    D, N, K, H, M = cfg.width, cfg.num_heads, cfg.num_kv_heads, cfg.head_dim, cfg.mlp_dim
    attn, mlp = LLM + "layers/attn/", LLM + f"layers/mlp{sfx}/"
    out = []
    for i in range(cfg.depth):
        layer = f"{torch_root}layers.{i}."
        out += [
            _Entry(layer + "self_attn.q_proj.weight", (N * H, D), attn + f"q_einsum{sfx}/w", (i,), _q_heads(N, H)),
            _Entry(layer + "self_attn.k_proj.weight", (K * H, D), attn + f"kv_einsum{sfx}/w", (i, 0), _q_heads(K, H)),
            _Entry(layer + "self_attn.v_proj.weight", (K * H, D), attn + f"kv_einsum{sfx}/w", (i, 1), _q_heads(K, H)),
            _Entry(
                layer + "self_attn.o_proj.weight", (D, N * H), attn + f"attn_vec_einsum{sfx}/w", (i,), _out_heads(N, H)
            ),
            _Entry(layer + "mlp.gate_proj.weight", (M, D), mlp + "gating_einsum", (i, 0), LINEAR),
            _Entry(layer + "mlp.up_proj.weight", (M, D), mlp + "gating_einsum", (i, 1), LINEAR),
            _Entry(layer + "mlp.down_proj.weight", (D, M), mlp + "linear", (i,), LINEAR),
        ]
        for norm, name in (("input_layernorm", "pre_attention_norm"), ("post_attention_layernorm", "pre_ffw_norm")):
            out += _norm_entries(layer + norm, LLM + f"layers/{name}{sfx}/", D, (i,), adarms=adarms)
    return out + _norm_entries(torch_root + "norm", LLM + f"final_norm{sfx}/", D, (), adarms=adarms)


def _norm_entries(key: str, target: str, width: int, index: tuple[int, ...], *, adarms: bool) -> list[_Entry]:
    """A plain RMSNorm scale, or pi0.5's adaptive one: `dense` [3w, w] makes (scale, shift, gate) from the time."""
    if not adarms:
        return [_Entry(key + ".weight", (width,), target + "scale", index, SAME)]
    return [
        _Entry(key + ".dense.weight", (3 * width, width), target + "Dense_0/kernel", index, LINEAR),
        _Entry(key + ".dense.bias", (3 * width,), target + "Dense_0/bias", index, SAME),
    ]


def _siglip_entries(cfg: SiglipConfig) -> list[_Entry]:
    w, m, n, p = cfg.width, cfg.mlp_dim, cfg.num_heads, cfg.patch_size
    h = w // n
    blk, att = IMG + "Transformer/encoderblock/", IMG + "Transformer/encoderblock/MultiHeadDotProductAttention_0/"
    out = [
        _Entry(VT + "embeddings.patch_embedding.weight", (w, 3, p, p), IMG + "embedding/kernel", (), CONV),
        _Entry(VT + "embeddings.patch_embedding.bias", (w,), IMG + "embedding/bias", (), SAME),
        _Entry(VT + "embeddings.position_embedding.weight", (cfg.num_tokens, w), IMG + "pos_embedding", (), POS),
        _Entry(VT + "post_layernorm.weight", (w,), IMG + "Transformer/encoder_norm/scale", (), SAME),
        _Entry(VT + "post_layernorm.bias", (w,), IMG + "Transformer/encoder_norm/bias", (), SAME),
        _Entry(PG + "model.multi_modal_projector.linear.weight", (cfg.out_dim, w), IMG + "head/kernel", (), LINEAR),
        _Entry(PG + "model.multi_modal_projector.linear.bias", (cfg.out_dim,), IMG + "head/bias", (), SAME),
    ]
    for i in range(cfg.depth):
        layer = f"{VT}encoder.layers.{i}."
        for torch_name, jax_name in (("layer_norm1", "LayerNorm_0"), ("layer_norm2", "LayerNorm_1")):
            out.append(_Entry(layer + torch_name + ".weight", (w,), blk + jax_name + "/scale", (i,), SAME))
            out.append(_Entry(layer + torch_name + ".bias", (w,), blk + jax_name + "/bias", (i,), SAME))
        for torch_name, jax_name in (("q_proj", "query"), ("k_proj", "key"), ("v_proj", "value")):
            out.append(
                _Entry(
                    layer + f"self_attn.{torch_name}.weight", (w, w), att + f"{jax_name}/kernel", (i,), _in_heads(n, h)
                )
            )
            out.append(
                _Entry(layer + f"self_attn.{torch_name}.bias", (w,), att + f"{jax_name}/bias", (i,), _bias_heads(n, h))
            )
        out += [
            _Entry(layer + "self_attn.out_proj.weight", (w, w), att + "out/kernel", (i,), _out_heads(n, h)),
            _Entry(layer + "self_attn.out_proj.bias", (w,), att + "out/bias", (i,), SAME),
            _Entry(layer + "mlp.fc1.weight", (m, w), blk + "MlpBlock_0/Dense_0/kernel", (i,), LINEAR),
            _Entry(layer + "mlp.fc1.bias", (m,), blk + "MlpBlock_0/Dense_0/bias", (i,), SAME),
            _Entry(layer + "mlp.fc2.weight", (w, m), blk + "MlpBlock_0/Dense_1/kernel", (i,), LINEAR),
            _Entry(layer + "mlp.fc2.bias", (w,), blk + "MlpBlock_0/Dense_1/bias", (i,), SAME),
        ]
    return out


def _layout(cfg: Pi0Config, embedding_key: str) -> list[_Entry]:
    """Every tensor of the PyTorch checkpoint of `cfg`, in OpenPI's order of leaves; the token embedding is read from
    `embedding_key` (`embed_tokens`, or `lm_head` where a checkpoint stores only that: the same table)."""
    we, a = cfg.expert.width, cfg.action_dim
    linears = {"action_in_proj": (we, a), "action_out_proj": (a, we)}
    if cfg.pi05:
        linears |= {"time_mlp_in": (we, we), "time_mlp_out": (we, we)}
    else:
        linears |= {"state_proj": (we, a), "action_time_mlp_in": (we, 2 * we), "action_time_mlp_out": (we, we)}
    entries = [
        _Entry(embedding_key, (cfg.gemma.vocab_size, cfg.gemma.width), LLM + "embedder/input_embedding", (), SAME),
        *_siglip_entries(cfg.siglip),
        *_gemma_entries(cfg.gemma, LM, "", adarms=False),
        *_gemma_entries(cfg.expert, EX + "model.", "_1", adarms=cfg.pi05),
    ]
    for name, (out_dim, in_dim) in linears.items():
        entries.append(_Entry(f"{name}.weight", (out_dim, in_dim), f"{name}/kernel", (), LINEAR))
        entries.append(_Entry(f"{name}.bias", (out_dim,), f"{name}/bias", (), SAME))
    return entries


# Tensors a checkpoint may hold that the policy never reads: the PaliGemma LM head (the embedding table again) and
# the action expert's LM head (LeRobot keeps it; the expert emits no tokens).
_UNUSED = (PG + "lm_head.weight", EX + "lm_head.weight")


@dataclasses.dataclass(frozen=True)
class TensorInfo:
    shape: tuple[int, ...]
    dtype: str  # safetensors' name: F32, BF16, ...


def read_tensor_infos(path: str | pathlib.Path) -> dict[str, TensorInfo]:
    """Key -> shape and dtype of every tensor, from the file's header (no tensor data is read)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights not found: {path}")
    with reading(path, "safetensors file"), safe_open(str(path), framework="np") as f:
        infos = {}
        for key in f.keys():  # noqa: SIM118  (safe_open is not a mapping)
            piece = f.get_slice(key)
            infos[key] = TensorInfo(tuple(piece.get_shape()), piece.get_dtype())
    return infos


def key_prefix(keys: list[str], where: str) -> str:
    """ "model." when every key has LeRobot's prefix, "" when none has (OpenPI's export); a mix is refused."""
    prefixed = [k.startswith(LEROBOT_PREFIX) for k in keys]
    if all(prefixed):
        return LEROBOT_PREFIX
    if not any(prefixed):
        return ""
    odd = next(k for k, p in zip(keys, prefixed, strict=True) if p != prefixed[0])
    raise ValueError(f"{where}: key {odd!r} breaks the file's key prefix ({LEROBOT_PREFIX!r} on some keys only)")


def torch_family(infos: Mapping[str, TensorInfo], *, where: str = "model.safetensors") -> str:
    """ "pi05" (a time MLP) or "pi0" (a state projection), from the keys alone."""
    prefix = key_prefix(list(infos), where)
    if prefix + "time_mlp_in.weight" in infos:
        return "pi05"
    if prefix + "state_proj.weight" in infos:
        return "pi0"
    raise ValueError(f"{where}: neither {prefix}time_mlp_in.weight (pi0.5) nor {prefix}state_proj.weight (pi0)")


def _layer_count(keys: list[str], root: str) -> int:
    indices = {int(m.group(1)) for k in keys if (m := re.match(re.escape(root) + r"(\d+)\.", k))}
    return max(indices) + 1 if indices else 0


def _divide(total: int, parts: int, what: str) -> int:
    if parts < 1 or total % parts:
        raise ValueError(f"{what}: {total} does not split into {parts} heads")
    return total // parts


def _embedding_key(keys: set[str]) -> str:
    return LM + "embed_tokens.weight" if LM + "embed_tokens.weight" in keys else PG + "lm_head.weight"


def pi0_config_from_tensors(
    infos: Mapping[str, TensorInfo], heads: HeadCounts = LEROBOT_HEADS, *, where: str = "model.safetensors"
) -> tuple[Pi0Config, str]:
    """(the architecture the tensors describe, the file's key prefix). Sizes come from anchor tensors; that every
    other tensor fits them is `check_tensors`' job."""
    keys = list(infos)
    prefix = key_prefix(keys, where)

    def shape(key: str) -> tuple[int, ...]:
        if prefix + key not in infos:
            raise ValueError(f"{where}: missing tensor {prefix + key!r}")
        return infos[prefix + key].shape

    stripped = [k[len(prefix) :] for k in keys]
    pi05 = torch_family(infos, where=where) == "pi05"
    vocab, width = shape(_embedding_key(set(stripped)))

    def gemma(root: str, vocab_size: int) -> GemmaConfig:
        depth = _layer_count(stripped, root + "layers.")
        q_out, w = shape(root + "layers.0.self_attn.q_proj.weight")
        head_dim = _divide(q_out, heads.gemma, f"{where}: {prefix}{root}layers.0.self_attn.q_proj.weight rows")
        k_out = shape(root + "layers.0.self_attn.k_proj.weight")[0]
        if k_out % head_dim:
            raise ValueError(
                f"{where}: {prefix}{root}layers.0.self_attn.k_proj.weight rows {k_out} are not whole heads"
            )
        mlp = shape(root + "layers.0.mlp.gate_proj.weight")[0]
        return GemmaConfig(
            w, depth, mlp, heads.gemma, k_out // head_dim, head_dim, vocab_size,
            scan=scan_by_default(depth), remat=remat_by_default(w),
        )  # fmt: skip

    llm = gemma(LM, vocab)
    if llm.width != width:
        raise ValueError(f"{where}: the embedding is {width} wide, the language model {llm.width}")
    expert = gemma(EX + "model.", 0)
    siglip_width, _, patch, _ = shape(VT + "embeddings.patch_embedding.weight")
    tokens = shape(VT + "embeddings.position_embedding.weight")[0]
    side = math.isqrt(tokens)
    if side * side != tokens:
        raise ValueError(f"{where}: SigLIP position embedding has {tokens} rows, not a square patch grid")
    n_siglip = heads.siglip
    if n_siglip is None:
        if siglip_width != SO400M_WIDTH:
            raise ValueError(
                f"{where}: SigLIP width {siglip_width} is not PaliGemma's ({SO400M_WIDTH}) and its head count is not "
                "in the weights; give it (a record of the folder's sizes)"
            )
        n_siglip = SO400M_HEADS
    _divide(siglip_width, n_siglip, f"{where}: SigLIP width")
    siglip_depth = _layer_count(stripped, VT + "encoder.layers.")
    siglip = SiglipConfig(
        siglip_width,
        siglip_depth,
        shape(VT + "encoder.layers.0.mlp.fc1.weight")[0],
        n_siglip,
        patch,
        side * patch,
        shape(PG + "model.multi_modal_projector.linear.weight")[0],
        scan_by_default(siglip_depth),
    )
    action_dim = shape("action_in_proj.weight")[1]
    return Pi0Config(llm, expert, siglip, pi05, action_dim), prefix


def check_tensors(infos: Mapping[str, TensorInfo], cfg: Pi0Config, prefix: str, *, where: str) -> list[_Entry]:
    """The layout of `cfg`, after checking the file holds exactly its tensors (plus the unused ones LeRobot keeps),
    each float and of its shape; the first problem is raised in one line naming the key."""
    stripped = {k[len(prefix) :]: info for k, info in infos.items()}
    entries = _layout(cfg, _embedding_key(set(stripped)))
    expected = {e.key: e.shape for e in entries}
    for key in expected:
        if key not in stripped:
            raise ValueError(f"{where}: missing tensor {prefix + key!r} (expected shape {list(expected[key])})")
    for key, info in stripped.items():
        if key not in expected and key not in _UNUSED:
            raise ValueError(f"{where}: unexpected tensor {prefix + key!r} (shape {list(info.shape)})")
        if info.dtype not in _FLOAT_DTYPES:
            raise ValueError(f"{where}: tensor {prefix + key!r} has dtype {info.dtype}, expected a float type")
    unused_widths = {PG + "lm_head.weight": cfg.gemma.width, EX + "lm_head.weight": cfg.expert.width}
    for key, info in stripped.items():
        want = expected.get(key)
        if want is None:  # an unused LM head: [any vocabulary, its stack's width]
            ok = len(info.shape) == 2 and info.shape[1] == unused_widths[key]
            want = ("V", unused_widths[key])
        else:
            ok = info.shape == want
        if not ok:
            raise ValueError(f"{where}: tensor {prefix + key!r} has shape {list(info.shape)}, expected {list(want)}")
    return entries


def _read_tensor(path: pathlib.Path, key: str) -> np.ndarray:
    # Opened per tensor: closing unmaps the file, so its pages leave the process's resident set at once.
    with reading(path, "safetensors file"), safe_open(str(path), framework="np") as f:
        return f.get_tensor(key)


def _aligned_empty(shape: tuple[int, ...], dtype: np.dtype, alignment: int = 64) -> np.ndarray:
    """An uninitialised array whose data starts on an `alignment`-byte boundary: XLA's CPU client adopts such a host
    buffer as the device array instead of copying it (NumPy only aligns to 16 bytes)."""
    size = math.prod(shape) * dtype.itemsize
    raw = np.empty(size + alignment, np.uint8)
    start = -raw.ctypes.data % alignment
    return raw[start : start + size].view(dtype).reshape(shape)


def _by_target(entries: list[_Entry]) -> Iterator[tuple[str, list[_Entry]]]:
    groups: dict[str, list[_Entry]] = {}
    for e in entries:
        groups.setdefault(e.target, []).append(e)
    yield from groups.items()


def load_safetensors_params(
    path: str | pathlib.Path, *, dtype: str | None = None, heads: HeadCounts = LEROBOT_HEADS
) -> tuple[dict[str, Any], Pi0Config]:
    """(params in OpenPI's tree on the default device, the architecture) from a PyTorch pi0 / pi0.5 checkpoint.

    `dtype` casts every weight (None keeps the file's). A key missing, unexpected or misshapen is refused in one
    line naming it, before any tensor is read."""
    path = pathlib.Path(path)
    where = str(path)
    infos = read_tensor_infos(path)
    cfg, prefix = pi0_config_from_tensors(infos, heads, where=where)
    entries = check_tensors(infos, cfg, prefix, where=where)
    shapes = pi0_param_shapes(cfg)
    flat: dict[str, Any] = {}
    for target, group in _by_target(entries):
        stored = [jnp.dtype(_FLOAT_DTYPES[infos[prefix + e.key].dtype]) for e in group]
        leaf = _aligned_empty(shapes[target], jnp.dtype(dtype) if dtype is not None else np.result_type(*stored))
        for e in group:
            leaf[e.index] = e.conv.load(_read_tensor(path, prefix + e.key))
        flat[target] = jax.device_put(leaf, may_alias=True)
        del leaf
    return unflatten_dict(flat), cfg


def torch_shapes(cfg: Pi0Config, *, prefix: str = LEROBOT_PREFIX) -> dict[str, tuple[int, ...]]:
    """Key -> shape of every tensor the PyTorch checkpoint of `cfg` holds (the embedding as `embed_tokens`)."""
    return {prefix + e.key: e.shape for e in _layout(cfg, LM + "embed_tokens.weight")}


def write_safetensors(
    path: str | pathlib.Path,
    shapes: Mapping[str, tuple[int, ...]],
    dtype: str,
    tensor: Callable[[str], np.ndarray],
    *,
    metadata: Mapping[str, str] | None = None,
) -> pathlib.Path:
    """Writes a safetensors file of `shapes` in `dtype`, asking `tensor(key)` for one tensor at a time, so that
    writing holds one tensor (not the whole state dict) in memory. `metadata` defaults to torch's {"format": "pt"}."""
    path = pathlib.Path(path)
    np_dtype = jnp.dtype(dtype)
    header: dict[str, Any] = {"__metadata__": dict(metadata or {"format": "pt"})}
    offset = 0
    for key, shape in shapes.items():
        size = math.prod(shape) * np_dtype.itemsize
        header[key] = {"dtype": _DTYPE_NAMES[dtype], "shape": list(shape), "data_offsets": [offset, offset + size]}
        offset += size
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned, as safetensors' own writer pads it
    with path.open("wb") as f:
        f.write(len(text).to_bytes(8, "little") + text)
        for key, shape in shapes.items():
            array = np.ascontiguousarray(tensor(key), np_dtype)
            if array.shape != tuple(shape):
                raise ValueError(f"tensor {key!r} has shape {list(array.shape)}, the header says {list(shape)}")
            f.write(array.view(np.uint8).data)
    return path


def save_safetensors_params(
    path: str | pathlib.Path,
    params: Mapping[str, Any],
    cfg: Pi0Config,
    *,
    prefix: str = LEROBOT_PREFIX,
    dtype: str = "float32",
    lm_heads: bool = False,
    metadata: Mapping[str, str] | None = None,
) -> pathlib.Path:
    """Writes an OpenPI pi0 / pi0.5 tree as the PyTorch checkpoint `load_safetensors_params` reads back (keys under
    `prefix`: LeRobot's `model.`, or "" for OpenPI's export; the embedding as `embed_tokens`). `lm_heads` adds the
    two LM heads LeRobot's module holds and its strict loader requires: PaliGemma's (the embedding table again) and
    the expert's (unused by the policy: zeros)."""
    flat = {k: np.asarray(v) for k, v in flatten_dict(dict(params)).items()}
    entries = {prefix + e.key: e for e in _layout(cfg, LM + "embed_tokens.weight")}
    shapes = {k: e.shape for k, e in entries.items()}
    vocab = cfg.gemma.vocab_size
    heads = {
        prefix + PG + "lm_head.weight": (vocab, cfg.gemma.width),
        prefix + EX + "lm_head.weight": (vocab, cfg.expert.width),
    }
    if lm_heads:
        shapes |= heads

    def tensor(key: str) -> np.ndarray:
        if key == prefix + EX + "lm_head.weight":
            return np.zeros(heads[key], np.float32)
        entry = entries[key if key not in heads else prefix + LM + "embed_tokens.weight"]
        return entry.conv.save(flat[entry.target][entry.index])

    return write_safetensors(path, shapes, dtype, tensor, metadata=metadata)
