"""Batched Grad-CAM for offline explanation: many inferences explained in one model call, sharded over devices.

`explain_batch` is the many-row counterpart of `engine.explain`: each row keeps its own action-token steps, and the
per-row results are the `Explanation`s the single-row path would give (tested against it). Rows whose generation
cannot be explained are answered with the same `CamSkipped` the side channel counts; they still ride through the
model call with a harmless step so that every batch of one size shares one compilation.

Data parallelism is plain SPMD: the stacked batch is padded to a multiple of the device count, every batched leaf is
placed with `NamedSharding(mesh, P("batch"))` and the params are replicated once; the jitted Grad-CAM functions then
partition themselves (rows never interact, so no cross-device traffic beyond gathering the results).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from openpi_cam.cam.engine import TARGETS, CamSkipped, Explanation
from openpi_cam.model import pi0_fast_maps
from openpi_cam.model.observation import Observation

BATCH_AXIS = "batch"


def data_mesh(devices: Sequence[Any] | None = None) -> Mesh | None:
    """A 1-D mesh over the local devices, or None when there is only one (nothing to shard)."""
    devices = list(jax.local_devices() if devices is None else devices)
    return Mesh(np.array(devices), (BATCH_AXIS,)) if len(devices) > 1 else None


def replicate_model(model: Any, mesh: Mesh | None) -> Any:
    """A shallow copy of `model` whose params live on every mesh device, placed once instead of on every call."""
    if mesh is None:
        return model
    replicated = copy.copy(model)
    replicated.params = jax.device_put(model.params, NamedSharding(mesh, PartitionSpec()))
    return replicated


def stack_observations(observations: Sequence[Observation]) -> Observation:
    """B=1 observations of one config -> one [B, ...] observation (same cameras and shapes in every row)."""
    return jax.tree.map(lambda *x: np.concatenate([np.asarray(a) for a in x]), *observations)


def pad_rows(x: np.ndarray, rows: int) -> np.ndarray:
    """Repeats the last row until `x` has `rows` rows (padding rows are computed and then dropped)."""
    x = np.asarray(x)
    return x if x.shape[0] == rows else np.concatenate([x, np.repeat(x[-1:], rows - x.shape[0], axis=0)])


def shard_batch(observation: Observation, mesh: Mesh | None, pad_to: int = 0) -> tuple[Observation, int]:
    """Pads the batch to at least `pad_to` rows and to a multiple of the mesh size, and shards every leaf over its
    rows; returns it and the padded row count."""
    rows = int(np.shape(observation.state)[0])
    n = 1 if mesh is None else mesh.devices.size
    padded = -(-max(rows, pad_to) // n) * n
    if mesh is None:
        return (observation if padded == rows else jax.tree.map(lambda x: pad_rows(x, padded), observation)), padded
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
    return jax.tree.map(lambda x: jax.device_put(pad_rows(x, padded), sharding), observation), padded


def _row_steps(tokenizer: Any, generated: np.ndarray, target: str, action_index: int) -> list[np.ndarray | CamSkipped]:
    """Decode steps each row's target explains, or why the row cannot be explained (engine.explain's rules)."""
    out: list[np.ndarray | CamSkipped] = []
    for row in generated:
        steps = np.asarray(tokenizer.action_token_steps(row), np.int32)
        if steps.size == 0:
            out.append(CamSkipped("no_action_tokens", "the generation holds no FAST action tokens to explain"))
        elif target == "action-token" and not 0 <= action_index < steps.size:
            out.append(
                CamSkipped(
                    "action_index_out_of_range", f"action token {action_index} requested, generation has {steps.size}"
                )
            )
        else:
            out.append(steps[[action_index]] if target == "action-token" else steps)
    return out


def explain_batch(
    model: Any,
    tokenizer: Any,
    observation: Observation,
    generated: np.ndarray,
    *,
    target: str,
    action_index: int = 0,
    mesh: Mesh | None = None,
    pad_to: int = 0,
) -> list[Explanation | CamSkipped]:
    """Grad-CAM of B inferences in one model call: `observation` [B, ...] and `generated` int32 [B, S] are the exact
    inputs and tokens of each inference. Returns one `Explanation` (or `CamSkipped`) per row, in row order.

    With a `mesh`, the model's params must already be on every mesh device (`replicate_model`). `pad_to`: pad the
    batch to this many rows (e.g. the batch size, so that a short last batch reuses the compiled program)."""
    if target not in TARGETS:
        raise ValueError(f"unknown Grad-CAM target {target!r}; expected one of {TARGETS}")
    generated = np.asarray(generated, np.int32)
    if generated.ndim != 2 or generated.shape[0] != np.shape(observation.state)[0]:
        raise ValueError(f"generated must be [B, S] with B = {np.shape(observation.state)[0]}, got {generated.shape}")
    rows = generated.shape[0]
    per_row = _row_steps(tokenizer, generated, target, action_index)
    counts = [0 if isinstance(s, CamSkipped) else s.size for s in per_row]
    if not any(counts):
        return list(per_row)  # type: ignore[arg-type]

    obs, padded = shard_batch(observation, mesh, pad_to)
    fed = pad_rows(generated, padded)
    if target == "chunk":
        # Ragged lists are native to the chunk target; skipped and padding rows explain step 0 and are dropped.
        lists = [s if isinstance(s, np.ndarray) else np.zeros(1, np.int32) for s in per_row]
        result = pi0_fast_maps.gradcam_for_chunk(model, obs, fed, lists + [lists[-1]] * (padded - rows))
    else:
        # One [B, T] step matrix: rows with fewer action tokens repeat their first step (the model already pads T to
        # a power of two the same way), so one forward pass and one compilation serve the whole batch.
        width = max(counts)
        steps = np.zeros((padded, width), np.int32)
        for b in range(padded):
            own = per_row[min(b, rows - 1)]
            if isinstance(own, np.ndarray):
                steps[b] = np.concatenate([own, np.repeat(own[:1], width - own.size)])
        result = pi0_fast_maps.gradcam_for_steps(model, obs, fed, steps)

    grid = list(model.config.siglip.grid)
    token_ids, positions, score = (np.asarray(a) for a in (result.token_ids, result.positions, result.score))
    out: list[Explanation | CamSkipped] = []
    for b, own in enumerate(per_row):
        if isinstance(own, CamSkipped):
            out.append(own)
            continue
        t = own.size
        if target == "chunk":
            index: Any = b
            row_score: float | list[float] = float(score[b])
        elif target == "action-token":
            index = (b, 0)
            row_score = float(score[b, 0])
        else:
            index = (b, slice(0, t))
            row_score = [float(s) for s in score[b, :t]]
        out.append(
            Explanation(
                target=target,
                maps={c: np.asarray(m[index], np.float32) for c, m in result.maps.items()},
                gradnorm_maps={c: np.asarray(m[index], np.float32) for c, m in result.gradnorm_maps.items()},
                token_ids=[int(x) for x in token_ids[b, :t]],
                decode_steps=[int(s) for s in own],
                positions=[int(p) for p in positions[b, :t]],
                action_indices=[action_index] if target == "action-token" else list(range(t)),
                score=row_score,
                cameras={
                    c: {"valid": bool(result.valid[c][b]), "grid": grid, "span": list(result.spans[c])}
                    for c in result.cameras
                },
            )
        )
    return out
