"""Copies of a safetensors file with tensors dropped, added, reshaped or recast (the bad-checkpoint tests), written
through the package's streaming writer and read back through safetensors' NumPy API."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from safetensors import safe_open

from openpi_cam.model.safetensors_weights import read_tensor_infos, write_safetensors


def edit_safetensors(
    src: Path,
    dst: Path,
    *,
    drop: tuple[str, ...] = (),
    add: Mapping[str, np.ndarray] | None = None,
    replace: Mapping[str, np.ndarray] | None = None,
    dtype: str = "float32",
    rename: Callable[[str], str] = lambda key: key,
) -> Path:
    """`src` without `drop`, with `add` and `replace` (key -> array), every key renamed by `rename`, in `dtype`."""
    infos = read_tensor_infos(src)
    originals = {rename(k): k for k in infos if k not in drop}
    arrays = {rename(k): v for k, v in {**(add or {}), **(replace or {})}.items()}
    shapes = {k: np.shape(arrays[k]) if k in arrays else infos[originals[k]].shape for k in {**originals, **arrays}}

    def tensor(key: str) -> np.ndarray:
        if key in arrays:
            return arrays[key]
        with safe_open(str(src), framework="np") as f:
            return f.get_tensor(originals[key])

    return write_safetensors(dst, shapes, dtype, tensor)
