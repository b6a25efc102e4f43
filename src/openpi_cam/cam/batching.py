"""Explaining inferences in batches: one explainer call for many traces, sharded over the local devices.

The live side channel explains one trace at a time (a batch of one); replays and datasets stack `batch_size` traces.
All three go through `explain_batch` (the maps, then each row's spot check), so there is one code path. Data
parallelism is plain SPMD: the stacked batch is padded to a multiple of the device count, every batched leaf is placed
with `NamedSharding(mesh, P("batch"))`, the explainer's params are replicated once (`Explainer.on_mesh`), and the
jitted map functions partition themselves (rows never interact).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from openpi_cam.cam.reliance import Resampler, reliance
from openpi_cam.cam.run_format import Reliance, SpotCheck
from openpi_cam.cam.spot_check import check_trace
from openpi_cam.model.observation import Observation, pad_rows, stack_observations
from openpi_cam.model.sharding import BATCH_AXIS
from openpi_cam.policies.family import Explainer, ExplainSkipped, Explanation
from openpi_cam.policies.policy import InferenceTrace
from openpi_cam.vocabulary import ExplainOptions


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
    request: ExplainOptions,
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
    request: ExplainOptions,
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


@dataclasses.dataclass(frozen=True)
class Explained:
    """One trace's explanation (or why it was skipped), its spot check (None: skipped, or no check asked), its
    reliance (None: skipped, or not asked) and the row's share of the wall time the batch's maps, checks and
    reliance took."""

    result: Explanation | ExplainSkipped
    check: SpotCheck | None
    explain_ms: float
    reliance: Reliance | None = None


def explain_batch(
    explainer: Explainer,
    traces: Sequence[InferenceTrace],
    options: ExplainOptions,
    seeds: Sequence[int],
    *,
    mesh: Mesh | None = None,
    pad_to: int = 0,
    before_check: Callable[[], object] | None = None,
    policy: Resampler | None = None,
) -> list[Explained]:
    """The maps of every trace (`explain_traces`), then each explained row's spot check (`cam.spot_check`, seeded by
    `seeds[i]`) when `options.check_patches` asks for one and its reliance (`cam.reliance`, re-run by `policy`)
    when `options.reliance` does. `before_check` runs between the maps and the re-runs (the side channel waits there
    for inference to pause). An exception of the explainer propagates; a failed check or reliance is recorded in
    it."""
    if options.reliance and policy is None:
        raise ValueError("reliance re-runs the policy: pass the policy that served the traces")
    start = time.perf_counter()
    results = explain_traces(explainer, traces, options.explanation, mesh=mesh, pad_to=pad_to)
    checks: list[SpotCheck | None] = [None] * len(results)
    relied: list[Reliance | None] = [None] * len(results)
    rerun = options.check_patches or options.reliance
    if rerun and before_check is not None and any(not isinstance(r, ExplainSkipped) for r in results):
        before_check()
    for i, (trace, result) in enumerate(zip(traces, results, strict=True)):
        if isinstance(result, ExplainSkipped):
            continue
        if options.check_patches:
            checks[i] = check_trace(
                explainer, trace, result, options.map_options, patches=options.check_patches, seed=seeds[i], mesh=mesh
            )
        if policy is not None and options.reliance:
            relied[i] = reliance(policy, explainer, trace, result, options.map_options, mesh=mesh)
    per_row_ms = (time.perf_counter() - start) * 1000.0 / max(1, len(results))
    return [Explained(r, c, per_row_ms, d) for r, c, d in zip(results, checks, relied, strict=True)]
