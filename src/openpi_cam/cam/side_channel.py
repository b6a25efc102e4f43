"""The Grad-CAM side channel around a policy: decides when to explain and what to log; never changes actions.

Scheduled inferences run through `infer_traced`, which returns the very response `infer` would plus the exact model
inputs and outputs of that call. A job carrying them goes into a bounded queue; one background worker has the
policy's explainer compute the maps and hands the record to the `CAMLogger`. The response never waits for the
worker; a full queue drops the new job (counted); every failure inside the side channel is counted per kind and
logged once.
"""

from __future__ import annotations

import dataclasses
import logging
import pathlib
import queue
import threading
import time
from collections.abc import Mapping
from typing import Any, Protocol

from openpi_cam.cam.batching import explain_traces
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.records import SAVE_FRAMES, SaveFrames, bounded_extra, split_extra, step_record
from openpi_cam.counters import WarnOnceCounter
from openpi_cam.model.attribution import MapKind, MapOptions
from openpi_cam.policies.family import Explainer, ExplainRequest, ExplainSkipped, Target
from openpi_cam.policies.policy import InferenceTrace

logger = logging.getLogger(__name__)


class TracedPolicy(Protocol):
    """What the side channel wraps (`openpi_cam.policies.Policy`)."""

    @property
    def metadata(self) -> dict[str, Any]: ...

    @property
    def explainer(self) -> Explainer: ...

    def infer(self, obs: Mapping[str, Any], context: object = None) -> dict[str, Any]: ...

    def infer_traced(self, obs: Mapping[str, Any]) -> tuple[dict[str, Any], InferenceTrace]: ...

    def warm_up(self) -> InferenceTrace | None: ...

    def stats(self) -> dict[str, Any]: ...

    def close(self, timeout: float | None = None) -> None: ...


@dataclasses.dataclass(frozen=True)
class CAMOptions:
    every_k: int = 1  # explain every k-th inference of each connection (0 = off)
    cam_dir: str | pathlib.Path = "cam_runs"
    save_frames: SaveFrames = "model"
    target: Target = "action-token"
    action_index: int = 0  # pi0-FAST: which action token ("action-token"); pi0 / pi0.5: horizon step ("action")
    action_dim_index: int = 0  # pi0 / pi0.5: which action dimension ("action")
    maps: tuple[MapKind, ...] = ("gradcam", "gradnorm")  # which map kinds each explained step carries
    map_options: MapOptions = dataclasses.field(default_factory=MapOptions)  # of the "ig" / "occlusion" kinds
    queue_size: int = 8
    max_steps: int | None = None
    max_bytes: int | None = None
    drain_timeout: float = 30.0  # seconds `close()` waits for queued jobs
    # `cam_extra/` values a client may have stored per step (sizes as stored: an array's bytes, other values' JSON);
    # larger values are dropped, counted and named in the step's `extra_dropped`, so no client can make the server
    # store megabytes per request.
    max_extra_value_bytes: int = 16 * 1024
    max_extra_bytes: int = 64 * 1024

    def __post_init__(self) -> None:
        if self.every_k < 0 or self.queue_size < 1:
            raise ValueError("every_k >= 0 and queue_size >= 1 are required")
        if self.save_frames not in SAVE_FRAMES:
            raise ValueError(f"save_frames must be one of {SAVE_FRAMES}, got {self.save_frames!r}")
        self.request  # noqa: B018  (validates target, action_index and map kinds at construction)

    @property
    def request(self) -> ExplainRequest:
        return ExplainRequest(self.target, self.action_index, self.action_dim_index, tuple(self.maps), self.map_options)


@dataclasses.dataclass
class _Job:
    trace: InferenceTrace
    connection: str
    step: int
    timestamp: float
    extra: dict[str, Any]


class CAMPolicy:
    """Serves exactly what the wrapped policy serves; explains scheduled inferences in the background."""

    def __init__(self, policy: TracedPolicy, options: CAMOptions, cam_logger: CAMLogger | None):
        self._policy = policy
        self._options = options
        self._logger = cam_logger
        self._queue: queue.Queue[_Job | None] = queue.Queue(maxsize=options.queue_size)
        self._lock = threading.Lock()
        self._events = WarnOnceCounter(logger, "Grad-CAM side channel")
        self._steps: dict[str, int] = {}  # per-connection inference index
        self._closed = False
        self._closer: threading.Thread | None = None  # started by begin_close: drains, then writes the manifest
        self._deadline = 0.0
        self._worker = threading.Thread(target=self._work, name="gradcam-worker", daemon=True)
        self._worker.start()

    @property
    def metadata(self) -> dict[str, Any]:
        return self._policy.metadata

    @property
    def policy(self) -> TracedPolicy:
        return self._policy

    @property
    def run_dir(self) -> pathlib.Path | None:
        return None if self._logger is None else self._logger.run_dir

    def count(self, kind: str, message: str | None = None) -> None:
        self._events.count(kind, message)

    def infer(self, obs: dict[str, Any], context: object = None) -> dict[str, Any]:
        obs, extra = split_extra(obs)
        connection = str(getattr(context, "connection_id", "local"))
        with self._lock:
            step = self._steps.get(connection, 0)
            self._steps[connection] = step + 1
        every_k = self._options.every_k
        if self._logger is None or self._closed or every_k == 0 or step % every_k:
            return self._policy.infer(obs, context)
        response, trace = self._policy.infer_traced(obs)
        self.count("scheduled")
        if self._options.save_frames not in ("raw", "both"):
            # A queued job keeps only model-size inputs: client frames (up to the message limit each) are not held
            # while the job waits when they will not be written.
            trace = dataclasses.replace(trace, raw_images=dict.fromkeys(trace.raw_images))
        try:
            kept, dropped = bounded_extra(extra, self._options.max_extra_value_bytes, self._options.max_extra_bytes)
            if dropped:
                self.count("extra_dropped", f"cam_extra values over the size limits dropped: {dropped[:3]}")
                kept["extra_dropped"] = dropped
            job = _Job(trace, connection, step, time.time(), kept)
            with self._lock:  # a job queued behind close's end marker would be lost without a trace
                if self._closed:
                    self.count("not_queued_closing", "the side channel closed while this inference ran")
                else:
                    self._queue.put_nowait(job)
        except queue.Full:
            self.count("dropped_queue_full", "queue full, job dropped")
        except Exception as e:  # the side channel never reaches the client
            self.count(f"enqueue_error_{type(e).__name__}", f"could not queue a job: {e}")
        return response

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                self._process(job)
            except Exception as e:  # a bug in the side channel must not stop the worker (or reach a client)
                self.count(f"worker_error_{type(e).__name__}", f"the worker raised {type(e).__name__}: {e}")
            finally:
                self._queue.task_done()

    def _process(self, job: _Job) -> None:
        t0 = time.perf_counter()
        try:
            (exp,) = explain_traces(self._policy.explainer, [job.trace], self._options.request)
        except Exception as e:
            self.count(f"failed_{type(e).__name__}", f"explaining raised {type(e).__name__}: {e}")
            return
        if isinstance(exp, ExplainSkipped):
            self.count(f"skipped_{exp.kind}", str(exp))
            return
        if job.trace.malformed_reason is not None:
            self.count("explained_malformed")
        explain_ms = (time.perf_counter() - t0) * 1000.0
        try:
            record = step_record(
                job.trace,
                exp,
                connection=job.connection,
                step=job.step,
                timestamp=job.timestamp,
                save_frames=self._options.save_frames,
                extra=job.extra,
                explain_ms=explain_ms,
            )
            logged = self._logger.log_step(record)  # type: ignore[union-attr]  (no jobs without a logger)
        except Exception as e:
            self.count(f"log_error_{type(e).__name__}", f"logging a step raised {type(e).__name__}: {e}")
            return
        self.count("completed" if logged else "not_logged")

    def stats(self) -> dict[str, Any]:
        cam: dict[str, Any] = self._events.snapshot()
        cam["queued"] = self._queue.qsize()
        if self._logger is not None:
            cam["logger"] = self._logger.counters
            cam["run"] = self._logger.run_dir.name  # the name only: /stats does not reveal the server's paths
        return {**self._policy.stats(), "gradcam": cam}

    def begin_close(self, timeout: float | None = None) -> None:
        """Stops scheduling and starts the drain without waiting: queued jobs are explained until `timeout` seconds
        from now, then the final manifest is written. The server calls this as soon as it is asked to stop, so the
        drain runs while connections are still closing (a container's stop grace period is short). Idempotent."""
        with self._lock:
            if self._closer is not None:
                return
            self._closed = True  # `infer` checks it under the same lock: nothing is queued behind the end marker
            self._deadline = time.monotonic() + (self._options.drain_timeout if timeout is None else timeout)
            self._closer = threading.Thread(target=self._drain, name="gradcam-drain", daemon=True)
            self._closer.start()

    def _drain(self) -> None:
        while time.monotonic() < self._deadline:
            try:
                self._queue.put(None, timeout=max(0.0, self._deadline - time.monotonic()))
                break
            except queue.Full:
                continue
        self._worker.join(max(0.0, self._deadline - time.monotonic()))
        if self._worker.is_alive():
            self.count("unfinished_at_shutdown", "shutdown deadline passed with jobs pending")
        if self._logger is not None:
            self._logger.set_external_counters(self._events.snapshot())
            self._logger.close()

    def close(self, timeout: float | None = None) -> None:
        """Stops scheduling, drains queued jobs up to the deadline (counted from `begin_close` when that came first),
        writes the final manifest, then closes the wrapped policy."""
        self.begin_close(timeout)
        assert self._closer is not None
        self._closer.join(max(0.0, self._deadline - time.monotonic()))
        self._policy.close(max(0.0, self._deadline - time.monotonic()))

    @property
    def computing(self) -> bool:
        """Whether the worker is still running (after `close`: an explanation outlived the drain deadline)."""
        return self._worker.is_alive()

    def warm_up(self) -> str:
        """Compiles inference and, when steps are recorded, the configured explanation on the robot's example
        observation, before the server reports ready; nothing is logged or counted. Returns what was warmed."""
        trace = self._policy.warm_up()
        if trace is None:
            return "nothing (the robot transform offers no example observation)"
        if self._logger is None or self._options.every_k == 0:
            return "inference"
        (exp,) = explain_traces(self._policy.explainer, [trace], self._options.request)
        if isinstance(exp, ExplainSkipped):
            return f"inference (the example's explanation was skipped: {exp})"
        if trace.malformed_reason is not None:
            # The example's generation holds no action tokens: the fallback target was compiled, not the configured
            # one (the side channel's first well-formed request compiles that, off the robot's path).
            return f"inference and the {exp.target} explanation (the example's generation: {trace.malformed_reason})"
        return f"inference and the {exp.target} explanation"


def wrap_policy_with_cam(
    policy: TracedPolicy, options: CAMOptions, *, run_config: dict[str, Any] | None = None, checkpoint: str = ""
) -> CAMPolicy:
    """Creates the run directory and the worker. If the run directory cannot be created, the server still serves:
    the side channel is disabled and the reason logged and counted."""
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
        wrapped.count("disabled_logger_unavailable")
        return wrapped
    logger.info(
        "Grad-CAM side channel on: every %d inference(s), run directory %s", options.every_k, cam_logger.run_dir
    )
    return CAMPolicy(policy, options, cam_logger)
