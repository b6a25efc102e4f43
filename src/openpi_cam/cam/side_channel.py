"""The explanation side channel around a policy: decides when to explain and what to log; never changes actions.

Scheduled inferences run through `infer_traced`, which returns the very response `infer` would plus the exact model
inputs and outputs of that call. A job carrying them becomes pending; one background worker has the policy's explainer
compute the maps and hands the record to the `CAMLogger`. The response never waits for the worker; every failure
inside the side channel is counted under its own key and logged once.

The robot must not feel the side channel, so the worker yields to inference: `infer` brackets every inference
(scheduled or not), and the worker starts an explanation, and later the writing of its step, only while no inference
is in flight and none has ended within `settle_ms` (the reply is still being sent then): a condition variable, woken
when the last inference ends, with the settle time as its only timeout. An explanation is one compiled JAX call and
cannot be pre-empted: an inference that arrives while one runs shares the CPU with it until it ends. A server that
infers without such pauses therefore explains nothing until it pauses (`oldest_pending_ms` in `/stats` shows it). A
batched call (`infer_batch`, for a fleet) is one inference in flight; each of its scheduled rows is its own job.

Overload is shared fairly across connections (`_Pending`):
- at most `queue_size` jobs are pending in all: a job arriving at the cap removes the oldest pending job of the
  connection that then holds the most (the arriving job counts; ties: the connection whose oldest job is oldest;
  counted `dropped_queue_full`), so a flooding connection loses its own jobs, never a quieter connection's;
- optionally (`per_connection`, default no limit) each connection keeps at most that many pending jobs: a newer job
  from the same connection replaces its oldest pending one (counted `superseded`), so its maps stay current;
- the worker serves oldest-first across connections (the pending job whose inference ended first), which is FIFO
  within a connection and bounds any job's wait by the jobs pending ahead of it.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import pathlib
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Protocol

import jax
import numpy as np
import tyro
from jax.sharding import Mesh

from openpi_cam.cam.batching import explain_batch
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.monitoring import RESPONSE_KEY, LiveMonitor, response_entry
from openpi_cam.cam.records import bounded_extra, split_extra, step_record
from openpi_cam.cam.reliance import Resampler
from openpi_cam.cam.run_format import StepRecord
from openpi_cam.cam.sample_spread import Resampling, with_sample_spread
from openpi_cam.counters import WarnOnceCounter
from openpi_cam.model.sharding import BATCH_AXIS
from openpi_cam.monitor.stream import StepScore
from openpi_cam.policies.family import Explainer, ExplainSkipped, resolve_target
from openpi_cam.policies.policy import InferenceTrace
from openpi_cam.vocabulary import SAVE_FRAMES, ExplainOptions, SaveFrames

logger = logging.getLogger(__name__)


class TracedPolicy(Resampler, Resampling, Protocol):
    """What the side channel wraps (`openpi_cam.policies.Policy`); re-running it (`Resampler`) only for reliance,
    drawing other samples of a call (`Resampling`) only for a monitor that reads the sample spread."""

    @property
    def metadata(self) -> dict[str, Any]: ...

    @property
    def explainer(self) -> Explainer: ...

    def infer(self, obs: Mapping[str, Any], context: object = None) -> dict[str, Any]: ...

    def infer_traced(
        self, obs: Mapping[str, Any], *, signals: bool = False
    ) -> tuple[dict[str, Any], InferenceTrace]: ...

    def infer_batch_traced(
        self, observations: Sequence[Mapping[str, Any]], *, signals: bool = False
    ) -> list[tuple[dict[str, Any], InferenceTrace] | Exception]: ...

    def warm_up(self, batch_sizes: Sequence[int] = (1,), *, signals: bool = False) -> InferenceTrace | None: ...

    def stats(self) -> dict[str, Any]: ...

    def close(self, timeout: float | None = None) -> None: ...


# How long `close` waits past the drain deadline for the final manifest, which the drain writes after it stops waiting
# for the worker (a few milliseconds of disk I/O; the bound only guards against a stalled disk).
MANIFEST_WRITE_S = 5.0


MiB, KiB = 1024 * 1024, 1024


@dataclasses.dataclass(frozen=True)
class SideChannelSettings:
    """When the side channel explains, where its run goes and how its queue makes room: what `CAMOptions` adds to the
    explanation options. `openpi-cam serve` offers each field as the flag `--cam.<field>` (`cli.serve`), with its name,
    unit, default and the comment above it as its help."""

    # explain every k-th inference of each connection (usually an episode); 0: off. `--cam-every-k` is the spelling of
    # earlier releases.
    every_k: Annotated[int, tyro.conf.arg(aliases=("--cam-every-k",))] = 0
    # a new run directory per wrapped policy (per server start) goes under this folder (an earlier run is never
    # overwritten).
    dir: pathlib.Path = pathlib.Path("cam_runs")
    # which camera frames are stored next to the maps (`model` is what `openpi-cam faithfulness` needs; `raw` and
    # `both` keep the run re-explainable by `openpi-cam explain`).
    save_frames: SaveFrames = "model"
    # pending jobs in all; at the cap the oldest job of the connection holding the most is dropped (module docstring).
    queue_size: int = 8
    # pending jobs per connection at most (a newer one supersedes that connection's oldest; e.g. 1: only the newest
    # waits); default: no such limit, the fair drop at the queue's cap applies.
    per_connection: int | None = None
    # jobs whose timings are kept; `/stats` lag percentiles are over these.
    stats_window: int = 1000
    # the worker starts an explanation only this long after the last inference ended: its reply is still being packed
    # and sent, and the robot would feel an explanation competing with it.
    settle_ms: float = 10.0
    # explain on this device (an index into `jax.devices()`, e.g. 1 for a second GPU), which holds a copy of the
    # parameters; explanations then run while the served model infers. Default: share the served model's device,
    # explaining only in its pauses.
    device: int | None = None
    # stop recording after this many steps; default: no limit.
    max_steps: int | None = None
    # stop recording once the run directory holds this many MiB; default: no limit.
    max_mb: float | None = None
    # largest `cam_extra/` value a step stores, in KiB as stored (an array's bytes, other values' JSON); larger ones
    # are dropped, counted and named in the step's `extra_dropped`, so no client can make the server store megabytes
    # per request.
    max_extra_value_kb: float = 16.0
    # all `cam_extra/` values a step stores together, in KiB.
    max_extra_kb: float = 64.0
    # with a failure monitor (`--monitor`), every response also carries `monitor: {score, flag}`, its call's score and
    # whether its connection is flagged so far, scored before the response is sent; off, the worker scores each call
    # after its response and responses are upstream's to the byte.
    monitor_response: bool = False
    # stream each explained step (frames, maps, the chunk, the monitor's score) to the Rerun viewer at this address
    # as it is written, e.g. rerun+http://127.0.0.1:9876/proxy (`rerun --serve-grpc`); a viewer that is not there or
    # goes away is logged once and stops the stream, never serving or the run. Default: no stream.
    rerun: str | None = None

    def __post_init__(self) -> None:
        if self.every_k < 0 or self.queue_size < 1 or self.stats_window < 1 or self.settle_ms < 0:
            raise ValueError("every_k >= 0, queue_size >= 1, stats_window >= 1 and settle_ms >= 0 are required")
        if self.device is not None and self.device < 0:
            raise ValueError(f"device must be an index into jax.devices() (>= 0), got {self.device}")
        if self.per_connection is not None and self.per_connection < 1:
            raise ValueError(f"per_connection must be >= 1 or None, got {self.per_connection}")
        if self.save_frames not in SAVE_FRAMES:
            raise ValueError(f"save_frames must be one of {SAVE_FRAMES}, got {self.save_frames!r}")

    def settings(self) -> dict[str, Any]:
        """These settings by field name (what a subclass passes on to `CAMOptions`)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(SideChannelSettings)}


class StepWatcher(Protocol):
    """Sees each step as the worker writes it (`--cam.rerun`'s stream); its own failures stay its own."""

    def watch(self, record: StepRecord, trace: InferenceTrace) -> None: ...

    def close(self) -> None: ...


@dataclasses.dataclass(frozen=True)
class CAMOptions(SideChannelSettings, ExplainOptions):
    """The side channel's options: the explanation options of every explained step, plus its own settings
    (`SideChannelSettings`). A `target` of None is the wrapped policy's family's default, resolved when the side
    channel wraps it."""

    def __post_init__(self) -> None:
        ExplainOptions.__post_init__(self)
        SideChannelSettings.__post_init__(self)

    def to_json(self) -> dict[str, Any]:
        """The explanation options as every run records them, then the side channel's own settings."""
        return {**super().to_json(), **self.settings(), "dir": str(self.dir)}


@dataclasses.dataclass
class _Job:
    trace: InferenceTrace
    connection: str
    step: int
    timestamp: float  # wall clock, for the step record
    extra: dict[str, Any]
    ended: float  # time.monotonic() when the inference returned: lag and ages are measured from here
    monitor: _MonitorSlot | None = None  # the call's monitor score, with a monitor


@dataclasses.dataclass
class _MonitorSlot:
    """Where a scheduled call's monitor score lands for its step file; the worker scores every call before it
    explains any job queued after it, so the slot is filled when the job is explained."""

    scored: StepScore | None = None


@dataclasses.dataclass(frozen=True)
class _Scoring:
    """A served call for the worker to score (`slot`: its explanation job's, when it is explained)."""

    connection: str
    trace: InferenceTrace
    slot: _MonitorSlot | None


@dataclasses.dataclass(frozen=True)
class _Closed:
    """A connection ended, in its place among the calls to score."""

    connection: str


@dataclasses.dataclass(frozen=True)
class JobTiming:
    """When the worker handled one job, on the `time.monotonic()` clock. `writing` and `written` are None when the job
    ended before its step was written (skipped, failed)."""

    connection: str
    step: int
    inference_end: float
    started: float  # the explanation began (no inference was in flight)
    explained: float
    writing: float | None = None  # the step's record and write began (no inference was in flight)
    written: float | None = None

    @property
    def lag_ms(self) -> float | None:
        """From the inference's end to the step being written."""
        return None if self.written is None else (self.written - self.inference_end) * 1000.0


class _Pending:
    """The pending jobs, per connection, under the fair rule of the module docstring. Not thread-safe: `CAMPolicy`
    holds its lock around every call."""

    def __init__(self, cap: int, per_connection: int | None) -> None:
        self._cap = cap
        self._per_connection = per_connection
        self._by_connection: dict[str, collections.deque[_Job]] = {}  # oldest first; no empty deques kept
        self.size = 0

    def add(self, job: _Job) -> tuple[int, int]:
        """Adds `job`; returns (superseded, dropped): how many older jobs left to make room, by reason."""
        mine = self._by_connection.setdefault(job.connection, collections.deque())
        superseded = 0
        if self._per_connection is not None and len(mine) >= self._per_connection:
            mine.popleft()
            self.size -= 1
            superseded = 1
        mine.append(job)
        self.size += 1
        dropped = 0
        while self.size > self._cap:
            # The new job counts toward its own connection: a flooder at a tie pays for its own surplus.
            busiest = max(self._by_connection.values(), key=lambda q: (len(q), -q[0].ended))
            self._pop(busiest)
            dropped += 1
        return superseded, dropped

    def pop_oldest(self) -> _Job:
        return self._pop(min(self._by_connection.values(), key=lambda q: q[0].ended))

    def oldest_end(self) -> float | None:
        return min((q[0].ended for q in self._by_connection.values()), default=None)

    def _pop(self, jobs: collections.deque[_Job]) -> _Job:
        job = jobs.popleft()
        self.size -= 1
        if not jobs:
            del self._by_connection[job.connection]
        return job


class CAMPolicy:
    """Serves exactly what the wrapped policy serves; explains scheduled inferences in the background and, with a
    failure monitor, scores every call (`cam.monitoring`): its worker scores each call in its connection's order
    as soon as it is served (a few NumPy operations, not held back for a pause in inference as explanations are),
    or the call itself does, before its response, with `monitor_response`. With a monitor every call is traced with
    its signals; without a logger (`every_k` 0) nothing is explained and only the monitor runs."""

    def __init__(
        self,
        policy: TracedPolicy,
        options: CAMOptions,
        cam_logger: CAMLogger | None,
        monitor: LiveMonitor | None = None,
        watcher: StepWatcher | None = None,
    ):
        self._policy = policy
        self._options = options
        self._logger = cam_logger
        self._monitor = monitor
        self._watcher = watcher
        self._scoring: collections.deque[_Scoring | _Closed] = collections.deque()  # guarded by `_lock`
        self._explainer = explainer_on_device(policy.explainer, options.device)
        self._lock = threading.Lock()
        # Guards the fields below with `_lock`; notified when the last in-flight inference ends and when the drain
        # begins: the two events the waiting worker acts on.
        self._cond = threading.Condition(self._lock)
        self._pending = _Pending(options.queue_size, options.per_connection)
        self._inflight = 0  # inferences inside `infer` right now
        self._last_end = 0.0  # time.monotonic() when the last one returned
        self._finishing = False  # set by the drain: the worker exits once nothing is pending
        self._timings: collections.deque[JobTiming] = collections.deque(maxlen=options.stats_window)
        self._events = WarnOnceCounter(logger, "explanation side channel")
        self._steps: dict[str, int] = {}  # per-connection inference index
        self._closed = False
        self._closer: threading.Thread | None = None  # started by begin_close: drains, then writes the manifest
        self._deadline = 0.0
        self._worker = threading.Thread(target=self._work, name="explain-worker", daemon=True)
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

    def count(self, event: str, message: str | None = None, *, n: int = 1) -> None:
        """Counts `event` (a `/stats` key) `n` times; `message` is logged the first time."""
        self._events.count(event, message, n=n)

    @property
    def monitor(self) -> LiveMonitor | None:
        return self._monitor

    def infer(self, obs: dict[str, Any], context: object = None) -> dict[str, Any]:
        obs, extra = split_extra(obs)
        ((connection, step, scheduled),) = self._begin_inference([context])
        try:
            if self._monitor is not None:
                response, trace = self._policy.infer_traced(obs, signals=True)
                return self._monitored(response, trace, connection, step, scheduled, extra, time.monotonic())
            if not scheduled:
                return self._policy.infer(obs, context)
            response, trace = self._policy.infer_traced(obs)
            self._enqueue(trace, connection, step, extra, time.monotonic())
            return response
        finally:
            self._end_inference()

    def _monitored(
        self,
        response: dict[str, Any],
        trace: InferenceTrace,
        connection: str,
        step: int,
        scheduled: bool,
        extra: dict[str, Any],
        ended: float,
    ) -> dict[str, Any]:
        """A served call under the monitor: scored now when the response carries its score, else queued for the
        worker (before its explanation job, which then finds the score in its slot); explained when scheduled."""
        slot = _MonitorSlot() if scheduled else None
        if self._options.monitor_response:
            scored = self._score(connection, trace)
            response = {**response, RESPONSE_KEY: response_entry(scored)}
            if slot is not None:
                slot.scored = scored
        else:
            with self._cond:
                self._scoring.append(_Scoring(connection, trace, slot))
                self._cond.notify_all()
        if scheduled:
            self._enqueue(trace, connection, step, extra, ended, slot)
        return response

    def _signals(self, trace: InferenceTrace) -> Mapping[str, np.ndarray]:
        """What the monitor scores of a call: its signals, and the sample spread where the monitor reads one."""
        assert self._monitor is not None
        samples = self._monitor.monitor.sample_spread
        return trace.signals if samples is None else with_sample_spread(self._policy, trace, samples)

    def _score(self, connection: str, trace: InferenceTrace) -> StepScore | None:
        """The connection's next call scored; None (counted, logged once) when the monitor cannot score it."""
        assert self._monitor is not None
        try:
            return self._monitor.score(connection, self._signals(trace), trace.prompt)
        except Exception as e:  # the monitor never reaches a client
            self.count(f"monitor_failed_{type(e).__name__}", f"scoring a call raised {type(e).__name__}: {e}")
            return None

    def connection_closed(self, connection_id: str) -> None:
        """The server's notice that a connection ended: its monitored episode is over (after its queued calls)."""
        if self._monitor is None:
            return
        with self._cond:
            self._scoring.append(_Closed(connection_id))
            self._cond.notify_all()

    def infer_batch(
        self, observations: Sequence[dict[str, Any]], contexts: Sequence[object]
    ) -> list[dict[str, Any] | Exception]:
        """Batched serving: one model call for requests of several connections, each answered (or its exception
        returned in its slot) as `infer` would; scheduled ones are explained like any other."""
        split = [split_extra(obs) for obs in observations]
        rows = self._begin_inference(contexts)
        try:
            policy_obs = [obs for obs, _ in split]
            if self._monitor is not None:
                results = self._policy.infer_batch_traced(policy_obs, signals=True)
            else:
                results = self._policy.infer_batch_traced(policy_obs)
            ended = time.monotonic()
            responses: list[dict[str, Any] | Exception] = []
            for (_, extra), (connection, step, scheduled), result in zip(split, rows, results, strict=True):
                if isinstance(result, Exception):
                    responses.append(result)
                    continue
                response, trace = result
                if self._monitor is not None:
                    response = self._monitored(response, trace, connection, step, scheduled, extra, ended)
                elif scheduled:
                    self._enqueue(trace, connection, step, extra, ended)
                responses.append(response)
            return responses
        finally:
            self._end_inference()

    def _begin_inference(self, contexts: Sequence[object]) -> list[tuple[str, int, bool]]:
        """Counts one inference in flight (the worker starts nothing until it ends) and numbers its requests per
        connection: (connection, step, whether the step is explained) per request."""
        every_k = self._options.every_k
        rows = []
        with self._lock:
            self._inflight += 1
            for context in contexts:
                connection = str(getattr(context, "connection_id", "local"))
                step = self._steps.get(connection, 0)
                self._steps[connection] = step + 1
                off = self._logger is None or self._closed or every_k == 0 or step % every_k
                rows.append((connection, step, not off))
        return rows

    def _end_inference(self) -> None:
        with self._cond:
            self._inflight -= 1
            self._last_end = time.monotonic()
            if self._inflight == 0:
                self._cond.notify_all()

    def _enqueue(
        self,
        trace: InferenceTrace,
        connection: str,
        step: int,
        extra: dict[str, Any],
        ended: float,
        monitor: _MonitorSlot | None = None,
    ) -> None:
        """Queues the explanation of one served inference; never raises (the side channel never reaches a client)."""
        self.count("scheduled")
        # A pending job holds the client's frames (up to the message limit each) only for what will use them: the
        # raw frames when they are written, the whole observation when prompt reliance prepares it again.
        unused: dict[str, Any] = {}
        if self._options.save_frames not in ("raw", "both"):
            unused["raw_images"] = dict.fromkeys(trace.raw_images)
        if not self._options.reliance:
            unused["request"] = None
        trace = dataclasses.replace(trace, **unused)
        try:
            kept, dropped = bounded_extra(
                extra, int(self._options.max_extra_value_kb * KiB), int(self._options.max_extra_kb * KiB)
            )
            if dropped:
                self.count("extra_dropped", f"cam_extra values over the size limits dropped: {dropped[:3]}")
                kept["extra_dropped"] = dropped
            job = _Job(trace, connection, step, time.time(), kept, ended, monitor)
            with self._lock:  # a job queued after the drain began would be lost without a trace
                if self._closed:
                    self.count("not_queued_closing", "the side channel closed while this inference ran")
                    return
                superseded, dropped_jobs = self._pending.add(job)
            if superseded:
                self.count("superseded", n=superseded)
            if dropped_jobs:
                self.count(
                    "dropped_queue_full",
                    "queue full: the oldest job of the connection with the most pending jobs dropped",
                    n=dropped_jobs,
                )
        except Exception as e:
            self.count(f"enqueue_error_{type(e).__name__}", f"could not queue a job: {e}")

    def _work(self) -> None:
        while True:
            job, started = self._next_job()
            if job is None:
                return
            try:
                if isinstance(job, _Job):
                    self._process(job, started)
                elif isinstance(job, _Scoring):
                    scored = self._score(job.connection, job.trace)
                    if job.slot is not None:
                        job.slot.scored = scored
                elif self._monitor is not None:
                    self._monitor.closed(job.connection)
            except Exception as e:  # a bug in the side channel must not stop the worker (or reach a client)
                self.count(f"worker_error_{type(e).__name__}", f"the worker raised {type(e).__name__}: {e}")

    def _next_job(self) -> tuple[_Job | _Scoring | _Closed | None, float]:
        """Blocks until a call is to be scored (returned at once, in the order served), or an explanation job is
        pending and no inference has run for `settle_ms`; returns it with the time of that decision, taken under the
        lock (an inference may begin right after it: the explanation cannot wait for it any more). None: drained,
        time to exit."""
        with self._cond:
            while True:
                if self._scoring:
                    return self._scoring.popleft(), time.monotonic()
                if self._pending.size:
                    if self._settled_or_wait():
                        return self._pending.pop_oldest(), time.monotonic()
                elif self._finishing:
                    return None, time.monotonic()
                else:
                    self._cond.wait()

    def _wait_for_no_inference(self) -> float:
        """Between the phases of a job (explanation, spot check, write): lets an inference that started meanwhile
        finish (and settle) first. Returns the time of that decision, taken under the lock."""
        with self._cond:
            while not self._settled_or_wait():
                pass  # it waited: check again
            return time.monotonic()

    def _settled_or_wait(self) -> bool:
        """With the lock held: True once no inference is in flight and none has ended within `settle_ms`; otherwise
        waits (until an inference ends, or the settle time runs out) and returns False so the caller checks again.
        On a device of its own (`CAMOptions.device`) the worker does not wait."""
        if self._options.device is not None:
            return True
        if self._inflight:
            self._cond.wait()
            return False
        remaining = self._last_end + self._options.settle_ms / 1000.0 - time.monotonic()
        if remaining > 0:
            self._cond.wait(remaining)
            return False
        return True

    def _process(self, job: _Job, started: float) -> None:
        try:
            # the spot check re-runs the model: a phase of its own, like the write
            (explained,) = explain_batch(
                self._explainer,
                [job.trace],
                self._options,
                [job.step],
                before_check=self._wait_for_no_inference,
                policy=self._policy,
            )
        except Exception as e:
            self._record(JobTiming(job.connection, job.step, job.ended, started, time.monotonic()))
            self.count(f"failed_{type(e).__name__}", f"explaining raised {type(e).__name__}: {e}")
            return
        explanation, check = explained.result, explained.check
        if isinstance(explanation, ExplainSkipped):
            self._record(JobTiming(job.connection, job.step, job.ended, started, time.monotonic()))
            self.count(f"skipped_{explanation.reason}", str(explanation))
            return
        if job.trace.malformed_reason is not None:
            self.count("explained_malformed")
        if check is not None and check.skipped is not None:
            self.count(f"check_skipped_{check.skipped}", check.error)
        explained_at = time.monotonic()  # the explanation and its spot check
        timing = JobTiming(job.connection, job.step, job.ended, started, explained_at)
        explain_ms = (explained_at - started) * 1000.0
        # Building the record and writing it hold the GIL and the disk for milliseconds: a second phase, started
        # only while no inference is in flight either.
        writing = self._wait_for_no_inference()
        try:
            record = step_record(
                job.trace,
                explanation,
                connection=job.connection,
                step=job.step,
                timestamp=job.timestamp,
                save_frames=self._options.save_frames,
                extra=job.extra,
                explain_ms=explain_ms,
                check=check,
                reliance=explained.reliance,
                monitor=None if job.monitor is None else job.monitor.scored,
            )
            logged = self._logger.log_step(record)  # type: ignore[union-attr]  (no jobs without a logger)
        except Exception as e:
            self._record(dataclasses.replace(timing, writing=writing))
            self.count(f"log_error_{type(e).__name__}", f"logging a step raised {type(e).__name__}: {e}")
            return
        written = time.monotonic() if logged else None
        self._record(dataclasses.replace(timing, writing=writing, written=written))
        self.count("completed" if logged else "not_logged")
        if logged and self._watcher is not None:
            self._wait_for_no_inference()  # drawing the step's images holds the GIL: a phase of its own too
            try:
                self._watcher.watch(record, job.trace)
            except Exception as e:  # a watcher's bug must not stop the worker
                self.count(f"watch_error_{type(e).__name__}", f"watching a step raised {type(e).__name__}: {e}")

    def _record(self, timing: JobTiming) -> None:
        with self._lock:
            self._timings.append(timing)

    def timings(self) -> list[JobTiming]:
        """The last `stats_window` jobs the worker handled, oldest first: when each phase began and ended."""
        with self._lock:
            return list(self._timings)

    def stats(self) -> dict[str, Any]:
        cam: dict[str, Any] = self._events.snapshot()
        now = time.monotonic()
        with self._lock:
            cam["queued"] = self._pending.size
            oldest = self._pending.oldest_end()
            lags = [t.lag_ms for t in self._timings if t.lag_ms is not None]
        # How far behind the served inferences the run is: from an inference's end to its step on disk, over the
        # last written steps, and how long the oldest job still pending has waited (None: nothing pending).
        cam["lag_ms"] = None
        if lags:
            p50, p99 = np.percentile(np.asarray(lags), [50, 99])
            cam["lag_ms"] = {"window": len(lags), "p50": float(p50), "p99": float(p99), "max": max(lags)}
        cam["oldest_pending_ms"] = None if oldest is None else (now - oldest) * 1000.0
        if self._logger is not None:
            cam["logger"] = self._logger.counters
            cam["run"] = self._logger.run_dir.name  # the name only: /stats does not reveal the server's paths
        monitor = {} if self._monitor is None else {"monitor": self._monitor.stats()}
        return {**self._policy.stats(), "explanations": cam, **monitor}

    def begin_close(self, timeout: float | None = None) -> None:
        """Stops scheduling and starts the drain without waiting: queued jobs are explained until `timeout` seconds
        from now (None: until none is left), then the final manifest is written. The server calls this as soon as it
        is asked to stop, with its drain timeout, so the drain runs while connections are still closing (a
        container's stop grace period is short). Idempotent."""
        with self._lock:
            if self._closer is not None:
                return
            self._closed = True  # `infer` checks it under the same lock: nothing is queued behind the end marker
            self._deadline = time.monotonic() + (math.inf if timeout is None else timeout)
            self._closer = threading.Thread(target=self._drain, name="explain-drain", daemon=True)
            self._closer.start()

    def _drain(self) -> None:
        with self._cond:  # the worker explains what is pending, then exits
            self._finishing = True
            self._cond.notify_all()
        self._worker.join(_left(self._deadline))
        if self._worker.is_alive():
            self.count("unfinished_at_shutdown", "shutdown deadline passed with jobs pending")
        if self._watcher is not None and not self._worker.is_alive():
            self._watcher.close()
        if self._logger is not None:
            self._logger.set_external_counters(self._events.snapshot())
            self._logger.close()

    def close(self, timeout: float | None = None) -> None:
        """Stops scheduling, drains queued jobs up to the deadline (counted from `begin_close` when that came first),
        writes the final manifest, then closes the wrapped policy."""
        self.begin_close(timeout)
        assert self._closer is not None
        # At the deadline the drain stops waiting for the worker, but it still writes the manifest: a caller that
        # exits right after `close` (serve, with an explanation still computing) must not cut that write short.
        left = _left(self._deadline)
        self._closer.join(None if left is None else left + MANIFEST_WRITE_S)
        if self._closer.is_alive():
            self.count("manifest_not_written", f"the final manifest was not written within {MANIFEST_WRITE_S} s")
        self._policy.close(_left(self._deadline))

    @property
    def computing(self) -> bool:
        """Whether the worker is still running (after `close`: an explanation outlived the drain deadline)."""
        return self._worker.is_alive()

    def warm_up(self, batch_sizes: Sequence[int] = (1,)) -> str:
        """Compiles inference (at each of `batch_sizes`; with a monitor, the program that computes its signals) and,
        when steps are recorded, the configured explanation on the robot's example observation, before the server
        reports ready; nothing is logged or counted. A monitor that cannot score the example's call (an input the
        model does not give) raises ValueError naming it. Returns what was warmed."""
        if self._monitor is not None:
            trace = self._policy.warm_up(batch_sizes, signals=True)
            if trace is not None:
                try:
                    signals = self._signals(trace)
                except ValueError as e:
                    raise ValueError(f"monitor {self._monitor.source}: {e}") from None
                self._monitor.check(signals, trace.prompt)
        else:
            trace = self._policy.warm_up(batch_sizes)
        if trace is None:
            return "nothing (the robot transform offers no example observation)"
        if self._logger is None or self._options.every_k == 0:
            return "inference" if self._monitor is None else "inference with the monitor's signals"
        (explained,) = explain_batch(self._explainer, [trace], self._options, [0], policy=self._policy)
        explanation, check = explained.result, explained.check
        if isinstance(explanation, ExplainSkipped):
            return f"inference (the example's explanation was skipped: {explanation})"
        what = f"inference and the {explanation.target} explanation"
        if check is not None:
            what += f" (spot check skipped: {check.skipped})" if check.skipped else " with its spot check"
        if trace.malformed_reason is not None:
            # The example's generation holds no action tokens: the fallback target was compiled, not the configured
            # one (the side channel's first well-formed request compiles that, off the robot's path).
            return f"{what} (the example's generation: {trace.malformed_reason})"
        return what


def _left(deadline: float) -> float | None:
    """Seconds until a `time.monotonic()` deadline (0 once past it); None for no deadline."""
    return None if math.isinf(deadline) else max(0.0, deadline - time.monotonic())


def explanation_device(index: int) -> jax.Device:
    """`jax.devices()[index]`, or an error naming the devices this machine has."""
    devices = jax.devices()
    if not 0 <= index < len(devices):
        raise ValueError(f"explanation device {index} requested, this machine has {len(devices)}: {devices}")
    return devices[index]


def explainer_on_device(explainer: Explainer, index: int | None) -> Explainer:
    """`explainer` with its parameters on `jax.devices()[index]` (itself for None)."""
    if index is None:
        return explainer
    return explainer.on_mesh(Mesh(np.array([explanation_device(index)]), (BATCH_AXIS,)))


def wrap_policy_with_cam(
    policy: TracedPolicy,
    options: CAMOptions,
    *,
    run_config: dict[str, Any] | None = None,
    checkpoint: str = "",
    monitor: LiveMonitor | None = None,
    watcher: StepWatcher | None = None,
) -> CAMPolicy:
    """Creates the run directory and the worker. If the run directory cannot be created, the server still serves:
    the side channel is disabled and the reason logged and counted. A `device` the machine lacks, or a target the
    policy's family cannot explain, is refused (ValueError) before anything is created; no target (None) becomes the
    family's default, which the run then records. With a `monitor`, every call is scored; with `every_k` 0 too, no
    run directory is made and only the monitor runs. `watcher` sees each written step (`--cam.rerun`'s stream)."""
    options = dataclasses.replace(options, target=resolve_target(policy.explainer, options.target))
    if options.device is not None:
        explanation_device(options.device)
    if options.monitor_response and monitor is None:
        raise ValueError("--cam.monitor-response needs a monitor (--monitor FILE)")
    if options.monitor_response and monitor is not None and monitor.monitor.sample_spread is not None:
        raise ValueError(
            f"--cam.monitor-response: the monitor {monitor.source} reads the sample spread "
            f"({monitor.monitor.sample_spread} action samples a call), which would hold every response back; serve "
            "without it"
        )
    if options.every_k == 0 and monitor is not None:
        logger.info("failure monitor %s on: every call scored, nothing explained", monitor.source)
        return CAMPolicy(policy, options, None, monitor)
    try:
        cam_logger = CAMLogger(
            options.dir,
            run_config=run_config or {},
            checkpoint=str(checkpoint),
            options=options.to_json(),
            max_steps=options.max_steps,
            max_bytes=None if options.max_mb is None else int(options.max_mb * MiB),
        )
    except OSError as e:
        logger.error("explanation side channel off: cannot create a run directory under %s: %s", options.dir, e)
        wrapped = CAMPolicy(policy, options, None, monitor)
        wrapped.count("disabled_logger_unavailable")
        return wrapped
    logger.info(
        "explanation side channel on: every %d inference(s), run directory %s", options.every_k, cam_logger.run_dir
    )
    return CAMPolicy(policy, options, cam_logger, monitor, watcher)
