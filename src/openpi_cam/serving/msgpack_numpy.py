"""msgpack with NumPy arrays, byte-compatible with openpi-client's `msgpack_numpy`, and strict when decoding.

Wire format (what openpi-client writes and reads): an array is the map
`{b"__ndarray__": True, b"data": <C-order bytes>, b"dtype": dtype.str, b"shape": [dims]}` and a NumPy scalar is
`{b"__npgeneric__": True, b"data": <python value>, b"dtype": dtype.str}`; everything else is plain msgpack
(str as str type, bytes as bin type).

Decoding untrusted bytes rejects anything that is not plain numbers, bools or strings laid out exactly as declared,
with an `InvalidRequest` naming the problem. Decoded arrays are read-only views of the received frame, as upstream's.
"""

from __future__ import annotations

import math
import re
from typing import Any

import msgpack
import numpy as np

from openpi_cam.errors import InvalidRequest

ARRAY_TAG = b"__ndarray__"
SCALAR_TAG = b"__npgeneric__"
_ARRAY_KEYS = frozenset({ARRAY_TAG, b"data", b"dtype", b"shape"})
_SCALAR_KEYS = frozenset({SCALAR_TAG, b"data", b"dtype"})
# bool, signed/unsigned int, float, bytes, unicode; never object, void/structured, complex, datetime.
_ALLOWED_KINDS = frozenset("biufSU")
_DTYPE_RE = re.compile(r"^[<>|=]?[biufSU]\d+$")
MAX_NDIM = 16
MAX_DIM = 2**31 - 1


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray | np.generic):
        if obj.dtype.kind not in _ALLOWED_KINDS or obj.dtype.fields is not None:
            raise TypeError(f"cannot send NumPy dtype {obj.dtype} (only bool, int, uint, float, bytes, str)")
        if isinstance(obj, np.generic):
            return {SCALAR_TAG: True, b"data": obj.item(), b"dtype": obj.dtype.str}
        return {ARRAY_TAG: True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": list(obj.shape)}
    if hasattr(obj, "__array__"):  # e.g. a jax.Array left in a response
        return _encode(np.asarray(obj))
    raise TypeError(f"cannot send an object of type {type(obj).__name__}")


def packb(obj: Any) -> bytes:
    """Serialises `obj` (dicts, lists, scalars, str, bytes, NumPy arrays and scalars) the way openpi-client does."""
    return msgpack.packb(obj, default=_encode, use_bin_type=True)


def _parse_dtype(value: Any) -> np.dtype:
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    if not isinstance(value, str) or not _DTYPE_RE.match(value):
        raise InvalidRequest(
            f"unsupported array dtype {value!r}: only bool, int, uint, float, bytes and str are accepted"
        )
    dtype = np.dtype(value)
    if dtype.kind not in _ALLOWED_KINDS or dtype.itemsize == 0:
        raise InvalidRequest(f"unsupported array dtype {value!r}")
    return dtype


def _decode_array(obj: dict) -> np.ndarray:
    if set(obj) != _ARRAY_KEYS:
        raise InvalidRequest(
            f"malformed array: keys {sorted(map(repr, obj))}, expected {sorted(map(repr, _ARRAY_KEYS))}"
        )
    dtype = _parse_dtype(obj[b"dtype"])
    shape = obj[b"shape"]
    if not isinstance(shape, list | tuple) or len(shape) > MAX_NDIM:
        raise InvalidRequest(f"malformed array shape {shape!r}: expected a list of at most {MAX_NDIM} sizes")
    if not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= MAX_DIM for d in shape):
        raise InvalidRequest(f"malformed array shape {shape!r}: sizes must be integers in [0, {MAX_DIM}]")
    data = obj[b"data"]
    if not isinstance(data, bytes):
        raise InvalidRequest(f"malformed array: data is {type(data).__name__}, expected bytes")
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise InvalidRequest(
            f"array buffer has {len(data)} bytes but shape {list(shape)} of dtype {dtype.str} needs {expected}"
        )
    return np.ndarray(shape=tuple(shape), dtype=dtype, buffer=data)


def _decode_scalar(obj: dict) -> np.generic:
    if set(obj) != _SCALAR_KEYS:
        raise InvalidRequest(
            f"malformed scalar: keys {sorted(map(repr, obj))}, expected {sorted(map(repr, _SCALAR_KEYS))}"
        )
    dtype = _parse_dtype(obj[b"dtype"])
    data = obj[b"data"]
    if not isinstance(data, bool | int | float | str | bytes):
        raise InvalidRequest(f"malformed scalar: data is {type(data).__name__}")
    try:
        return dtype.type(data)
    except (TypeError, ValueError, OverflowError) as e:
        raise InvalidRequest(f"scalar {data!r} does not fit dtype {dtype.str}: {e}") from e


def _decode_map(obj: dict) -> Any:
    if ARRAY_TAG in obj:
        return _decode_array(obj)
    if SCALAR_TAG in obj:
        return _decode_scalar(obj)
    return obj


def _reject_ext(code: int, data: bytes) -> Any:
    raise InvalidRequest(f"msgpack extension type {code} is not accepted")


def unpackb(data: bytes) -> Any:
    """Decodes bytes written by openpi-client's packer; anything malformed raises `InvalidRequest`."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise InvalidRequest(f"expected bytes, got {type(data).__name__}")
    try:
        return msgpack.unpackb(data, object_hook=_decode_map, ext_hook=_reject_ext, raw=False, strict_map_key=True)
    except InvalidRequest:
        raise
    except (ValueError, TypeError, msgpack.UnpackException, RecursionError) as e:
        # ValueError covers msgpack's FormatError, ExtraData, truncated input and non-str/bytes map keys.
        raise InvalidRequest(f"request is not valid msgpack: {type(e).__name__}: {e or 'malformed data'}") from e


def unpack_request(data: bytes) -> dict[str, Any]:
    """Decodes one observation frame: a msgpack map with string keys at the top level."""
    obj = unpackb(data)
    if not isinstance(obj, dict):
        raise InvalidRequest(f"request must be a map of observation fields, got {type(obj).__name__}")
    bad = [k for k in obj if not isinstance(k, str)]
    if bad:
        raise InvalidRequest(f"request keys must be strings, got {bad[:3]!r}")
    return obj
