"""Explaining inferences in batches: one explainer call for many traces, sharded over the local devices.

The live side channel explains one trace at a time (a batch of one); offline explanation stacks `batch_size` traces.
Both go through `explain_traces`, so there is one code path. Data parallelism is plain SPMD: the stacked batch is
padded to a multiple of the device count, every batched leaf is placed with `NamedSharding(mesh, P("batch"))`, the
explainer's params are replicated once (`Explainer.on_mesh`), and the jitted map functions partition themselves
(rows never interact).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from openpi_cam.model.observation import Observation, pad_rows, stack_observations
from openpi_cam.model.sharding import BATCH_AXIS
from openpi_cam.policies.family import Explainer, ExplainRequest, ExplainSkipped, Explanation
from openpi_cam.policies.policy import InferenceTrace


def data_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh | None:
    """A 1-D mesh over the local devices, or None when there is only one (nothing to shard)."""
    devices = list(jax.local_devices() if devices is None else devices)
    return Mesh(np.array(devices), (BATCH_AXIS,)) if len(devices) > 1 else None


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


def explain_traces(
    explainer: Explainer,
    traces: Sequence[InferenceTrace],
    request: ExplainRequest,
    *,
    mesh: Mesh | None = None,
    pad_to: int = 0,
) -> list[Explanation | ExplainSkipped]:
    """One result per trace, in order, from the exact model inputs and outputs of each traced call.

    With a `mesh`, `explainer` must already be placed on it (`explainer.on_mesh(mesh)`). `pad_to`: pad the batch to
    this many rows (e.g. the batch size, so that a short last batch reuses the compiled program)."""
    rows = [(t.observation, np.asarray(t.output), t.sample_inputs) for t in traces]
    return explain_rows(explainer, rows, request, mesh=mesh, pad_to=pad_to)


def explain_rows(
    explainer: Explainer,
    rows: Sequence[tuple[Observation, np.ndarray, Mapping[str, np.ndarray]]],
    request: ExplainRequest,
    *,
    mesh: Mesh | None = None,
    pad_to: int = 0,
) -> list[Explanation | ExplainSkipped]:
    """`explain_traces` for rows given as (observation [B = 1], raw output without its batch axis, sampler inputs
    without it), e.g. rebuilt from logged steps."""
    if not rows:
        return []
    observation, padded = shard_batch(stack_observations([obs for obs, _, _ in rows]), mesh, pad_to)
    outputs = pad_rows(np.stack([np.asarray(out) for _, out, _ in rows]), padded)
    drawn = {k: pad_rows(np.stack([np.asarray(r[2][k]) for r in rows]), padded) for k in rows[0][2]}
    return explainer.explain(observation, outputs, request, drawn)[: len(rows)]
