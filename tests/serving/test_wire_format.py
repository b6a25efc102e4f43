"""The msgpack-numpy wire format in process: values, dtypes and byte order survive; malformed frames are refused
naming the problem before anything large is allocated; decoded arrays are read-only views, like upstream's."""

from __future__ import annotations

import dataclasses
import tracemalloc

import msgpack
import numpy as np
import pytest

from openpi_cam.errors import InvalidRequest
from openpi_cam.serving import msgpack_numpy


def _packed_array(data: bytes, dtype: str, shape: list) -> dict:
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}


def test_wire_format_round_trip_keeps_values_dtypes_and_byte_order():
    obj = {
        "f64": np.linspace(-1, 1, 7),
        "big_endian": np.arange(4, dtype=">f4"),
        "fortran": np.asfortranarray(np.arange(12, dtype=np.int32).reshape(3, 4)),
        "empty": np.zeros((0, 5), np.uint8),
        "zero_d": np.array(True),
        "strings": np.array(["ab", "c"]),
        "nested": {"scalar": np.int64(-3), "list": [1, 2.5, "x", b"raw"]},
    }
    back = msgpack_numpy.unpack_request(msgpack_numpy.packb(obj))
    for key in ("f64", "big_endian", "fortran", "empty", "zero_d", "strings"):
        assert back[key].dtype == obj[key].dtype, key
        np.testing.assert_array_equal(back[key], obj[key], err_msg=key)
    assert type(back["nested"]["scalar"]) is np.int64 and back["nested"]["scalar"] == -3
    assert back["nested"]["list"] == [1, 2.5, "x", b"raw"]


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (b"\xc1\xc1", "not valid msgpack"),
        (msgpack_numpy.packb({"a": np.zeros(10)})[:-5], "not valid msgpack"),
        (msgpack_numpy.packb([1, 2]), "must be a map"),
        (msgpack_numpy.packb({"a": _packed_array(b"\0" * 16, "<c8", [2])}), "'<c8'"),
        (msgpack_numpy.packb({"a": _packed_array(b"\0" * 8, "|O8", [1])}), "'|O8'"),
        (msgpack_numpy.packb({"a": _packed_array(b"\0" * 8, "|V8", [1])}), "'|V8'"),
        (msgpack_numpy.packb({"a": _packed_array(b"\0" * 8, "[('x', '<i4')]", [1])}), "dtype"),
        (msgpack_numpy.packb({"a": _packed_array(b"\0" * 10, "<f4", [3])}), "10 bytes"),
        (msgpack_numpy.packb({"a": _packed_array(b"", "|u1", [0, 2**40])}), "shape"),
        (msgpack_numpy.packb({"a": _packed_array(b"", "|u1", [-1])}), "shape"),
        (msgpack_numpy.packb({"a": _packed_array(b"", "|u1", [1] * 40)}), "shape"),
        (msgpack_numpy.packb({"a": {b"__npgeneric__": True, b"data": 300, b"dtype": "|u1"}}), "does not fit"),
        (msgpack_numpy.packb({"a": {b"__ndarray__": True, b"data": b""}}), "malformed array"),
    ],
)
def test_wire_format_rejects_malformed_requests_naming_the_problem(payload: bytes, expected: str):
    with pytest.raises(InvalidRequest) as info:
        msgpack_numpy.unpack_request(payload)
    assert expected in str(info.value)


def test_decoding_stops_at_its_budget_before_allocating_the_frame():
    """A 1.9 MB frame of two million empty maps (~140 bytes of Python objects each: 137 MB measured when decoded in
    full) is refused once the container budget is spent. Measured peak of the refused decode: 0.7 MB (tracemalloc);
    the bound 8 MB is 4x the frame itself, far below a full decode."""
    payload = msgpack.packb({"junk": [{}] * 2_000_000})
    tracemalloc.start()
    try:
        with pytest.raises(InvalidRequest, match="more than 10000 maps and lists"):
            msgpack_numpy.unpack_request(payload)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20
    limits = msgpack_numpy.DecodeLimits(max_containers=3, max_depth=2, max_arrays=1, max_key_chars=4)
    assert msgpack_numpy.unpack_request(msgpack.packb({"a": [1], "b": {"c": 2}}), limits) == {"a": [1], "b": {"c": 2}}
    for obj, message in (
        ({"a": [1], "b": [2], "c": [3]}, "more than 3 maps and lists"),
        ({"a": [[1]]}, "deeper than 2 levels"),
        ({"a": np.zeros(1), "b": np.ones(1)}, "more than 1 arrays"),  # (each array is a map and a shape list)
        ({"abcde": 1}, "longer than 4 characters"),
    ):
        with pytest.raises(InvalidRequest, match=message):
            budget = dataclasses.replace(limits, max_containers=10) if "arrays" in message else limits
            msgpack_numpy.unpack_request(msgpack_numpy.packb(obj), budget)


def test_responses_pack_jax_arrays_and_refuse_unsendable_dtypes():
    import jax.numpy as jnp

    back = msgpack_numpy.unpackb(msgpack_numpy.packb({"a": jnp.arange(3, dtype=jnp.float32)}))
    assert back["a"].dtype == np.float32 and back["a"].tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(TypeError, match="complex128"):
        msgpack_numpy.packb({"a": np.zeros(2, complex)})
    with pytest.raises(TypeError, match="object"):
        msgpack_numpy.packb({"a": object()})


def test_decoded_arrays_are_read_only_views_like_upstream():
    back = msgpack_numpy.unpack_request(msgpack_numpy.packb({"x": np.ones(3)}))
    assert not back["x"].flags.writeable
