"""Whether an explanation's backward pass can keep its layer activations on the device it runs on.

Full-size layer stacks recompute each layer in the backward pass (`GemmaConfig.remat`), because without it a
full-size explanation's temporaries exceed a CPU host's memory. A GPU with room to spare runs the same explanation
faster without remat, at a higher device peak (docs/DESIGN_NOTES.md). So the choice is made per compiled program, by
XLA's own memory analysis of the remat-free program against the device's free memory; a backend that reports no
device memory (the CPU) keeps the configured layout. The analysis compiles the very program that then runs (JAX
caches it), so a program that fits costs no extra compilation.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any, TypeVar

import jax
import numpy as np

from openpi_cam.model.config import GemmaConfig

logger = logging.getLogger(__name__)

# Share of the device's free memory that one explanation program's temporaries may take: the rest stays for
# inference, which shares the device, and for other programs.
HEADROOM = 0.5

C = TypeVar("C")

_fits: dict[Any, bool] = {}  # program signature -> whether its remat-free version fits


def without_remat(cfg: C) -> C:
    """`cfg` with every layer stack's remat off (its `GemmaConfig` fields: pi0-FAST's `gemma`, pi0's `expert` too)."""
    changes = {
        f.name: dataclasses.replace(v, remat=False)
        for f in dataclasses.fields(cfg)  # type: ignore[arg-type]
        if isinstance(v := getattr(cfg, f.name), GemmaConfig) and v.remat
    }
    return dataclasses.replace(cfg, **changes) if changes else cfg  # type: ignore[type-var]


def free_device_bytes(params: Any) -> int | None:
    """Free memory of the device holding `params` (its limit less what is in use), None where the backend does not
    report device memory (the CPU: host memory, which XLA's analysis of a CPU program does not bound well)."""
    leaf = jax.tree.leaves(params)[0]
    stats = next(iter(leaf.devices())).memory_stats() if isinstance(leaf, jax.Array) else None
    if not stats or "bytes_limit" not in stats:
        return None
    return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))


def fits_without_remat(program: Any, lean_cfg: Any, args: tuple, static: dict[str, Any]) -> bool:
    """Whether `program(*args, cfg=lean_cfg, **static)` (a `jax.jit` function) needs at most HEADROOM of the free
    memory of the device holding args[0] (the params) for its temporaries; decided once per program signature."""
    free = free_device_bytes(args[0])
    if free is None:
        return False
    leaves, tree = jax.tree.flatten(args)
    shapes = tuple((np.shape(x), str(getattr(x, "dtype", type(x)))) for x in leaves)
    key = (program, lean_cfg, tree, shapes, *static.items())
    if key not in _fits:
        analysis = program.lower(*args, cfg=lean_cfg, **static).compile().memory_analysis()
        need = getattr(analysis, "temp_size_in_bytes", None)
        _fits[key] = need is not None and need <= HEADROOM * free
        logger.info(
            "explanation program %s without remat: %s of temporaries, %.2f GB free on the device: %s",
            getattr(program, "__name__", program),
            "unknown" if need is None else f"{need / 1e9:.2f} GB",
            free / 1e9,
            "remat off" if _fits[key] else "remat kept",
        )
    return _fits[key]


def backward_layout(
    program: Any, cfg: C, args: tuple, static: dict[str, Any], layout: Callable[[C], C] = lambda c: c
) -> C:
    """The config `program` differentiates with: `layout(cfg)` (the family's own layout rule, e.g. pi0-FAST's unrolled
    one-token stack) with every stack's remat off where that program fits its device (`fits_without_remat`), else
    `layout(cfg)` as configured."""
    configured, lean = layout(cfg), layout(without_remat(cfg))
    return lean if lean != configured and fits_without_remat(program, lean, args, static) else configured
