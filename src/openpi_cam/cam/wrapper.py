"""The Grad-CAM side channel around a `Policy`: decides when to explain and what to log; never changes actions.

Scheduled inferences run through `Policy.infer_traced`, which returns the very response `infer` would plus the exact
model inputs and generated tokens of that call. A job carrying them goes into a bounded queue; one background worker
computes Grad-CAM and hands the result to the `CAMLogger`. The response never waits for the worker; a full queue
drops the new job (counted); every failure inside the side channel is counted per kind and logged once.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import pathlib
import queue
import threading
import time
from typing import Any, Literal

from openpi_cam.cam.engine import TARGETS, CamSkipped, explain
from openpi_cam.cam.records import SaveFrames, jsonable, split_extra, step_record

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class CAMOptions:
    every_k: int = 1  # explain every k-th inference of each connection (0 = off)
    cam_dir: str | pathlib.Path = "cam_runs"
    save_frames: SaveFrames = "model"
    target: Literal["action-token", "all-action-tokens", "chunk"] = "action-token"
    action_index: int = 0  # which FAST action token, for target "action-token"
    queue_size: int = 8
    max_steps: int | None = None
    max_bytes: int | None = None
    drain_timeout: float = 30.0  # seconds `close()` waits for queued jobs

    def __post_init__(self):
        if self.every_k < 0 or self.queue_size < 1 or self.action_index < 0:
            raise ValueError("every_k >= 0, queue_size >= 1 and action_index >= 0 are required")
        if self.target not in TARGETS:
            raise ValueError(f"unknown Grad-CAM target {self.target!r}; expected one of {TARGETS}")
        if self.save_frames not in ("none", "raw", "model", "both"):
            raise ValueError(f"save_frames must be none|raw|model|both, got {self.save_frames!r}")


@dataclasses.dataclass
class _Job:
    trace: Any
    connection: str
    step: int
    timestamp: float
    extra: dict[str, Any]


class CAMPolicy:
    """Serves exactly what the wrapped policy serves; explains scheduled inferences in the background."""

    def __init__(self, policy: Any, options: CAMOptions, cam_logger: Any):
        self._policy = policy
        self._options = options
        self._logger = cam_logger
        self._queue: queue.Queue[_Job | None] = queue.Queue(maxsize=options.queue_size)
        self._lock = threading.Lock()
        self._counters: collections.Counter[str] = collections.Counter()
        self._steps: collections.Counter[str] = collections.Counter()  # per-connection inference index
        self._warned: set[str] = set()
        self._closed = False
        self._worker = threading.Thread(target=self._work, name="gradcam-worker", daemon=True)
        self._worker.start()

    @property
    def metadata(self) -> dict[str, Any]:
        return self._policy.metadata

    @property
    def policy(self) -> Any:
        return self._policy

    @property
    def run_dir(self) -> pathlib.Path | None:
        return None if self._logger is None else self._logger.run_dir

    def _count(self, kind: str, message: str | None = None) -> None:
        with self._lock:
            self._counters[kind] += 1
            first = kind not in self._warned
            self._warned.add(kind)
        if message is not None and first:
            logger.warning("Grad-CAM side channel: %s (%s); further occurrences are only counted", message, kind)

    def infer(self, obs: dict[str, Any], context: Any = None) -> dict[str, Any]:
        obs, extra = split_extra(obs)
        connection = getattr(context, "connection_id", "local")
        with self._lock:
            step = self._steps[connection]
            self._steps[connection] += 1
        every_k = self._options.every_k
        if self._logger is None or self._closed or every_k == 0 or step % every_k:
            return self._policy.infer(obs, context)
        response, trace = self._policy.infer_traced(obs)
        self._count("scheduled")
        try:
            job = _Job(trace, connection, step, time.time(), {k: jsonable(v) for k, v in extra.items()})
            self._queue.put_nowait(job)
        except queue.Full:
            self._count("dropped_queue_full", "queue full, job dropped")
        except Exception as e:  # the side channel never reaches the client
            self._count(f"enqueue_error_{type(e).__name__}", f"could not queue a job: {e}")
        return response

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                self._process(job)
            except Exception as e:  # a bug in the side channel must not stop the worker (or reach a client)
                self._count(f"worker_error_{type(e).__name__}", f"side-channel worker raised {type(e).__name__}: {e}")
            finally:
                self._queue.task_done()

    def _process(self, job: _Job) -> None:
        t0 = time.perf_counter()
        try:
            trace = job.trace
            exp = explain(
                self._policy.model,
                self._policy.tokenizer,
                trace.observation,
                trace.generated_tokens,
                target=self._options.target,
                action_index=self._options.action_index,
            )
        except CamSkipped as e:
            self._count(f"skipped_{e.kind}", str(e))
            return
        except Exception as e:
            self._count(f"failed_{type(e).__name__}", f"Grad-CAM raised {type(e).__name__}: {e}")
            return
        gradcam_s = time.perf_counter() - t0
        try:
            record = step_record(
                trace,
                exp,
                connection=job.connection,
                step=job.step,
                timestamp=job.timestamp,
                save_frames=self._options.save_frames,
                extra=job.extra,
                gradcam_ms=gradcam_s * 1000.0,
            )
            logged = self._logger.log_step(record)
        except Exception as e:
            self._count(f"log_error_{type(e).__name__}", f"logging a step raised {type(e).__name__}: {e}")
            return
        self._count("completed" if logged else "not_logged")

    def stats(self) -> dict[str, Any]:
        base = self._policy.stats() if hasattr(self._policy, "stats") else {}
        with self._lock:
            cam = dict(self._counters)
        cam["queued"] = self._queue.qsize()
        if self._logger is not None:
            cam["logger"] = self._logger.counters
            cam["run_dir"] = str(self._logger.run_dir)
        return {**base, "gradcam": cam}

    def close(self, timeout: float | None = None) -> None:
        """Stops scheduling, drains queued jobs up to the deadline, writes the final manifest."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + (self._options.drain_timeout if timeout is None else timeout)
        while time.monotonic() < deadline:
            try:
                self._queue.put(None, timeout=max(0.0, deadline - time.monotonic()))
                break
            except queue.Full:
                continue
        self._worker.join(max(0.0, deadline - time.monotonic()))
        if self._worker.is_alive():
            self._count("unfinished_at_shutdown", "shutdown deadline passed with jobs pending")
        if self._logger is not None:
            with self._lock:
                counters = dict(self._counters)
            self._logger.set_external_counters(counters)
            self._logger.close()
        if hasattr(self._policy, "close"):
            self._policy.close(timeout)


def wrap_policy_with_cam(
    policy: Any, options: CAMOptions, *, run_config: dict[str, Any] | None = None, checkpoint: str = ""
) -> CAMPolicy:
    """Creates the run directory and the worker. If the run directory cannot be created, the server still serves:
    the side channel is disabled and the reason logged and counted."""
    from openpi_cam.cam.logger import CAMLogger

    try:
        cam_logger = CAMLogger(
            options.cam_dir,
            run_config=run_config or {},
            checkpoint=str(checkpoint),
            options={k: str(v) if isinstance(v, pathlib.Path) else v for k, v in dataclasses.asdict(options).items()},
            max_steps=options.max_steps,
            max_bytes=options.max_bytes,
        )
    except OSError as e:
        logger.error("Grad-CAM side channel disabled: cannot create a run directory under %s: %s", options.cam_dir, e)
        wrapped = CAMPolicy(policy, options, None)
        wrapped._count("disabled_logger_unavailable")
        return wrapped
    logger.info(
        "Grad-CAM side channel on: every %d inference(s), run directory %s", options.every_k, cam_logger.run_dir
    )
    return CAMPolicy(policy, options, cam_logger)
