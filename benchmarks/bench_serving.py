"""Serving latency with the explanation side channel off vs on (every request), interleaved in one run.

    python benchmarks/bench_serving.py [--requests 200 --pause-ms 500 --block 10 --target action-token]

Two servers on loopback over the same policy (the bundled demo model, whose generations hold action tokens to
explain): plain, and wrapped with the side channel explaining every request (`every_k=1`). One websocket client
speaking the openpi-client protocol keeps a connection to each and alternates between them in blocks of `--block`
requests (off-on, then on-off, ...), so drift in the machine's load falls on both modes alike; never both at once,
which would make them compete. Before each block the side channel is left to finish its jobs, so an "on" block's
explanations are not charged to the "off" block after it. Two patterns, each with `--requests` requests per mode:

- robot cadence: a pause of `--pause-ms` after each answer (a DROID robot executes a chunk for about 0.5 s);
- back to back: no pause (the side channel then finds few gaps between inferences).

Printed per pattern and mode: p50 / p99 of the round-trip latency the client measures; the on/off ratios of p50 and
p99 with bootstrap 95% intervals (requests resampled within each mode); explanations completed of those scheduled;
and the explanation lag (from an inference's end to its step on disk) p50 / p99 / max.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import tempfile
import time
from typing import Any

import numpy as np
from websockets.sync.client import ClientConnection, connect

from openpi_cam.cam.side_channel import CAMOptions, CAMPolicy, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.serving import msgpack_numpy
from openpi_cam.serving.server import start_server_in_thread

# Counters that end a scheduled job (each job ends in exactly one of them); the rest (extra_dropped, ...) do not.
_OUTCOMES = ("completed", "not_logged", "dropped_queue_full", "superseded", "not_queued_closing")
_OUTCOME_PREFIXES = ("failed_", "skipped_", "log_error_", "worker_error_", "enqueue_error_")


def demo_setup(n: int, seed: int = 0) -> tuple[Any, list[dict[str, Any]]]:
    """The bundled demo policy and `n` client observations of random scenes (with their `cam_extra/` truth)."""
    from openpi_cam.demo import bundled, task

    rng = np.random.default_rng(seed)
    observations = []
    for _ in range(n):
        scene = task.random_scene(rng)
        observations.append(bundled.client_observation(task.observe(scene, task.random_start(rng, scene)), scene))
    return model_spec.create_demo_policy(), observations


def open_client(stack: contextlib.ExitStack, port: int) -> ClientConnection:
    ws = stack.enter_context(connect(f"ws://127.0.0.1:{port}", max_size=None, compression=None))
    ws.recv()  # the metadata frame
    return ws


def request(ws: ClientConnection, obs: dict[str, Any]) -> float:
    """One round trip as the client measures it, in ms."""
    t0 = time.perf_counter()
    ws.send(msgpack_numpy.packb(obs))
    reply = ws.recv()
    elapsed = (time.perf_counter() - t0) * 1e3
    if isinstance(reply, str):
        raise RuntimeError(reply)
    return elapsed


def ended_jobs(counters: dict[str, Any]) -> int:
    return sum(
        v for k, v in counters.items() if isinstance(v, int) and (k in _OUTCOMES or k.startswith(_OUTCOME_PREFIXES))
    )


def wait_settled(wrapped: CAMPolicy, timeout: float = 300.0) -> None:
    """Until every scheduled job has ended (written, dropped or failed): the worker is idle."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        counters = wrapped.stats()["explanations"]
        if counters["queued"] == 0 and ended_jobs(counters) >= counters.get("scheduled", 0):
            return
        time.sleep(0.01)
    raise TimeoutError("the side channel did not finish its jobs")


def machine_line(load_before: tuple[float, ...], load_after: tuple[float, ...]) -> str:
    """Where a benchmark ran and how busy the machine was (1/5/15-minute load averages before and after)."""
    return (
        f"machine: {platform.machine()}, {os.cpu_count()} cores; load average (1/5/15 min) before "
        f"{'/'.join(f'{x:.2f}' for x in load_before)}, after {'/'.join(f'{x:.2f}' for x in load_after)}"
    )


def bootstrap_ratio(on: np.ndarray, off: np.ndarray, q: float, rng: np.random.Generator, n: int) -> tuple[float, ...]:
    """The ratio of the q-th percentiles (on / off) and its percentile-bootstrap 95% interval."""
    ratios = [np.percentile(rng.choice(on, on.size), q) / np.percentile(rng.choice(off, off.size), q) for _ in range(n)]
    lo, hi = np.percentile(ratios, [2.5, 97.5])
    return float(np.percentile(on, q) / np.percentile(off, q)), float(lo), float(hi)


def run_pattern(
    ports: dict[str, int], wrapped: CAMPolicy, observations: list[dict[str, Any]], n: int, block: int, pause_s: float
) -> dict[str, Any]:
    """`n` requests per mode, alternating modes in blocks (off-on, on-off, ...), the side channel settled before
    each block."""
    latencies: dict[str, list[float]] = {"off": [], "on": []}
    before = wrapped.stats()["explanations"]
    started = time.monotonic()
    with contextlib.ExitStack() as stack:
        clients = {mode: open_client(stack, port) for mode, port in ports.items()}
        sent = 0
        for pair in range(-(-n // block)):
            order = ("off", "on") if pair % 2 == 0 else ("on", "off")
            count = min(block, n - sent)
            for mode in order:
                wait_settled(wrapped)
                for i in range(count):
                    latencies[mode].append(request(clients[mode], observations[(sent + i) % len(observations)]))
                    time.sleep(pause_s)
            sent += count
        wait_settled(wrapped)
    after = wrapped.stats()["explanations"]
    lags = [t.lag_ms for t in wrapped.timings() if t.inference_end >= started and t.lag_ms is not None]
    return {
        "latencies": {mode: np.asarray(v) for mode, v in latencies.items()},
        "scheduled": after.get("scheduled", 0) - before.get("scheduled", 0),
        "completed": after.get("completed", 0) - before.get("completed", 0),
        "lags": np.asarray(lags),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--requests", type=int, default=200, help="requests per mode and pattern")
    ap.add_argument("--pause-ms", type=float, default=500.0, help="pause after each answer at robot cadence")
    ap.add_argument("--block", type=int, default=10, help="requests per mode before switching")
    ap.add_argument("--target", default="action-token", choices=["action-token", "all-action-tokens", "chunk"])
    ap.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples")
    ap.add_argument("--scenes", type=int, default=50, help="distinct observations, sent in turn")
    ap.add_argument("--settle-ms", type=float, default=CAMOptions.settle_ms, help="the side channel's settle_ms")
    args = ap.parse_args()
    # The window of timings must hold every job of a pattern (the lag is read from it).
    window = 2 * args.requests + 100

    load_before = os.getloadavg()
    policy, observations = demo_setup(args.scenes)
    with tempfile.TemporaryDirectory() as cam_dir:
        options = CAMOptions(every_k=1, dir=cam_dir, target=args.target, stats_window=window, settle_ms=args.settle_ms)
        wrapped = wrap_policy_with_cam(policy, options)
        plain_server = start_server_in_thread(policy, close_policy_on_stop=False)
        cam_server = start_server_in_thread(wrapped, close_policy_on_stop=False)
        ports = {"off": plain_server.port, "on": cam_server.port}
        try:
            # Warm-up: compiles inference and explanation, opens the run directory.
            run_pattern(ports, wrapped, observations, 3, 3, 0.05)
            results = {
                "robot cadence": run_pattern(
                    ports, wrapped, observations, args.requests, args.block, args.pause_ms / 1e3
                ),
                "back to back": run_pattern(ports, wrapped, observations, args.requests, args.block, 0.0),
            }
        finally:
            plain_server.stop()
            cam_server.stop()
            wrapped.close(60)
        counters = wrapped.stats()["explanations"]
    load_after = os.getloadavg()

    rng = np.random.default_rng(0)
    print(machine_line(load_before, load_after))
    print(
        f"{args.requests} requests per mode and pattern, blocks of {args.block}, target {args.target}, robot cadence "
        f"pause {args.pause_ms:.0f} ms, settle {args.settle_ms:.0f} ms, {args.bootstrap} bootstrap resamples"
    )
    columns = ["pattern", "side channel", "p50 ms", "p99 ms", "p50 on/off [95% CI]", "p99 on/off [95% CI]"]
    columns += ["explained", "lag ms p50 / p99 / max"]
    print("| " + " | ".join(columns) + " |")
    print("|" + " --- |" * len(columns))
    for pattern, res in results.items():
        off, on = res["latencies"]["off"], res["latencies"]["on"]
        r50, lo50, hi50 = bootstrap_ratio(on, off, 50, rng, args.bootstrap)
        r99, lo99, hi99 = bootstrap_ratio(on, off, 99, rng, args.bootstrap)
        lags = res["lags"]
        lag = "/".join(f"{x:.1f}" for x in (*np.percentile(lags, [50, 99]), lags.max())) if lags.size else "none"
        print(f"| {pattern} | off | {np.percentile(off, 50):.1f} | {np.percentile(off, 99):.1f} | | | | |")
        print(
            f"| {pattern} | on | {np.percentile(on, 50):.1f} | {np.percentile(on, 99):.1f} | "
            f"{r50:.3f} [{lo50:.3f}, {hi50:.3f}] | {r99:.3f} [{lo99:.3f}, {hi99:.3f}] | "
            f"{res['completed']} / {res['scheduled']} | {lag} |"
        )
    shown = {k: v for k, v in counters.items() if k not in ("logger", "run", "lag_ms")}
    print(f"side-channel counters (warm-up included): {shown}")


if __name__ == "__main__":
    main()
