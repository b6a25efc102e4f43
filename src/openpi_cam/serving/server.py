"""Websocket policy server, wire-compatible with `openpi_client.WebsocketClientPolicy`.

Protocol (as upstream's): on connect the server sends the packed metadata; then each binary frame is one packed
observation, answered by one packed response (the policy's dict plus `server_timing`). A text frame from the server
is an error message; the real client raises it as RuntimeError.

Beyond upstream: inference runs on one worker thread so the event loop keeps answering `/healthz`, `/stats`,
websocket pings and other connections while the model computes; bad requests are answered with a text frame and the
connection stays usable; an optional API key; a message size limit; graceful shutdown that lets in-flight requests
finish and then closes the policy (which drains the explanation side channel).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import dataclasses
import hmac
import http
import itertools
import json
import logging
import signal
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any, Protocol
from urllib.parse import urlsplit

import numpy as np
import websockets
import websockets.asyncio.server as ws_server

from openpi_cam.errors import InvalidRequest
from openpi_cam.serving import RequestContext, msgpack_numpy
from openpi_cam.serving.batching import RequestBatcher

logger = logging.getLogger(__name__)

DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
DEFAULT_MAX_BUFFERED_BYTES = 256 * 1024 * 1024
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
# A peer gets this long to read a reply, and to answer our close frame, before its connection is dropped: a robot that
# stopped reading must not hold the server (or its shutdown) forever. Shutdown thus ends within the in-flight request,
# plus PEER_TIMEOUT_S for the closes (all connections at once), plus the policy's drain.
PEER_TIMEOUT_S = 2.0
# Wrong API keys: the first AUTH_FREE_FAILURES per client address are answered at once, then each answer waits
# 0.2, 0.4, ... up to AUTH_MAX_DELAY_S seconds (a robot with a typo is told quickly; guessing is slowed down).
AUTH_FREE_FAILURES = 5
AUTH_MAX_DELAY_S = 5.0
_MAX_ERROR_TEXT = 2000  # characters of an unexpected exception's message sent to the client without debug


class ServedPolicy(Protocol):
    def infer(self, obs: dict, context: RequestContext | None = None) -> dict: ...


@dataclasses.dataclass
class _Connection:
    id: str
    websocket: ws_server.ServerConnection
    busy: bool = False


class ServerStats:
    """Counters and a bounded latency window; touched only from the event loop thread."""

    def __init__(self, window: int) -> None:
        self.started = time.monotonic()
        self.requests = 0
        self.ok = 0
        self.errors: collections.Counter[str] = collections.Counter()
        self.connections_total = 0
        self.infer_ms: collections.deque[float] = collections.deque(maxlen=window)
        self.total_ms: collections.deque[float] = collections.deque(maxlen=window)

    def record_ok(self, infer_ms: float, total_ms: float) -> None:
        """An answered request: its inference time and its time from arrival to the reply sent."""
        self.ok += 1
        self.infer_ms.append(infer_ms)
        self.total_ms.append(total_ms)

    @staticmethod
    def _percentiles(values: collections.deque[float]) -> dict[str, float] | None:
        if not values:
            return None
        p50, p90, p99 = np.percentile(np.fromiter(values, float), [50, 90, 99])
        return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "max": float(max(values))}

    def snapshot(self, open_connections: int) -> dict[str, Any]:
        return {
            "uptime_s": time.monotonic() - self.started,
            "connections": {"open": open_connections, "total": self.connections_total},
            "requests": self.requests,
            "ok": self.ok,
            "errors": dict(self.errors),
            "latency_ms": {
                "window": len(self.infer_ms),
                "infer": self._percentiles(self.infer_ms),
                "total": self._percentiles(self.total_ms),
            },
        }


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic | np.ndarray):
        return obj.tolist()
    return str(obj)


class PolicyServer:
    """Serves `policy` over websockets; see the module docstring for the protocol.

    `policy` needs `infer(obs, context)`, and `infer_batch(observations, contexts)` with `batch_window_ms` (requests
    from all connections arriving within that many ms share one call of up to `max_batch`: `serving.batching`).
    `stats()` (merged into `/stats`), `begin_close(timeout)` (called as soon as a stop is requested, must not block),
    `close(timeout)` (called once in-flight requests are answered) and `connection_closed(connection_id)` (called when
    a connection ends, after its last answer; must not block) are used when present. Both closes get `drain_timeout`:
    the seconds the policy may drain from the stop request (None: until it is done).
    """

    def __init__(
        self,
        policy: ServedPolicy,
        *,
        host: str = "0.0.0.0",
        port: int = 8000,
        metadata: dict | None = None,
        api_key: str | None = None,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        debug: bool = False,
        latency_window: int = 1000,
        close_policy_on_stop: bool = True,
        drain_timeout: float | None = None,
        max_connections: int = 64,
        max_buffered_bytes: int = DEFAULT_MAX_BUFFERED_BYTES,
        batch_window_ms: float | None = None,
        max_batch: int = 8,
    ) -> None:
        if max_message_bytes <= 0 or max_connections < 1 or max_buffered_bytes < max_message_bytes:
            raise ValueError(
                "max_message_bytes and max_connections must be positive and max_buffered_bytes >= max_message_bytes, "
                f"got {max_message_bytes}, {max_connections}, {max_buffered_bytes}"
            )
        if drain_timeout is not None and drain_timeout < 0:
            raise ValueError(f"drain_timeout must be >= 0, got {drain_timeout}")
        if batch_window_ms is not None and not callable(getattr(policy, "infer_batch", None)):
            raise ValueError(f"batched serving needs a policy with infer_batch; {type(policy).__name__} has none")
        if batch_window_ms is not None and (batch_window_ms < 0 or max_batch < 1):
            raise ValueError(
                f"batch_window_ms >= 0 and max_batch >= 1 are required, got {batch_window_ms}, {max_batch}"
            )
        self._policy = policy
        self._batch_window_ms = batch_window_ms
        self._max_batch = max_batch
        self._batcher: RequestBatcher | None = None
        self._host = host
        self._port = port
        self._metadata_frame = msgpack_numpy.packb(metadata or {})  # fails here, not per connection
        self._api_key = api_key
        self._max_message_bytes = max_message_bytes
        self._debug = debug
        self._close_policy_on_stop = close_policy_on_stop
        self._drain_timeout = drain_timeout
        # Each connection may hold one queued frame of up to max_message_bytes: this caps what clients can make the
        # server buffer at max_connections x max_message_bytes.
        self._max_connections = max_connections
        # Request frames being decoded, waiting for the model or computing, all connections together: a frame that
        # would take the total past this is refused (its connection closed with 1013), whatever the connection count.
        self._max_buffered_bytes = max_buffered_bytes
        self._buffered_bytes = 0
        self._auth_failures: dict[str, int] = {}  # client address -> wrong API keys so far
        self._stats = ServerStats(latency_window)
        self._connections: dict[str, _Connection] = {}
        self._connection_ids = itertools.count()
        self._stopping = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self.bound_port: int | None = None

    # ---------------------------------------------------------------- lifecycle

    def serve_forever(self) -> None:
        """Runs until SIGINT or SIGTERM, then shuts down gracefully."""

        async def main() -> None:
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, self.request_stop)
            await self.run(on_ready=lambda port: logger.info("serving on ws://%s:%d", self._host, port))

        asyncio.run(main())

    def request_stop(self) -> None:
        """Asks a running server to shut down; safe to call from any thread."""
        if self._loop is not None and self._stop_event is not None:
            self._loop.call_soon_threadsafe(self._stop_event.set)

    async def run(self, on_ready: Callable[[int], None] | None = None) -> None:
        """Serves until `request_stop()`; then stops accepting, finishes in-flight requests and closes the policy."""
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        if self._api_key is None and self._host not in LOOPBACK_HOSTS:
            logger.warning(
                "listening on %s without an API key: anyone who can reach this port can send observations and read "
                "/stats (pass --api-key, or --host 127.0.0.1 to serve this machine only)",
                self._host,
            )
        executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="policy-infer")
        batching: asyncio.Task | None = None
        if self._batch_window_ms is not None:
            self._batcher = RequestBatcher(
                self._policy,  # type: ignore[arg-type]  (checked in __init__)
                executor,
                window_s=self._batch_window_ms / 1000,
                max_batch=self._max_batch,
                open_connections=lambda: len(self._connections),
            )
            batching = asyncio.create_task(self._batcher.run())
        try:
            async with ws_server.serve(
                lambda ws: self._handle(ws, executor),
                self._host,
                self._port,
                compression=None,
                max_size=self._max_message_bytes,
                # A robot sends one request and waits for the answer: one queued frame per connection bounds what a
                # connection can make the server hold to about one message (websockets' default queues 16).
                max_queue=1,
                close_timeout=PEER_TIMEOUT_S,
                process_request=self._process_request,
            ) as server:
                self.bound_port = server.sockets[0].getsockname()[1]
                if on_ready is not None:
                    on_ready(self.bound_port)
                await self._stop_event.wait()
                begin_close = getattr(self._policy, "begin_close", None)
                if self._close_policy_on_stop and callable(begin_close):
                    # The drain (e.g. the side channel's queued explanations) starts now and runs while connections
                    # close; `close` below waits for it within the same deadline.
                    begin_close(self._drain_timeout)
                await self._shutdown(server)
        finally:
            if batching is not None:
                batching.cancel()  # every connection has been answered and closed by now
            executor.shutdown(wait=True)
        close = getattr(self._policy, "close", None)
        if self._close_policy_on_stop and callable(close):
            logger.info("closing the policy (drain timeout %s s)", self._drain_timeout)
            await asyncio.to_thread(close, self._drain_timeout)

    async def _shutdown(self, server: ws_server.Server) -> None:
        logger.info("shutting down: no new connections; finishing %d open", len(self._connections))
        self._stopping = True
        server.close(close_connections=False)
        # Idle connections close now, all at once (each waits at most PEER_TIMEOUT_S for the peer's answer); busy ones
        # close themselves once their response is sent.
        idle = [conn.websocket for conn in self._connections.values() if not conn.busy]
        await asyncio.gather(*(ws.close(websockets.CloseCode.GOING_AWAY, "server shutting down") for ws in idle))
        await server.wait_closed()

    # ---------------------------------------------------------------- HTTP side

    def _authorized(self, request: ws_server.Request) -> bool:
        if self._api_key is None:
            return True
        expected = f"Api-Key {self._api_key}"
        return hmac.compare_digest(request.headers.get("Authorization", "").encode(), expected.encode())

    async def _process_request(
        self, connection: ws_server.ServerConnection, request: ws_server.Request
    ) -> ws_server.Response | None:
        path = urlsplit(request.path).path
        if path == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        if not self._authorized(request):
            self._stats.errors["unauthorized"] += 1
            host = str(connection.remote_address[0]) if connection.remote_address else "?"
            if len(self._auth_failures) >= 10_000 and host not in self._auth_failures:
                self._auth_failures.clear()  # bounded memory whatever the number of addresses
            failures = self._auth_failures[host] = self._auth_failures.get(host, 0) + 1
            if failures <= AUTH_FREE_FAILURES or failures & (failures - 1) == 0:  # then once per doubling
                logger.warning("refused %s from %s: missing or wrong API key (%d times)", path, host, failures)
            # Back-off per client address: guessing keys gets slower with every miss (the answer, not the server).
            if failures > AUTH_FREE_FAILURES:
                await asyncio.sleep(min(AUTH_MAX_DELAY_S, 0.1 * 2 ** (failures - AUTH_FREE_FAILURES)))
            return connection.respond(
                http.HTTPStatus.UNAUTHORIZED,
                "missing or wrong API key: send the header 'Authorization: Api-Key <key>'\n",
            )
        if path == "/stats":
            response = connection.respond(http.HTTPStatus.OK, json.dumps(await self.stats(), default=_json_default))
            response.headers["Content-Type"] = "application/json"
            return response
        return None

    async def stats(self) -> dict[str, Any]:
        """The `/stats` document: server counters plus `policy.stats()` under "policy"."""
        snapshot = self._stats.snapshot(len(self._connections))
        if self._batcher is not None:
            snapshot["batching"] = self._batcher.stats()
        policy_stats = getattr(self._policy, "stats", None)
        if callable(policy_stats):
            try:
                snapshot["policy"] = await asyncio.to_thread(policy_stats)
            except Exception as e:  # a broken stats() must not take /stats down
                logger.exception("policy.stats() failed")
                snapshot["policy"] = {"error": f"{type(e).__name__}: {e}"}
        return snapshot

    # ---------------------------------------------------------------- websocket side

    async def _handle(self, websocket: ws_server.ServerConnection, executor: concurrent.futures.Executor) -> None:
        """One connection from its opening to its close."""
        conn = await self._admit(websocket)
        if conn is None:
            return
        try:
            await websocket.send(self._metadata_frame)
            await self._serve_requests(conn, executor)
        except websockets.ConnectionClosed as e:
            if e.sent is not None and e.sent.code == websockets.CloseCode.MESSAGE_TOO_BIG:
                self._stats.errors["too_large"] += 1
                logger.warning("%s closed: message over %d bytes", conn.id, self._max_message_bytes)
        finally:
            del self._connections[conn.id]
            logger.info("%s closed", conn.id)
            closed = getattr(self._policy, "connection_closed", None)
            if callable(closed):
                try:
                    closed(conn.id)
                except Exception:  # a broken hook must not take the connection handling down
                    logger.exception("policy.connection_closed(%s) failed", conn.id)

    async def _admit(self, websocket: ws_server.ServerConnection) -> _Connection | None:
        """Registers a new connection, or closes it (None) when `max_connections` are open."""
        if len(self._connections) >= self._max_connections:
            self._stats.errors["too_many_connections"] += 1
            logger.warning("refused a connection from %s: %d open", websocket.remote_address, len(self._connections))
            await websocket.close(websockets.CloseCode.TRY_AGAIN_LATER, "too many connections")
            return None
        conn = _Connection(id=f"conn{next(self._connection_ids):04d}", websocket=websocket)
        self._connections[conn.id] = conn
        self._stats.connections_total += 1
        logger.info("%s opened from %s", conn.id, websocket.remote_address)
        return conn

    async def _serve_requests(self, conn: _Connection, executor: concurrent.futures.Executor) -> None:
        """Answers a connection's requests one at a time until it closes, stops reading or the server stops."""
        prev_total_ms: float | None = None
        for request_index in itertools.count():
            # Upstream starts its per-request clock before waiting for the frame, so `prev_total_ms` includes the
            # wait for the request; kept for compatibility. /stats measures from the frame's arrival.
            wait_start = time.monotonic()
            frame = await conn.websocket.recv()
            start = time.monotonic()
            if not await self._has_room(conn, len(frame)):
                break
            conn.busy = True
            self._stats.requests += 1
            reply, infer_ms = await self._answer_buffered(
                frame, RequestContext(conn.id, request_index), prev_total_ms, executor
            )
            del frame  # not held while the reply is sent
            if not await self._send_reply(conn, reply):
                break
            if infer_ms is not None:
                end = time.monotonic()
                prev_total_ms = (end - wait_start) * 1000
                self._stats.record_ok(infer_ms, (end - start) * 1000)
            if self._stopping:
                await conn.websocket.close(websockets.CloseCode.GOING_AWAY, "server shutting down")
                break

    async def _has_room(self, conn: _Connection, size: int) -> bool:
        """Whether a request of `size` bytes fits under `max_buffered_bytes`; if not, its connection is closed."""
        if self._buffered_bytes + size <= self._max_buffered_bytes:
            return True
        self._stats.errors["server_busy"] += 1
        logger.warning(
            "%s closed: %d bytes of requests in progress, %d more would pass --max-buffered-mb",
            conn.id, self._buffered_bytes, size,
        )  # fmt: skip
        await conn.websocket.close(websockets.CloseCode.TRY_AGAIN_LATER, "server busy: too many bytes queued")
        return False

    async def _answer_buffered(
        self,
        frame: bytes | str,
        context: RequestContext,
        prev_total_ms: float | None,
        executor: concurrent.futures.Executor,
    ) -> tuple[bytes | str, float | None]:
        """`_answer`, with the frame counted in the bytes in progress meanwhile."""
        self._buffered_bytes += len(frame)
        try:
            return await self._answer(frame, context, prev_total_ms, executor)
        finally:
            self._buffered_bytes -= len(frame)

    async def _send_reply(self, conn: _Connection, reply: bytes | str) -> bool:
        """Sends a reply; a peer that does not read it within PEER_TIMEOUT_S is dropped (False)."""
        try:
            await asyncio.wait_for(conn.websocket.send(reply), PEER_TIMEOUT_S)
            return True
        except TimeoutError:
            self._stats.errors["send_timeout"] += 1
            logger.warning("%s dropped: reply not read within %.0f s", conn.id, PEER_TIMEOUT_S)
            conn.websocket.transport.abort()
            return False
        finally:
            conn.busy = False

    async def _answer(
        self,
        frame: bytes | str,
        context: RequestContext,
        prev_total_ms: float | None,
        executor: concurrent.futures.Executor,
    ) -> tuple[bytes | str, float | None]:
        """Returns (packed response, infer_ms) on success, (error text, None) otherwise."""
        stage = "decode"
        try:
            if isinstance(frame, str):
                stage = "text_frame"
                raise InvalidRequest("expected a binary msgpack frame, got a text frame")
            # Off the event loop: a large frame must not stall /healthz and the other connections while it decodes.
            obs = await asyncio.to_thread(msgpack_numpy.unpack_request, frame)
            stage = "invalid_request"
            if self._batcher is not None:
                result, infer_ms = await self._batcher.infer(obs, context)
            else:
                loop = asyncio.get_running_loop()
                result, infer_ms = await loop.run_in_executor(executor, self._infer, obs, context)
            stage = "internal"
            if not isinstance(result, dict):
                raise TypeError(f"policy returned {type(result).__name__}, expected a dict")
            timing = {"infer_ms": infer_ms}
            if prev_total_ms is not None:
                # Like upstream: only the previous request's total is known here (it includes sending the response).
                timing["prev_total_ms"] = prev_total_ms
            return msgpack_numpy.packb({**result, "server_timing": timing}), infer_ms
        except InvalidRequest as e:
            self._stats.errors[stage] += 1
            text = str(e)[:_MAX_ERROR_TEXT]  # messages quote short prefixes; this bounds whatever else they hold
            logger.info("%s request %d rejected: %s", context.connection_id, context.request_index, text)
            return f"InvalidRequest: {text}", None
        except Exception as e:
            self._stats.errors["internal"] += 1
            logger.exception("%s request %d failed", context.connection_id, context.request_index)
            text = f"Internal server error: {type(e).__name__}: {e}"[:_MAX_ERROR_TEXT]
            if self._debug:
                return f"{text}\n\n{traceback.format_exc()}", None
            return f"{text} (details in the server log)", None

    def _infer(self, obs: dict, context: RequestContext) -> tuple[dict, float]:
        start = time.monotonic()
        result = self._policy.infer(obs, context)
        return result, (time.monotonic() - start) * 1000


@dataclasses.dataclass
class RunningServer:
    """A `PolicyServer` running on its own thread and event loop (tests, the demo)."""

    server: PolicyServer
    host: str
    port: int
    thread: threading.Thread

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def stop(self, timeout: float = 60.0) -> None:
        self.server.request_stop()
        self.thread.join(timeout)
        if self.thread.is_alive():
            raise TimeoutError(f"server on port {self.port} did not stop within {timeout}s")


def start_server_in_thread(
    policy: ServedPolicy, host: str = "127.0.0.1", port: int = 0, startup_timeout: float = 30.0, **kwargs: Any
) -> RunningServer:
    """Starts a `PolicyServer` (kwargs as its constructor's) on a daemon thread; port 0 lets the OS pick one."""
    server = PolicyServer(policy, host=host, port=port, **kwargs)
    ready = threading.Event()
    failure: list[BaseException] = []

    def target() -> None:
        try:
            asyncio.run(server.run(on_ready=lambda _: ready.set()))
        except BaseException as e:
            failure.append(e)
            logger.exception("policy server thread failed")
        finally:
            ready.set()

    thread = threading.Thread(target=target, name=f"policy-server-{port}", daemon=True)
    thread.start()
    if not ready.wait(startup_timeout):
        raise TimeoutError(f"policy server did not start within {startup_timeout}s")
    if failure or server.bound_port is None:
        raise RuntimeError(f"policy server failed to start on {host}:{port}") from (failure[0] if failure else None)
    return RunningServer(server=server, host=host, port=server.bound_port, thread=thread)
