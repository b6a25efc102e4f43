"""Serving latency with the Grad-CAM side channel off vs on (every step), measured side by side in one run.

    python benchmarks/bench_serving.py [--requests 30 --pause-ms 300 --target action-token]

Two servers on loopback over the same policy (the bundled demo model, whose generations hold action tokens to
explain): plain, and wrapped with `--cam-every-k 1`. A websocket client speaking the openpi-client
protocol sends the same observations to each, in two patterns: paced (pausing `--pause-ms` between requests, as a
robot executing its action chunk would) and back to back. Printed: request latency p50 / p99 per mode, the on/off
ratios, and Grad-CAM jobs completed per second of wall time.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from typing import Any

import numpy as np
from websockets.sync.client import connect

from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.policies import demo_reach
from openpi_cam.serving import msgpack_numpy
from openpi_cam.serving.server import start_server_in_thread


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def drive(port: int, observations: list[dict[str, Any]], pause_s: float) -> list[float]:
    """Round-trip latency (ms) of each request, as a client measures it."""
    latencies = []
    with connect(f"ws://127.0.0.1:{port}", max_size=None, compression=None) as ws:
        ws.recv()  # metadata
        for obs in observations:
            t0 = time.perf_counter()
            ws.send(msgpack_numpy.packb(obs))
            reply = ws.recv()
            latencies.append((time.perf_counter() - t0) * 1e3)
            if isinstance(reply, str):
                raise RuntimeError(reply)
            time.sleep(pause_s)
    return latencies


def wait_drained(wrapped, timeout: float = 300.0) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        stats = wrapped.stats()["gradcam"]
        finished = sum(v for k, v in stats.items() if isinstance(v, int) and k != "scheduled" and k != "queued")
        if stats.get("queued", 0) == 0 and finished >= stats.get("scheduled", 0):
            return
        time.sleep(0.05)


def demo_setup(n: int, seed: int = 0):
    """The bundled demo policy and `n` client observations of random scenes (with their `cam_extra/` truth)."""
    from openpi_cam.demo import bundled, task

    rng = np.random.default_rng(seed)
    observations = []
    for _ in range(n):
        scene = task.random_scene(rng)
        observations.append(bundled.client_observation(task.observe(scene, task.random_start(rng, scene)), scene))
    return demo_reach.create_demo_policy(), observations


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--requests", type=int, default=30)
    ap.add_argument("--pause-ms", type=float, default=300.0)
    ap.add_argument("--target", default="action-token", choices=["action-token", "all-action-tokens", "chunk"])
    args = ap.parse_args()

    policy, observations = demo_setup(args.requests)
    for obs in observations[:2]:  # compile inference before timing
        policy.infer({k: v for k, v in obs.items() if not k.startswith("cam_extra/")})
    with tempfile.TemporaryDirectory() as cam_dir:
        options = CAMOptions(every_k=1, cam_dir=cam_dir, target=args.target, queue_size=4)
        wrapped = wrap_policy_with_cam(policy, options)
        plain_server = start_server_in_thread(policy, close_policy_on_stop=False)
        cam_server = start_server_in_thread(wrapped, close_policy_on_stop=False)
        try:
            drive(plain_server.port, observations[:2], 0.0)  # warm both servers (connections, compilation)
            drive(cam_server.port, observations[:2], 0.0)
            wait_drained(wrapped)
            results = {}
            for pattern, pause in (("paced", args.pause_ms / 1e3), ("back-to-back", 0.0)):
                for mode, server in (("off", plain_server), ("on", cam_server)):
                    before = wrapped.stats()["gradcam"].get("completed", 0)
                    t0 = time.perf_counter()
                    lat = drive(server.port, observations, pause)
                    wait_drained(wrapped)  # jobs/s counts until the last job of this mode is written
                    wall = time.perf_counter() - t0
                    done = wrapped.stats()["gradcam"].get("completed", 0) - before
                    results[pattern, mode] = (lat, wall, done)
        finally:
            plain_server.stop()
            cam_server.stop()
            wrapped.close(60)
        stats = wrapped.stats()["gradcam"]
    print(
        f"machine: {platform.machine()}, {__import__('os').cpu_count()} cores; {args.requests} requests per mode; "
        f"target {args.target}; pause {args.pause_ms:.0f} ms (paced)"
    )
    print("| pattern | side channel | p50 ms | p99 ms | Grad-CAM jobs done | jobs / s |")
    print("| --- | --- | --- | --- | --- | --- |")
    for (pattern, mode), (lat, wall, done) in results.items():
        print(
            f"| {pattern} | {mode} | {statistics.median(lat):.1f} | {percentile(lat, 99):.1f} | {done} | "
            f"{done / wall:.2f} |"
        )
    for pattern in ("paced", "back-to-back"):
        off, on = results[pattern, "off"][0], results[pattern, "on"][0]
        print(
            f"{pattern}: p50 on/off = {statistics.median(on) / statistics.median(off):.2f}, "
            f"p99 on/off = {percentile(on, 99) / percentile(off, 99):.2f}"
        )
    print(f"side-channel counters: { {k: v for k, v in stats.items() if k not in ('logger', 'run_dir')} }")


if __name__ == "__main__":
    main()
