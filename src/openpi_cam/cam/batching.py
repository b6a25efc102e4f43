"""Explaining inferences in batches: one explainer call for many traces, sharded over the local devices.

The live side channel explains one trace at a time (a batch of one); offline explanation stacks `batch_size` traces.
Both go through `explain_traces`, so there is one code path. Data parallelism is plain SPMD: the stacked batch is
padded to a multiple of the device count, every batched leaf is placed with `NamedSharding(mesh, P("batch"))`, the
explainer's params are replicated once (`Explainer.on_mesh`), and the jitted map functions partition themselves
(rows never interact).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from openpi_cam.model.observation import Observation
from openpi_cam.policies.family import Explainer, ExplainRequest, ExplainSkipped, Explanation
from openpi_cam.policies.policy import InferenceTrace

BATCH_AXIS = "batch"


def data_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh | None:
    """A 1-D mesh over the local devices, or None when there is only one (nothing to shard)."""
    devices = list(jax.local_devices() if devices is None else devices)
    return Mesh(np.array(devices), (BATCH_AXIS,)) if len(devices) > 1 else None


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
    if not traces:
        return []
    observation, padded = shard_batch(stack_observations([t.observation for t in traces]), mesh, pad_to)
    outputs = pad_rows(np.stack([np.asarray(t.output) for t in traces]), padded)
    drawn = {k: pad_rows(np.stack([t.sample_inputs[k] for t in traces]), padded) for k in traces[0].sample_inputs}
    return explainer.explain(observation, outputs, request, drawn)[: len(traces)]
