"""What the serving tests share: reading a server's run directories, comparing a served response with the
in-process one, policies that record or hold their requests, the bad requests and the robot's client scripts, and a
peer that hangs after its handshake. The module fixtures are in `conftest.py`."""

from __future__ import annotations

import base64
import os
import socket
import threading
from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.cam.run_format import RUN_JSON
from openpi_cam.serving import RequestContext, msgpack_numpy


def run_dirs(cam_dir: Path) -> list[Path]:
    """The run directories a server wrote under `cam_dir` (each holds its run.json)."""
    return sorted(p.parent for p in Path(cam_dir).glob(f"*/{RUN_JSON}"))


def assert_same_response(served: dict, local: dict) -> None:
    """The served response is the in-process one: same keys, and every non-timing value equal in dtype and bits."""
    assert set(served) == set(local) | {"server_timing"}
    for key in set(local) - {"policy_timing"}:
        assert served[key].dtype == np.asarray(local[key]).dtype, key
        np.testing.assert_array_equal(served[key], np.asarray(local[key]), err_msg=key)


class TracingPolicy:
    """A real policy that records the model output of every request it serves (the generated ids, which depend on
    the observation even where the actions do not)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.outputs: list[np.ndarray] = []

    @property
    def metadata(self) -> dict:
        return self.inner.metadata

    def infer(self, obs: dict, context: RequestContext | None = None) -> dict:
        response, trace = self.inner.infer_traced(obs)
        self.outputs.append(trace.output)
        return response


class GatedPolicy:
    """The real policy, except that `infer` can be held (gate closed) to keep a request in flight."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.entered = threading.Event()
        self.gate = threading.Event()
        self.gate.set()
        self.events: list[str] = []
        self.contexts: list[RequestContext | None] = []

    @property
    def metadata(self) -> dict:
        return self.inner.metadata

    def infer(self, obs: dict, context: RequestContext | None = None) -> dict:
        self.contexts.append(context)
        self.entered.set()
        if not self.gate.wait(120):
            raise TimeoutError("the test never opened the gate")
        result = self.inner.infer(obs, context)
        self.events.append("infer")
        return result

    def stats(self) -> dict:
        return {"gated_calls": len(self.contexts)}

    def close(self, timeout: float) -> None:
        self.events.append(f"close({timeout})")


BAD_REQUESTS = r"""
import functools

JOINT = "observation/joint_position"
IMAGE = "observation/exterior_image_1_left"
policy = connect()
good = droid_obs(np.random.RandomState(0), size=(64, 96))

def with_field(key, value):
    obs = dict(good)
    obs[key] = value
    return obs

def without(key):
    return {k: v for k, v in good.items() if k != key}

nested = functools.reduce(lambda a, _: [a], range(500), 0)  # msgpack's packer stops at 512 levels

def crafted(obs):
    # Plain msgpack with hand-made array maps: the client's own packer refuses these dtypes.
    return msgpack.packb(obs, default=msgpack_numpy.pack_array)

def arr(data, dtype, shape):
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}

cases = {
    "garbage": lambda: infer_raw(policy, b"\xc1\xc1 this is not msgpack"),
    "truncated": lambda: infer_raw(policy, msgpack_numpy.packb(good)[:-7]),
    "text_frame": lambda: infer_raw(policy, "hello"),
    "top_level_list": lambda: policy.infer([1, 2, 3]),
    "complex_dtype": lambda: infer_raw(policy, crafted(with_field(JOINT, arr(b"\0" * 112, "<c16", [7])))),
    "object_dtype": lambda: infer_raw(policy, crafted(with_field(JOINT, arr(b"\0" * 56, "|O8", [7])))),
    "void_dtype": lambda: infer_raw(policy, crafted(with_field(JOINT, arr(b"\0" * 56, "|V8", [7])))),
    "buffer_mismatch": lambda: infer_raw(policy, crafted(with_field(IMAGE, arr(b"\0" * 100, "|u1", [64, 96, 3])))),
    "absurd_shape": lambda: infer_raw(policy, crafted(with_field(IMAGE, arr(b"", "|u1", [0, 2**40, 3])))),
    "missing_key": lambda: policy.infer(without(JOINT)),
    "image_shape": lambda: policy.infer(with_field(IMAGE, good[IMAGE][..., 0])),
    "image_dtype": lambda: policy.infer(with_field(IMAGE, good[IMAGE].astype(np.int32))),
    "non_finite_state": lambda: policy.infer(with_field(JOINT, np.array([0.1, np.nan, 0, 0, 0, 0, 0]))),
    # Hostile frames (issue 20): amplification, deep nesting, huge strings echoed back, a dtype JAX cannot take.
    "many_empty_maps": lambda: infer_raw(policy, crafted(with_field("junk", [{}] * 300_000))),
    "deep_nesting": lambda: infer_raw(policy, crafted(with_field("junk", nested))),
    "huge_dtype": lambda: infer_raw(policy, crafted(with_field(JOINT, arr(b"\0" * 56, "<f8" + " " * 1_000_000, [7])))),
    "huge_shape": lambda: infer_raw(policy, crafted(with_field(IMAGE, arr(b"", "|u1", [1] * 1_000_000)))),
    "huge_key": lambda: infer_raw(policy, crafted(with_field("k" * 1_000_000, 1))),
    "float128": lambda: infer_raw(policy, crafted(with_field(JOINT, arr(b"\0" * 112, "<f16", [7])))),
}
results = {}
for name, fn in cases.items():
    error = error_of(fn)
    after = policy.infer(good)  # the same connection keeps serving
    results[name] = {"error": error, "after_shape": list(after["actions"].shape)}
done(results=results)
"""

# What each bad request's message must name. "decode" problems are caught by the wire format, the rest by the
# policy's input transforms.
BAD_REQUEST_EXPECTATIONS = {
    "garbage": ("decode", "not valid msgpack"),
    "truncated": ("decode", "not valid msgpack"),
    "text_frame": ("text_frame", "text frame"),
    "top_level_list": ("decode", "must be a map"),
    "complex_dtype": ("decode", "'<c16'"),
    "object_dtype": ("decode", "'|O8'"),
    "void_dtype": ("decode", "'|V8'"),
    "buffer_mismatch": ("decode", "100 bytes"),
    "absurd_shape": ("decode", "shape"),
    "missing_key": ("invalid_request", "observation/joint_position"),
    "image_shape": ("invalid_request", "observation/exterior_image_1_left"),
    "image_dtype": ("invalid_request", "int32"),
    "non_finite_state": ("invalid_request", "NaN"),
    "many_empty_maps": ("decode", "more than 10000 maps and lists"),
    "deep_nesting": ("decode", "deeper than 32 levels"),
    "huge_dtype": ("decode", "unsupported array dtype"),
    "huge_shape": ("decode", "malformed array shape"),
    "huge_key": ("decode", "longer than 1024 characters"),
    "float128": ("decode", "128-bit f numbers"),
}
# The longest error text any of them may send back: the message quotes at most 60 characters of a value.
MAX_ERROR_CHARS = 400


# A robot that keeps working while the hostile clients run: paced good requests on its own connection.
ROBOT = r"""
import time
policy = connect()
rng = np.random.RandomState(1)
shapes, latencies = [], []
for _ in range(ARGS["n"]):
    start = time.monotonic()
    shapes.append(list(policy.infer(droid_obs(rng, size=(64, 96)))["actions"].shape))
    latencies.append(time.monotonic() - start)
    time.sleep(0.1)
done(shapes=shapes, latencies=latencies)
"""


def droid_obs_bytes(rng: np.random.Generator, size: tuple[int, int]) -> bytes:
    """A DROID observation as the client packs it (our packer writes the client's bytes)."""
    obs = {
        "observation/exterior_image_1_left": rng.integers(256, size=(*size, 3), dtype=np.uint8),
        "observation/wrist_image_left": rng.integers(256, size=(64, 96, 3), dtype=np.uint8),
        "observation/joint_position": rng.random(7),
        "observation/gripper_position": rng.random(1),
        "prompt": "do something",
    }
    return msgpack_numpy.packb(obs)


def stalled_peer(port: int) -> socket.socket:
    """A websocket client that completes the opening handshake and then never reads or answers again (a robot process
    that hung): the server's metadata frame and close frame go unanswered."""
    sock = socket.create_connection(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        (
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return sock
