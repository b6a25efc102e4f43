"""Fresh parameters for a parameter tree given by its shapes (training the demo models from scratch)."""

from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp

from openpi_cam.nested import unflatten_dict


def _fan_in(path: str, shape: tuple[int, ...]) -> int:
    if path.endswith("embedding/kernel"):  # [p, p, 3, width]
        return shape[0] * shape[1] * shape[2]
    if path.endswith("Attention_0/out/kernel"):  # [depth, heads, head_dim, width]
        return shape[-3] * shape[-2]
    if path.endswith(("query/kernel", "key/kernel", "value/kernel")):  # [depth, width, heads, head_dim]
        return shape[1]
    return shape[-2]  # every other weight maps its second-to-last axis to its last


def init_from_shapes(shapes: Mapping[str, tuple[int, ...]], rng: jax.Array) -> dict:
    """Weights LeCun-normal; biases and LoRA `b` factors zero; LayerNorm scales one; RMSNorm scales zero (they act as
    1 + scale); embeddings N(0, 1/width); adaRMS modulations (`.../Dense_0` of a norm) zero, as upstream initialises
    them, so pi0.5's expert norms start as plain norms with closed gates."""
    leaves = {}
    for (path, shape), key in zip(shapes.items(), jax.random.split(rng, len(shapes)), strict=True):
        name = path.rsplit("/", 1)[-1]
        adarms = "_norm" in path and "/Dense_0/" in path
        if name == "bias" or name.endswith("lora_b") or adarms or (name == "scale" and "/llm/" in path):
            leaves[path] = jnp.zeros(shape, jnp.float32)
        elif name == "scale":
            leaves[path] = jnp.ones(shape, jnp.float32)
        elif name in ("input_embedding", "pos_embedding"):
            leaves[path] = jax.random.normal(key, shape) * shape[-1] ** -0.5
        else:
            leaves[path] = jax.random.normal(key, shape) * _fan_in(path, shape) ** -0.5
    return unflatten_dict(leaves)


def randomized(params: dict, scope: str, rng: jax.Array) -> dict:
    """`params` with the weights in `scope` replaced by Gaussian noise of each tensor's own mean and standard
    deviation: "llm" the language model (and pi0's action expert, which lives in the same transformer) only, SigLIP
    and the projections kept; "all" every weight. Each leaf keeps its dtype. For the model randomisation test of
    attribution maps (Adebayo et al. 2018). Matching each tensor's moments rather than re-running the training
    initialisation keeps every path open: pi0.5's adaRMS gates start at zero, which would cut the action expert off
    from the images and make every map constant."""
    if scope not in ("llm", "all"):
        raise ValueError(f"randomisation scope must be 'llm' or 'all', got {scope!r}")
    target = params if scope == "all" else params["PaliGemma"]["llm"]
    leaves, treedef = jax.tree.flatten(target)
    fresh = []
    for leaf, key in zip(leaves, jax.random.split(rng, len(leaves)), strict=True):
        x = jnp.asarray(leaf, jnp.float32)
        noise = jax.random.normal(key, x.shape) * jnp.std(x) + jnp.mean(x)
        fresh.append(noise.astype(leaf.dtype))
    fresh_tree = jax.tree.unflatten(treedef, fresh)
    if scope == "all":
        return fresh_tree
    return {**params, "PaliGemma": {**params["PaliGemma"], "llm": fresh_tree}}
