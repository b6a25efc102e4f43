"""OpenPI params checkpoints: orbax PyTree directories holding `{"params": <pure dict>}`.

Both layouts upstream restores are read: released checkpoints (leaf paths end at the parameter name) and
training checkpoints written through `nnx.State` (every leaf path ends in an extra `value` key).
"""

from __future__ import annotations

import pathlib
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from openpi_cam.model.config import check_param_tree, expected_param_shapes
from openpi_cam.nested import flatten_dict, unflatten_dict


def _strip_value_suffix(flat: dict[str, Any]) -> dict[str, Any]:
    if flat and all(path.endswith("/value") for path in flat):
        return {path[: -len("/value")]: v for path, v in flat.items()}
    return flat


def _checkpointer() -> ocp.PyTreeCheckpointer:
    return ocp.PyTreeCheckpointer()


def read_param_shapes(params_dir: str | pathlib.Path) -> dict[str, tuple[int, ...]]:
    """Paths and shapes from the checkpoint's metadata, without reading any array data."""
    params_dir = _resolve(params_dir)
    meta = _checkpointer().metadata(params_dir)
    tree = getattr(meta, "item_metadata", meta)
    tree = getattr(tree, "tree", tree)
    if "params" not in tree:
        raise ValueError(f"{params_dir} is not an OpenPI params checkpoint: no top-level 'params' item")
    return _strip_value_suffix({p: tuple(m.shape) for p, m in flatten_dict(tree["params"]).items()})


def _resolve(params_dir: str | pathlib.Path) -> pathlib.Path:
    path = pathlib.Path(params_dir).expanduser().resolve()
    if not path.is_dir():
        raise FileNotFoundError(f"params checkpoint directory not found: {path} (expected <checkpoint>/params)")
    if not (path / "_METADATA").exists() and (path / "params" / "_METADATA").exists():
        path = path / "params"  # the user named the checkpoint root rather than its params/ item
    if not (path / "_METADATA").exists():
        raise FileNotFoundError(f"{path} is not an orbax params checkpoint: {path / '_METADATA'} is missing")
    return path


def load_params(params_dir: str | pathlib.Path, *, dtype: str | None = None, check: bool = True) -> dict[str, Any]:
    """Restores the params pytree (upstream names) onto the default device.

    Arrays are restored straight into host numpy buffers (cast to `dtype` by orbax while reading, if given) and moved
    to the device one leaf at a time, so host memory holds one copy of the params plus orbax's transient read
    buffers. With `check`, the tree must be exactly the tree upstream builds for the family and architecture its shapes
    describe (pi0-FAST, pi0 or pi0.5).
    """
    params_dir = _resolve(params_dir)
    shapes = read_param_shapes(params_dir)
    if check:
        check_param_tree(shapes, expected_param_shapes(shapes))
    ckptr = _checkpointer()
    meta = ckptr.metadata(params_dir)
    tree = getattr(meta, "item_metadata", meta)
    tree = getattr(tree, "tree", tree)
    item = {"params": tree["params"]}
    np_dtype = None if dtype is None else jnp.dtype(dtype)
    restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray, dtype=np_dtype), item)
    restored = ckptr.restore(params_dir, args=ocp.args.PyTreeRestore(item=item, restore_args=restore_args))["params"]
    flat = _strip_value_suffix(flatten_dict(restored))
    del restored  # `flat` now holds the only references to the host buffers
    device_flat = {}
    for path in list(flat):
        # On a CPU backend the device array may alias the host buffer instead of copying it; on an accelerator the
        # host copy is dropped as soon as it is on the device.
        device_flat[path] = jax.device_put(flat.pop(path), may_alias=True)
    return unflatten_dict(device_flat)


def save_params(params_dir: str | pathlib.Path, params: Mapping[str, Any]) -> pathlib.Path:
    """Writes `{"params": params}` in the orbax layout of OpenPI's released `<checkpoint>/params`."""
    params_dir = pathlib.Path(params_dir).expanduser().resolve()
    tree = jax.tree.map(jnp.asarray, dict(params))
    _checkpointer().save(params_dir, {"params": tree})
    return params_dir
