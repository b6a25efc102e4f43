"""msgpack with NumPy arrays, byte-compatible with openpi-client's `msgpack_numpy`, and strict when decoding.

Wire format (what openpi-client writes and reads): an array is the map
`{b"__ndarray__": True, b"data": <C-order bytes>, b"dtype": dtype.str, b"shape": [dims]}` and a NumPy scalar is
`{b"__npgeneric__": True, b"data": <python value>, b"dtype": dtype.str}`; everything else is plain msgpack
(str as str type, bytes as bin type).

Decoding untrusted bytes rejects anything that is not plain numbers, bools or strings laid out exactly as declared,
with an `InvalidRequest` naming the problem. Decoded arrays are read-only views of the received frame, as upstream's.
A frame is decoded within explicit budgets (`DecodeLimits`: containers, nesting depth, arrays, key length), checked
while msgpack builds it, so a frame of a million empty maps is refused after the budget, not after allocating them
all; error messages quote at most a short prefix of an offending value.
"""

from __future__ import annotations

import dataclasses
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
# Item sizes NumPy and JAX both take: float128 / int128 do not exist on the model's side.
_ITEMSIZES = {"b": (1,), "i": (1, 2, 4, 8), "u": (1, 2, 4, 8), "f": (2, 4, 8)}
_QUOTE_CHARS = 60  # longest prefix of an offending value an error message quotes


@dataclasses.dataclass(frozen=True)
class DecodeLimits:
    """Budgets of one decoded request. A robot's observation has a few dozen keys, a handful of arrays and a
    nesting depth of 2-3; the defaults leave two orders of magnitude of room."""

    max_containers: int = 10_000  # maps and lists in the whole frame
    max_depth: int = 32  # nesting of maps and lists
    max_arrays: int = 1_000  # NumPy arrays and scalars
    max_key_chars: int = 1_024  # length of one map key


DEFAULT_LIMITS = DecodeLimits()


def quote(value: Any, limit: int = _QUOTE_CHARS) -> str:
    """repr(value) cut to `limit` characters, naming the full length: what error messages and log lines quote."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


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
    if not isinstance(value, str) or len(value) > 16 or not _DTYPE_RE.match(value):
        raise InvalidRequest(
            f"unsupported array dtype {quote(value)}: only bool, int, uint, float, bytes and str are accepted"
        )
    dtype = np.dtype(value)
    if dtype.kind not in _ALLOWED_KINDS or dtype.itemsize == 0:
        raise InvalidRequest(f"unsupported array dtype {quote(value)}")
    if dtype.kind in _ITEMSIZES and dtype.itemsize not in _ITEMSIZES[dtype.kind]:
        raise InvalidRequest(f"unsupported array dtype {quote(value)}: {dtype.itemsize * 8}-bit {dtype.kind} numbers")
    return dtype


def _decode_array(obj: dict) -> np.ndarray:
    if set(obj) != _ARRAY_KEYS:
        raise InvalidRequest(f"malformed array: keys {quote(sorted(map(repr, obj)))}, expected {sorted(_ARRAY_KEYS)}")
    dtype = _parse_dtype(obj[b"dtype"])
    shape = obj[b"shape"]
    if not isinstance(shape, list | tuple) or len(shape) > MAX_NDIM:
        raise InvalidRequest(f"malformed array shape {quote(shape)}: expected a list of at most {MAX_NDIM} sizes")
    if not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= MAX_DIM for d in shape):
        raise InvalidRequest(f"malformed array shape {quote(shape)}: sizes must be integers in [0, {MAX_DIM}]")
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
        raise InvalidRequest(f"malformed scalar: keys {quote(sorted(map(repr, obj)))}, expected {sorted(_SCALAR_KEYS)}")
    dtype = _parse_dtype(obj[b"dtype"])
    data = obj[b"data"]
    if not isinstance(data, bool | int | float | str | bytes):
        raise InvalidRequest(f"malformed scalar: data is {type(data).__name__}")
    try:
        return dtype.type(data)
    except (TypeError, ValueError, OverflowError) as e:
        raise InvalidRequest(f"scalar {quote(data)} does not fit dtype {dtype.str}: {quote(str(e))}") from e


class _Budget:
    """Counts what msgpack builds, container by container (its hooks run as each map or list is complete), and stops
    the decode as soon as a budget is exceeded."""

    def __init__(self, limits: DecodeLimits) -> None:
        self.limits = limits
        self.containers = 0
        self.arrays = 0

    def _count(self) -> None:
        self.containers += 1
        if self.containers > self.limits.max_containers:
            raise InvalidRequest(f"request has more than {self.limits.max_containers} maps and lists")

    def decode_map(self, obj: dict) -> Any:
        self._count()
        if ARRAY_TAG in obj or SCALAR_TAG in obj:
            self.arrays += 1
            if self.arrays > self.limits.max_arrays:
                raise InvalidRequest(f"request has more than {self.limits.max_arrays} arrays")
            return _decode_array(obj) if ARRAY_TAG in obj else _decode_scalar(obj)
        for key in obj:
            if isinstance(key, (str, bytes)) and len(key) > self.limits.max_key_chars:
                raise InvalidRequest(f"map key {quote(key)} is longer than {self.limits.max_key_chars} characters")
        return obj

    def decode_list(self, obj: list) -> list:
        self._count()
        return obj


def _check_depth(obj: Any, max_depth: int) -> None:
    """Nesting depth of maps and lists, walked without recursion (a deep request must not exhaust the stack)."""
    stack = [(obj, 1)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict | list):
            if depth > max_depth:
                raise InvalidRequest(f"request nests maps and lists deeper than {max_depth} levels")
            children = node.values() if isinstance(node, dict) else node
            stack.extend((child, depth + 1) for child in children)


def _reject_ext(code: int, data: bytes) -> Any:
    raise InvalidRequest(f"msgpack extension type {code} is not accepted")


def unpackb(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> Any:
    """Decodes bytes written by openpi-client's packer within `limits`; anything malformed raises `InvalidRequest`."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise InvalidRequest(f"expected bytes, got {type(data).__name__}")
    budget = _Budget(limits)
    try:
        obj = msgpack.unpackb(
            data,
            object_hook=budget.decode_map,
            list_hook=budget.decode_list,
            ext_hook=_reject_ext,
            raw=False,
            strict_map_key=True,
        )
    except InvalidRequest:
        raise
    except (ValueError, TypeError, msgpack.UnpackException, RecursionError) as e:
        # ValueError covers msgpack's FormatError, ExtraData, truncated input, too deep input and non-str/bytes keys.
        raise InvalidRequest(
            f"request is not valid msgpack: {type(e).__name__}: {quote(str(e) or 'malformed data')}"
        ) from e
    _check_depth(obj, limits.max_depth)
    return obj


def unpack_request(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> dict[str, Any]:
    """Decodes one observation frame: a msgpack map with string keys at the top level."""
    obj = unpackb(data, limits)
    if not isinstance(obj, dict):
        raise InvalidRequest(f"request must be a map of observation fields, got {type(obj).__name__}")
    bad = [k for k in obj if not isinstance(k, str)]
    if bad:
        raise InvalidRequest(f"request keys must be strings, got {quote(bad[:3])}")
    return obj
