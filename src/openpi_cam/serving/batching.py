"""Batched serving for a fleet: requests from several connections that arrive within a short window share one model
call (`--batch-window-ms`).

The first request of a batch waits at most `window_s` for company; a batch closes early when it is full
(`max_batch`) or when every open connection already has a request in it (nobody else could join: a lone robot never
waits for the window). While the model computes one batch the next one fills, so under load batches form without any
wait. The
policy answers each request as if it had been served alone (`BatchedPolicy.infer_batch`); a request that fails gets
its own error, the others their actions.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from openpi_cam.serving import RequestContext


class BatchedPolicy(Protocol):
    def infer_batch(
        self, observations: Sequence[dict], contexts: Sequence[RequestContext]
    ) -> list[dict | Exception]: ...


@dataclasses.dataclass
class _Request:
    obs: dict
    context: RequestContext
    future: asyncio.Future
    arrived: float


class RequestBatcher:
    """Collects requests on the event loop and runs each batch on the server's single inference thread."""

    def __init__(
        self,
        policy: BatchedPolicy,
        executor: concurrent.futures.Executor,
        *,
        window_s: float,
        max_batch: int,
        open_connections: Callable[[], int] = lambda: 0,
    ) -> None:
        if window_s < 0 or max_batch < 1:
            raise ValueError(f"window_s >= 0 and max_batch >= 1 are required, got {window_s}, {max_batch}")
        self._policy = policy
        self._executor = executor
        self._window_s = window_s
        self._max_batch = max_batch
        self._open_connections = open_connections
        self._queue: collections.deque[_Request] = collections.deque()
        self._arrived = asyncio.Event()
        self.sizes: collections.Counter[int] = collections.Counter()  # batch size -> batches run

    async def infer(self, obs: dict, context: RequestContext) -> tuple[dict, float]:
        """(this request's response, the batch's model time in ms); raises the request's own error."""
        future = asyncio.get_running_loop().create_future()
        self._queue.append(_Request(obs, context, future, time.monotonic()))
        self._arrived.set()
        return await future

    async def run(self) -> None:
        """Forms and runs batches until cancelled."""
        loop = asyncio.get_running_loop()
        while True:
            await self._wait_for_batch()
            batch = [self._queue.popleft() for _ in range(min(self._max_batch, len(self._queue)))]
            batch = [r for r in batch if not r.future.done()]  # e.g. cancelled with a closed connection
            if not batch:
                continue
            start = time.monotonic()
            try:
                results = await loop.run_in_executor(
                    self._executor, self._policy.infer_batch, [r.obs for r in batch], [r.context for r in batch]
                )
                if len(results) != len(batch):
                    raise RuntimeError(f"infer_batch returned {len(results)} results for {len(batch)} requests")
            except Exception as e:  # the whole call failed: every request in it hears why
                results = [e] * len(batch)
            infer_ms = (time.monotonic() - start) * 1000
            self.sizes[len(batch)] += 1
            for request, result in zip(batch, results, strict=True):
                if request.future.done():
                    continue
                if isinstance(result, Exception):
                    request.future.set_exception(result)
                else:
                    request.future.set_result((result, infer_ms))

    async def _wait_for_batch(self) -> None:
        """Returns once a request is queued and the batch is full, or holds a request of every open connection, or its
        oldest request has waited out the window."""
        while not self._queue:
            self._arrived.clear()
            await self._arrived.wait()
        while len(self._queue) < self._max_batch:
            if len({r.context.connection_id for r in self._queue}) >= self._open_connections():
                return
            remaining = self._queue[0].arrived + self._window_s - time.monotonic()
            if remaining <= 0:
                return
            self._arrived.clear()
            try:
                await asyncio.wait_for(self._arrived.wait(), remaining)
            except TimeoutError:
                return

    def stats(self) -> dict[str, Any]:
        batches = sum(self.sizes.values())
        rows = sum(size * n for size, n in self.sizes.items())
        return {
            "window_ms": self._window_s * 1000,
            "max_batch": self._max_batch,
            "batches": batches,
            "requests": rows,
            "mean_size": rows / batches if batches else None,
            "sizes": {str(size): n for size, n in sorted(self.sizes.items())},
        }
