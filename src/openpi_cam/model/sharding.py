"""Data parallelism inside the model's programs: the one mesh axis batched work is spread over.

Callers that shard (offline explanation, the faithfulness report) build a 1-D mesh named `BATCH_AXIS` over the local
devices; a program traced under that mesh (`jax.set_mesh`) may spread an axis of independent work over it with
`spread`. Without an ambient mesh `spread` does nothing, so the same code serves one device.
"""

from __future__ import annotations

import jax
from jax.sharding import PartitionSpec

BATCH_AXIS = "batch"


def spread(x: jax.Array, axis: int) -> jax.Array:
    """`x` with `axis` split over the ambient mesh's batch devices (traced; identity without such a mesh)."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or BATCH_AXIS not in mesh.axis_names:
        return x
    spec = [None] * x.ndim
    spec[axis] = BATCH_AXIS
    return jax.lax.with_sharding_constraint(x, PartitionSpec(*spec))
