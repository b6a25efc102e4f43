"""Copies of a safetensors file with tensors dropped, added, reshaped or recast (the bad-checkpoint tests), written
through the package's streaming writer, and single tensors read back through safetensors' NumPy API."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from safetensors import safe_open

from openpi_cam.model.safetensors_weights import read_tensor_infos, write_safetensors


def read_tensor(path: Path, key: str) -> np.ndarray:
    """One tensor of a safetensors file, as stored."""
    with safe_open(str(path), framework="np") as f:
        return f.get_tensor(key)


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
        return arrays[key] if key in arrays else read_tensor(src, originals[key])

    return write_safetensors(dst, shapes, dtype, tensor)
