"""`gemma.attend`'s hand-written backward pass against JAX's own differentiation of the same forward computation."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from openpi_cam.model import gemma

# Relative to the largest reference gradient of each input. float32: both are float32 sums of the same products in
# another order (measured at most 4.7e-7); bfloat16 keys and values round the cotangents too (measured at most 4.0e-3).
TOLERANCE = {"float32": 1e-5, "bfloat16": 2e-2}


@pytest.mark.parametrize(
    "q_dtype, kv_dtype, hidden_slots",
    [
        ("float32", "float32", 0),  # pi0-FAST in float32
        ("float32", "float32", 5),  # a replay cut short of the decode length
        ("float32", "bfloat16", 3),  # pi0-FAST in bfloat16: RoPE keeps the queries float32
        ("bfloat16", "bfloat16", 0),  # pi0 / pi0.5 in bfloat16
    ],
)
def test_attention_gradients_equal_the_differentiated_computation(q_dtype, kv_dtype, hidden_slots):
    """Masks with fully masked rows (padding, which softmaxes uniformly and must pass no gradient to its logits),
    a row that sees one slot, and ordinary rows; random cotangents. The forward pass is the plain computation."""
    b, t, s, k, g, h = 2, 6, 9, 1, 2, 8
    keys = jax.random.split(jax.random.key(0), 5)
    q = jax.random.normal(keys[0], (b, t, k, g, h)).astype(q_dtype)
    kk = jax.random.normal(keys[1], (b, s, k, h)).astype(kv_dtype)
    v = jax.random.normal(keys[2], (b, s, k, h)).astype(kv_dtype)
    mask = np.array(jax.random.bernoulli(keys[3], 0.6, (b, t, s)))
    mask[0, 1] = False  # fully masked row
    mask[1, 4] = False
    mask[1, 4, 2] = True  # one visible slot
    cot = jax.random.normal(keys[4], (b, t, k, g, h)).astype(kv_dtype)

    def plain(q, kk, v):
        return gemma._masked_softmax_attention(q, kk, v, mask, hidden_slots)[0]

    def custom(q, kk, v):
        return gemma.attend(q, kk, v, mask, hidden_slots)

    want, want_vjp = jax.vjp(plain, q, kk, v)
    got, got_vjp = jax.vjp(custom, q, kk, v)
    np.testing.assert_array_equal(np.asarray(got, np.float32), np.asarray(want, np.float32))
    tol = TOLERANCE[kv_dtype]
    for name, x, ref in zip(("q", "k", "v"), got_vjp(cot), want_vjp(cot), strict=True):
        assert x.dtype == ref.dtype, name
        x, ref = np.asarray(x, np.float32), np.asarray(ref, np.float32)
        scale = np.abs(ref).max()
        assert scale > 0, name
        assert np.abs(x - ref).max() <= tol * scale, f"d{name}: {np.abs(x - ref).max() / scale:.2e} of its scale"
    assert not np.any(np.asarray(got_vjp(cot)[0], np.float32)[0, 1])  # the padding row's query gets no gradient
