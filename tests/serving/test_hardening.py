"""What clients cannot do to the server: bad requests get named errors and the connection keeps working, unexpected
errors stay short unless --debug, health and stats answer during inference, API keys, message, connection and
buffer caps, peers that never read their replies, and a shutdown that finishes the request in flight."""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from typing import Any

import numpy as np
import pytest
import websockets
from client_env import collect, run_client, spawn_client
from real_clients import (
    client_script,
    get_stats,
    http_get,
    responses,
    send_observations,
)
from serving_support import (
    BAD_REQUEST_EXPECTATIONS,
    BAD_REQUESTS,
    MAX_ERROR_CHARS,
    GatedPolicy,
    assert_same_response,
    droid_obs_bytes,
    stalled_peer,
)
from websockets.sync.client import connect

from openpi_cam.serving import RequestContext, msgpack_numpy
from openpi_cam.serving.server import (
    AUTH_FREE_FAILURES,
    PEER_TIMEOUT_S,
    start_server_in_thread,
)


def test_bad_requests_get_named_errors_and_the_connection_keeps_working(policy):
    running = start_server_in_thread(policy, metadata={}, close_policy_on_stop=False)
    try:
        result = run_client(client_script(BAD_REQUESTS), json.dumps({"port": running.port}))["results"]
        stats = get_stats(running.port)
    finally:
        running.stop()
    assert set(result) == set(BAD_REQUEST_EXPECTATIONS)
    for name, (_, expected) in BAD_REQUEST_EXPECTATIONS.items():
        error = result[name]["error"]
        assert error is not None, f"{name}: the server accepted it"
        # The real client raises a text frame as RuntimeError("Error in inference server:\n<frame>").
        assert error.startswith("RuntimeError: Error in inference server:\nInvalidRequest: "), (name, error)
        assert expected in error, (name, error)
        assert len(error) <= MAX_ERROR_CHARS, (name, len(error))  # a 1 MB value is not echoed back
        assert result[name]["after_shape"] == [10, 8], name

    n = len(BAD_REQUEST_EXPECTATIONS)
    assert stats["requests"] == 2 * n
    assert stats["ok"] == n
    expected_errors: dict[str, int] = {}
    for kind, _ in BAD_REQUEST_EXPECTATIONS.values():
        expected_errors[kind] = expected_errors.get(kind, 0) + 1
    assert stats["errors"] == expected_errors
    latency = stats["latency_ms"]
    assert latency["window"] == n
    assert 0 < latency["infer"]["p50"] <= latency["infer"]["p90"] <= latency["infer"]["p99"] <= latency["infer"]["max"]
    assert latency["total"]["p50"] >= latency["infer"]["p50"]
    assert stats["connections"] == {"open": 0, "total": 1}


class _Exploding:
    """A policy whose infer fails the way a bug would (not an InvalidRequest)."""

    metadata: dict = {}  # noqa: RUF012

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.calls = 0

    def infer(self, obs: dict, context: RequestContext | None = None) -> dict:
        self.calls += 1
        if self.calls == 1:
            raise ZeroDivisionError("boom in the model")
        return self.inner.infer(obs, context)


@pytest.mark.parametrize("debug", [False, True])
def test_unexpected_errors_are_reported_short_unless_debug(policy, debug):
    running = start_server_in_thread(_Exploding(policy), debug=debug, close_policy_on_stop=False)
    body = r"""
policy = connect()
obs = droid_obs(np.random.RandomState(0), size=(32, 32))
error = error_of(lambda: policy.infer(obs))
done(error=error, after=list(policy.infer(obs)["actions"].shape))
"""
    try:
        result = run_client(client_script(body), json.dumps({"port": running.port}))
        stats = get_stats(running.port)
    finally:
        running.stop()
    assert "Internal server error: ZeroDivisionError: boom in the model" in result["error"]
    assert ("Traceback (most recent call last)" in result["error"]) == debug
    assert result["after"] == [10, 8]
    assert stats["errors"] == {"internal": 1}


def test_healthz_stats_and_new_connections_answer_while_inference_runs(demo_policy, demo_observations, tmp_path):
    gated = GatedPolicy(demo_policy)
    running = start_server_in_thread(gated, metadata={"who": "gated"}, close_policy_on_stop=False)
    try:
        gated.gate.clear()
        busy = send_observations(running.port, tmp_path / "busy", demo_observations[:1])
        assert gated.entered.wait(60), "the request never reached the policy"

        status, body = http_get(f"http://127.0.0.1:{running.port}/healthz")
        assert (status, body) == (200, "OK\n")
        stats = get_stats(running.port)
        assert stats["connections"]["open"] == 1 and stats["policy"] == {"gated_calls": 1}
        metadata_only = run_client(
            client_script("done(meta=connect().get_server_metadata())"), json.dumps({"port": running.port})
        )
        assert metadata_only["meta"] == {"who": "gated"}
        # All of that happened with the only request still held inside the policy.
        assert gated.events == [] and busy.poll() is None

        gated.gate.set()
        collect(busy)
    finally:
        gated.gate.set()
        running.stop()
    (served,) = responses(tmp_path / "busy", 1)
    assert_same_response(served, demo_policy.infer(demo_observations[0]))
    (context,) = gated.contexts
    assert context is not None and context.request_index == 0 and context.connection_id


def test_request_context_identifies_connection_and_frame(policy):
    recorder = GatedPolicy(policy)  # gate open: only records the contexts
    running = start_server_in_thread(recorder, close_policy_on_stop=False)
    body = r"""
obs = droid_obs(np.random.RandomState(0), size=(32, 32))
first = connect()
error_of(lambda: infer_raw(first, b"not msgpack"))  # frame 0: rejected before the policy
first.infer(obs)
first.infer(obs)
connect().infer(obs)
done(ok=True)
"""
    try:
        run_client(client_script(body), json.dumps({"port": running.port}))
    finally:
        running.stop()
    a, b, c = recorder.contexts
    assert (a.connection_id, a.request_index) == (b.connection_id, 1)
    assert b.request_index == 2
    assert c.request_index == 0 and c.connection_id != a.connection_id


def test_api_key_and_message_size_limit(policy):
    running = start_server_in_thread(policy, api_key="s3cret", max_message_bytes=200_000, close_policy_on_stop=False)
    body = r"""
res = {}
res["no_key"] = error_of(lambda: connect())
res["wrong_key"] = error_of(lambda: connect(api_key="nope"))
policy = connect(api_key="s3cret")
small = droid_obs(np.random.RandomState(0), size=(96, 128))  # ~74 kB packed
big = droid_obs(np.random.RandomState(0), size=(224, 224))  # ~301 kB packed
res["small"] = list(policy.infer(small)["actions"].shape)
res["big"] = error_of(lambda: policy.infer(big))
res["after_reconnect"] = list(connect(api_key="s3cret").infer(small)["actions"].shape)
done(**res)
"""
    try:
        result = run_client(client_script(body), json.dumps({"port": running.port}))
        base = f"http://127.0.0.1:{running.port}"
        healthz = http_get(f"{base}/healthz")
        stats_without_key = http_get(f"{base}/stats")
        stats = get_stats(running.port, {"Authorization": "Api-Key s3cret"})
    finally:
        running.stop()
    assert "401" in result["no_key"] and "401" in result["wrong_key"]
    assert result["small"] == [10, 8] and result["after_reconnect"] == [10, 8]
    # websockets closes an over-limit message's connection with 1009 (message too big), naming the limit.
    assert "1009" in result["big"] and "200000" in result["big"], result["big"]
    assert healthz == (200, "OK\n")
    assert stats_without_key[0] == 401 and "Api-Key" in stats_without_key[1]
    assert stats["errors"] == {"unauthorized": 3, "too_large": 1}
    assert stats["ok"] == 2


def _port_refuses(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    except OSError:
        return True
    return False


def test_shutdown_finishes_in_flight_request_then_closes_the_policy(policy, tmp_path):
    gated = GatedPolicy(policy)
    running = start_server_in_thread(gated, drain_timeout=7.5)
    body = r"""
policy = connect()
obs = droid_obs(np.random.RandomState(0), size=(32, 32))
first = list(policy.infer(obs)["actions"].shape)
done(first=first, second=error_of(lambda: policy.infer(obs)))
"""
    gated.gate.clear()
    proc = spawn_client(client_script(body), json.dumps({"port": running.port}))
    try:
        assert gated.entered.wait(60)
        stopper = threading.Thread(target=running.stop)
        stopper.start()
        deadline = time.monotonic() + 10
        while not _port_refuses(running.port) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _port_refuses(running.port), "still accepting connections after stop()"
        assert gated.events == []
    finally:
        gated.gate.set()
    stopper.join(60)
    result = collect(proc)
    assert result["first"] == [10, 8]  # the in-flight request was answered
    assert "1001" in result["second"]  # then the connection closed as "going away"
    assert gated.events == ["infer", "close(7.5)"]


def test_connections_beyond_the_cap_are_refused_with_try_again_later(policy):
    """With `max_connections` open, a further connection is closed at once with code 1013 and counted, and a slot
    that frees up is usable again: what one client can make the server buffer stays bounded."""
    running = start_server_in_thread(policy, metadata={"m": 1}, close_policy_on_stop=False, max_connections=2)
    try:
        holders = [stalled_peer(running.port) for _ in range(2)]
        with connect(f"ws://127.0.0.1:{running.port}") as ws, pytest.raises(websockets.ConnectionClosed) as closed:
            ws.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1013
        holders.pop().close()
        deadline = time.monotonic() + 10
        while get_stats(running.port)["connections"]["open"] > 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        with connect(f"ws://127.0.0.1:{running.port}") as ws:
            assert msgpack_numpy.unpackb(ws.recv(timeout=10)) == {"m": 1}  # the metadata frame: served again
        assert get_stats(running.port)["errors"]["too_many_connections"] == 1
    finally:
        for holder in holders:
            holder.close()
        running.stop()


def test_wrong_api_keys_are_answered_ever_slower(policy):
    """Guessing keys: the first AUTH_FREE_FAILURES misses from an address are answered at once, the following ones
    wait 0.2, 0.4, 0.8 s ... (capped at AUTH_MAX_DELAY_S); the right key is not delayed."""
    running = start_server_in_thread(policy, api_key="s3cret", close_policy_on_stop=False)
    base = f"http://127.0.0.1:{running.port}/stats"
    try:
        waits = []
        for _ in range(AUTH_FREE_FAILURES + 3):
            start = time.monotonic()
            assert http_get(base, headers={"Authorization": "Api-Key guess"})[0] == 401
            waits.append(time.monotonic() - start)
        start = time.monotonic()
        assert http_get(base, headers={"Authorization": "Api-Key s3cret"})[0] == 200
        right = time.monotonic() - start
    finally:
        running.stop()
    # The delays are sleeps the server adds: lower bounds hold whatever the machine's load.
    assert all(w >= d for w, d in zip(waits[AUTH_FREE_FAILURES:], (0.2, 0.4, 0.8), strict=True)), waits
    assert right < waits[-1]  # the right key does not inherit the address's back-off (0.8 s above)


def _masked_binary_frame(payload: bytes) -> bytes:
    """One client-to-server websocket binary frame (clients must mask; RFC 6455 section 5.2)."""
    mask = os.urandom(4)
    n = len(payload)
    length = bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + n.to_bytes(2, "big")
    if n >= 2**16:
        length = bytes([0x80 | 127]) + n.to_bytes(8, "big")
    data = np.frombuffer(payload, np.uint8) ^ np.resize(np.frombuffer(mask, np.uint8), n)
    return b"\x82" + length + mask + data.tobytes()


class _LargeReplies:
    """The real policy with a 64 MB array added to every response: more than the socket buffers of both ends hold."""

    metadata: dict = {}  # noqa: RUF012

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def infer(self, obs: dict, context: RequestContext | None = None) -> dict:
        return {**self.inner.infer(obs, context), "padding": np.zeros(64 * 2**20, np.uint8)}


def test_a_peer_that_never_reads_its_reply_is_dropped_and_the_stop_completes(policy):
    """A robot process that hung after sending a request: its reply cannot be sent. The server gives it PEER_TIMEOUT_S,
    drops the connection (counted `send_timeout`), keeps serving others, and stops promptly. Before the send timeout,
    the handler waited forever and `stop()` never returned."""
    running = start_server_in_thread(_LargeReplies(policy), close_policy_on_stop=False)
    obs = droid_obs_bytes(np.random.default_rng(0), size=(64, 96))
    peer = stalled_peer(running.port)
    try:
        peer.sendall(_masked_binary_frame(obs))  # and never reads again
        deadline = time.monotonic() + 60
        while get_stats(running.port)["errors"].get("send_timeout", 0) < 1:
            assert time.monotonic() < deadline, get_stats(running.port)
            time.sleep(0.1)
        with connect(f"ws://127.0.0.1:{running.port}", max_size=None) as ws:  # others are served meanwhile and after
            ws.recv(timeout=10)
            ws.send(obs)
            assert msgpack_numpy.unpackb(ws.recv(timeout=60))["actions"].shape == (10, 8)
        start = time.monotonic()
    finally:
        running.stop(timeout=60)
        peer.close()
    assert time.monotonic() - start < PEER_TIMEOUT_S + 5


def test_requests_past_the_global_buffer_cap_close_their_connection_with_try_again_later(policy):
    """Many connections each within the message limit could still make the server hold more than it can: request
    bytes in progress over all connections are capped. With 1 MiB allowed and one 0.7 MiB request held in the model,
    a second 0.7 MiB request on another connection is refused (1013, counted `server_busy`); once the first is
    answered the same request is served."""
    gated = GatedPolicy(policy)
    running = start_server_in_thread(
        gated, close_policy_on_stop=False, max_message_bytes=2**20, max_buffered_bytes=2**20
    )
    frame = droid_obs_bytes(np.random.default_rng(0), size=(400, 600))
    assert 0.6 * 2**20 < len(frame) < 0.8 * 2**20
    try:
        gated.gate.clear()
        with connect(f"ws://127.0.0.1:{running.port}", max_size=None) as first:
            first.recv(timeout=10)
            first.send(frame)
            assert gated.entered.wait(60)
            with connect(f"ws://127.0.0.1:{running.port}", max_size=None) as second:
                second.recv(timeout=10)
                second.send(frame)
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    second.recv(timeout=10)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1013
            gated.gate.set()
            assert msgpack_numpy.unpackb(first.recv(timeout=60))["actions"].shape == (10, 8)
        with connect(f"ws://127.0.0.1:{running.port}", max_size=None) as third:
            third.recv(timeout=10)
            third.send(frame)
            assert msgpack_numpy.unpackb(third.recv(timeout=60))["actions"].shape == (10, 8)
        assert get_stats(running.port)["errors"] == {"server_busy": 1}
    finally:
        gated.gate.set()
        running.stop()
