"""`openpi-cam serve`: load an OpenPI checkpoint of any family (pi0-FAST, pi0, pi0.5) and serve it like upstream's
`scripts/serve_policy.py`.

With `--cam.every-k K > 0` every K-th request per connection also gets its maps written under `--cam.dir` (off the
request path; see docs/FORMAT.md). The side channel's flags are one dataclass, `SideChannelFlags`, nested as `--cam.*`
and generated from the side channel's own settings (`cam.side_channel.SideChannelSettings`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Any, ClassVar

import tyro

from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.cam.side_channel import CAMOptions, CAMPolicy, SideChannelSettings, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli.options import BUNDLED_MODEL, ExplainFlags
from openpi_cam.lerobot.served_episodes import EpisodeRecorder
from openpi_cam.monitor import monitor_file
from openpi_cam.policies.family import resolve_target
from openpi_cam.policies.policy import Policy
from openpi_cam.serving.server import PolicyServer
from openpi_cam.viz.rerun_sink import LiveRerun
from openpi_cam.vocabulary import Target

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class SideChannelFlags(SideChannelSettings, ExplainFlags):
    """The explanation side channel's flags, `--cam.*`: what each explained step explains and carries
    (`ExplainFlags`), then the side channel's own settings, generated from `SideChannelSettings` field by field (one
    name, unit and default each)."""

    FLAG_PREFIX: ClassVar[str] = "--cam."

    def __post_init__(self) -> None:
        ExplainFlags.__post_init__(self)  # builds the options, which check every flag

    def options(self, target: Target | None = None, model: ModelSpec | None = None) -> CAMOptions:
        """The side channel's options; `target`, when given, stands for the flag's (the served family's resolved
        target); `model`, the served model (its own occlusion head)."""
        return super().options(target, model).extended(CAMOptions, **self.settings())


SIDE_CHANNEL_OFF = SideChannelFlags()
DEFAULT_MAX_BATCH = 8
DEFAULT_RECORD_FPS = 10


class StartupError(Exception):
    """A start-up problem of the operator's making (a flag, a file, a checkpoint of another family): reported in one
    line with this exit status, without a traceback."""

    def __init__(self, message: str, status: int) -> None:
        super().__init__(message)
        self.status = status


def main(
    model: tyro.conf.OmitArgPrefixes[ModelSpec] = BUNDLED_MODEL,
    port: int = 8000,
    host: str = "0.0.0.0",
    api_key: str | None = None,
    max_message_mb: float = 64.0,
    max_connections: int = 64,
    max_buffered_mb: float = 256.0,
    debug: bool = False,
    stop_at_action_end: bool = False,
    cam: SideChannelFlags = SIDE_CHANNEL_OFF,
    warm_up: bool = True,
    batch_window_ms: float | None = None,
    max_batch: int = DEFAULT_MAX_BATCH,
    record: Path | None = None,
    record_fps: int = DEFAULT_RECORD_FPS,
    drain_timeout: Annotated[float, tyro.conf.arg(aliases=("--cam.drain-timeout",))] = 5.0,
    monitor: Path | None = None,
    no_monitor: tyro.conf.FlagCreatePairsOff[bool] = False,
) -> int:
    """Serve an OpenPI checkpoint (pi0-FAST, pi0 or pi0.5) over websockets (openpi-client compatible), optionally
    explaining every k-th request of each connection in the background (`--cam.every-k`).

    Args:
        model: which model to serve (the same flags as every command's; default: the bundled demo model).
        port: TCP port.
        host: interface to listen on (0.0.0.0 = all, like upstream).
        api_key: if set, clients must send `Authorization: Api-Key <key>` (openpi-client's `api_key=`).
        max_message_mb: largest accepted request frame; larger ones close the connection (code 1009).
        max_connections: open connections at most; further ones are closed at once (code 1013, try again later).
        max_buffered_mb: request bytes being handled at once over all connections (decoding, waiting for the model,
            computing); a request that would pass it closes its connection (code 1013). At least --max-message-mb.
        debug: send tracebacks of unexpected errors to clients.
        stop_at_action_end: pi0-FAST: stop decoding at the end of the action string instead of running to EOS.
        cam: the explanation side channel (off unless --cam.every-k > 0).
        warm_up: compile inference (and the side channel's explanation) on the robot's example observation before
            listening, so `/healthz` answers only once the first request will not wait for compilation.
        batch_window_ms: serve a fleet in batches: requests from all connections arriving within this many ms of the
            first share one model call, each row answered as if served alone (docs/SERVING.md). None: one request
            per model call, as upstream.
        max_batch: requests per batched call at most, a power of two (calls run at power-of-two batch sizes: one
            compiled program each, all compiled at warm-up).
        record: record every connection as an episode of a new LeRobot v3.0 dataset in this folder (its requests'
            images and values, prompts and served chunks; `lerobot.served_episodes`), saved when it closes.
        record_fps: the recorded dataset's frame rate (LeRobot's timestamps are frame index / fps): the rate at which
            the robot sends requests.
        drain_timeout: on SIGTERM, seconds the server lets the served policy drain (the side channel's queued
            explanations, the recorder's last episodes), counted from the signal while connections close, before the
            run's manifest is closed: SIGTERM exits within this, the in-flight inference and 2 s for unresponsive
            peers, inside a container's 10 s stop grace period. `--cam.drain-timeout` is its earlier spelling.
        monitor: a failure monitor file (`openpi-cam monitor fit`): every served call is scored by the side
            channel's worker, off the request path (per connection, the maximum step score so far against the
            monitor's threshold), explained steps carry it (`monitor/...`) and `/stats` counts flagged connections;
            works with `--cam.every-k 0` too (then only the monitor runs). Default: a demo model's own
            `<assets>/monitor.json` when it ships one, else none.
        no_monitor: run without a failure monitor, even a demo model's own.
    """
    _configure_logging()
    try:
        _check_batching(batch_window_ms, max_batch)
        if drain_timeout < 0:
            raise StartupError(f"--drain-timeout must be >= 0, got {drain_timeout}", 2)
        live = _monitor(model, monitor, no_monitor)
        _check_side_channel_flags(cam, live is not None)
        _check_recording(record, record_fps)
        policy = _create_policy(model, stop_at_action_end)
        run_config = {**model.resolved().to_json(), "stop_at_action_end": stop_at_action_end}
        served = _with_side_channel(policy, cam, model, run_config, live)
        outer = served if record is None else _recording(served, record, record_fps)
        server = _server(
            outer,
            policy.metadata,
            family=policy.model.family,
            host=host,
            port=port,
            api_key=api_key,
            max_message_mb=max_message_mb,
            max_connections=max_connections,
            max_buffered_mb=max_buffered_mb,
            debug=debug,
            drain_timeout=drain_timeout,
            batch_window_ms=batch_window_ms,
            max_batch=max_batch,
        )
    except StartupError as e:
        print(f"openpi-cam serve: {e}", file=sys.stderr)
        return e.status
    if live is not None:  # said once the command is sure to start, so that a refusal stays its one line
        logger.info("failure monitor %s: %s, threshold %s", live.source, live.monitor.kind, live.monitor.threshold)
    if warm_up:
        try:
            _warm_up(served, policy, batch_window_ms, max_batch)
        except ValueError as e:  # a monitor that cannot score this model's calls
            print(f"openpi-cam serve: {e}", file=sys.stderr)
            outer.close(0.0)
            return 2
    return _serve(server, served, outer, host, port)


def _configure_logging() -> None:
    # force: importing orbax has already put a handler on the root logger; ours gives every line a time stamp. INFO
    # for this package only (readiness, connections, shutdown); libraries stay at WARNING.
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True)
    logging.getLogger("openpi_cam").setLevel(logging.INFO)


def _monitor(model: ModelSpec, path: Path | None, off: bool) -> LiveMonitor | None:
    """The failure monitor to serve with: `--monitor`, else a demo model's own (`ModelSpec.default_monitor`), none
    with `--no-monitor`; a file that is not a monitor is refused in one line."""
    try:
        path = model.chosen_monitor(path, off)
    except ValueError as e:
        raise StartupError(str(e), 2) from None
    if path is None:
        return None
    try:
        loaded = monitor_file.load(path)
    except ValueError as e:
        raise StartupError(f"--monitor {e}", 2) from None
    return LiveMonitor(loaded, path.name)


def _check_side_channel_flags(flags: SideChannelFlags, monitored: bool) -> None:
    """With the side channel off, a --cam flag would be accepted and ignored: refused instead, naming it (the
    monitor's response key needs a monitor, which runs with the side channel off too)."""
    if flags.monitor_response and not monitored:
        raise StartupError("--cam.monitor-response needs a failure monitor: add --monitor FILE", 2)
    if flags.every_k:
        return
    unused = [
        f.name
        for f in dataclasses.fields(flags)
        if f.name not in ("every_k", "monitor_response") and getattr(flags, f.name) != getattr(SIDE_CHANNEL_OFF, f.name)
    ]
    if unused:
        names = ", ".join("--cam." + n.replace("_", "-") for n in unused)
        raise StartupError(f"{names} given but the side channel is off: add --cam.every-k K", 2)


def _check_batching(batch_window_ms: float | None, max_batch: int) -> None:
    """Batched serving runs (and warms up) one program per power-of-two batch size up to --max-batch."""
    if batch_window_ms is None and max_batch != DEFAULT_MAX_BATCH:
        raise StartupError("--max-batch sizes batched calls: add --batch-window-ms MS", 2)
    if batch_window_ms is not None and (batch_window_ms < 0 or max_batch < 1 or max_batch & (max_batch - 1)):
        raise StartupError(
            f"need --batch-window-ms >= 0 and --max-batch a power of two, got {batch_window_ms} and {max_batch}", 2
        )


def _create_policy(model: ModelSpec, stop_at_action_end: bool) -> Policy:
    try:
        return model.create(stop_at_action_end=stop_at_action_end)
    except KeyError as e:  # an unknown config name: its message lists the known ones
        raise StartupError(str(e.args[0]) if e.args else repr(e), 1) from None
    except (FileNotFoundError, ValueError, OSError) as e:
        # Missing files or a checkpoint that is not the config's family are operator problems, not bugs: the message
        # says what is wrong and where.
        raise StartupError(str(e), 1) from None


def _with_side_channel(
    policy: Policy, flags: SideChannelFlags, model: ModelSpec, run_config: dict[str, Any], live: LiveMonitor | None
) -> Policy | CAMPolicy:
    """The policy as served: itself, or wrapped in the side channel explaining the target the flags name (by default
    the family's own) and scoring every call with the monitor; a target the family cannot explain is refused, naming
    those it can. With a monitor and `--cam.every-k 0` the side channel scores and explains nothing."""
    if flags.every_k == 0 and live is None:
        return policy
    try:
        target = resolve_target(policy.explainer, flags.target)
    except ValueError as e:
        raise StartupError(f"--cam.target {e}", 2) from None
    try:
        served = wrap_policy_with_cam(
            policy,
            flags.options(target, model),
            run_config=run_config,
            checkpoint=str(model.checkpoint),
            monitor=live,
            watcher=_rerun_stream(flags.rerun),
        )
    except ValueError as e:  # e.g. --cam.device names a device this machine does not have, or a head of another model
        raise StartupError(str(e), 2) from None
    if flags.every_k:
        logger.info(
            "side channel: explaining every %d request(s) of each connection, target %s, runs under %s",
            flags.every_k,
            target,
            flags.dir,
        )
    return served


def _rerun_stream(address: str | None) -> LiveRerun | None:
    """`--cam.rerun`'s stream; refused in one line without rerun-sdk."""
    if address is None:
        return None
    try:
        stream = LiveRerun(address)
    except ImportError as e:
        raise StartupError(f"--cam.rerun: {e}", 2) from None
    logger.info("side channel: streaming explained steps to the Rerun viewer at %s", address)
    return stream


def _server(
    served: Policy | CAMPolicy | EpisodeRecorder,
    metadata: dict[str, Any],
    *,
    family: str,
    host: str,
    port: int,
    api_key: str | None,
    max_message_mb: float,
    max_connections: int,
    max_buffered_mb: float,
    debug: bool,
    drain_timeout: float,
    batch_window_ms: float | None,
    max_batch: int,
) -> PolicyServer:
    """The websocket server, not yet listening; it refuses limits it cannot serve with."""
    if batch_window_ms is not None and family != "pi0_fast":
        logger.warning(
            "batched %s serving: actions match serving each request alone only to floating-point rounding (batched "
            "matrix products round differently; docs/SERVING.md)",
            family,
        )
    try:
        return PolicyServer(
            served,
            host=host,
            port=port,
            metadata=dict(metadata),
            api_key=api_key,
            max_message_bytes=int(max_message_mb * 1024 * 1024),
            max_connections=max_connections,
            max_buffered_bytes=int(max_buffered_mb * 1024 * 1024),
            debug=debug,
            drain_timeout=drain_timeout,
            batch_window_ms=batch_window_ms,
            max_batch=max_batch,
        )
    except ValueError as e:
        served.close(0.0)  # the side channel may have opened its run: close it with its manifest
        raise StartupError(
            f"server limits (--max-message-mb, --max-connections, --max-buffered-mb, --drain-timeout): {e}", 2
        ) from None


def _warm_up(served: Policy | CAMPolicy, policy: Policy, batch_window_ms: float | None, max_batch: int) -> None:
    start = time.monotonic()
    sizes = (1,) if batch_window_ms is None else tuple(1 << i for i in range(max_batch.bit_length()))
    if isinstance(served, CAMPolicy):
        warmed = served.warm_up(sizes)
    elif policy.warm_up(sizes) is not None:
        warmed = "inference"
    else:
        warmed = "nothing (the robot transform offers no example)"
    batches = "" if batch_window_ms is None else f" (batch sizes {list(sizes)})"
    logger.info("warmed up %s in %.1f s%s", warmed, time.monotonic() - start, batches)


def _check_recording(root: Path | None, fps: int) -> None:
    if root is None and fps != DEFAULT_RECORD_FPS:
        raise StartupError("--record-fps is the recorded dataset's rate: add --record DIR", 2)
    if root is not None and root.exists() and any(root.iterdir()):
        raise StartupError(f"--record {root} exists and is not empty: name a new folder", 2)
    if fps < 1:
        raise StartupError(f"--record-fps must be >= 1, got {fps}", 2)


def _recording(served: Policy | CAMPolicy, root: Path, fps: int) -> EpisodeRecorder:
    logger.info("recording every connection as an episode of the LeRobot dataset %s", root)
    return EpisodeRecorder(served, root, fps=fps)


def _serve(
    server: PolicyServer, served: Policy | CAMPolicy, outer: Policy | CAMPolicy | EpisodeRecorder, host: str, port: int
) -> int:
    """Listens until SIGINT / SIGTERM, then drains and closes (`outer`: what the server serves, `served` within it)."""
    try:
        server.serve_forever()
    except OSError as e:  # the port is taken, or the host is not this machine's
        print(f"openpi-cam serve: cannot listen on {host}:{port}: {e}", file=sys.stderr)
        outer.close(0.0)
        return 1
    if isinstance(served, CAMPolicy) and served.computing:
        # The manifest is written; an explanation still runs in XLA on the worker thread, and interpreter shutdown
        # under a running XLA computation aborts the process. Exit without the interpreter's teardown instead.
        logger.warning("exiting with an explanation still computing past --drain-timeout (its step is not written)")
        logging.shutdown()
        os._exit(0)
    return 0
