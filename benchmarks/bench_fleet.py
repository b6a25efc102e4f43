"""A fleet on one server: 1, 4 and 10 robots at once, served one request per model call (as upstream) vs in batches
(`--batch-window-ms`), interleaved in one run.

    python benchmarks/bench_fleet.py [--clients 1 4 10 --requests 60 --rounds 3 --window-ms 5 --max-batch 16]

Two servers on loopback over the same policy (the bundled demo model): serial, and batched. For each fleet size the
robots (one thread and one websocket connection each, speaking the openpi-client protocol) send their requests back
to back (each robot's next request leaves as soon as its answer arrives), first to one server, then to the other,
for `--rounds` rounds alternating which goes first, so drift in the machine's load falls on both alike. Printed per
fleet size and mode: throughput (answers per second over the whole fleet), p50 / p99 of the latency each robot
measures, the batched/serial ratios with bootstrap 95% intervals, and the mean batch size; and whether every answer
equalled the serial server's for the same observation (it must).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import threading
import time
import urllib.request
from typing import Any

import numpy as np
from bench_serving import bootstrap_ratio, demo_setup, machine_line, open_client
from websockets.sync.client import ClientConnection

from openpi_cam.serving import msgpack_numpy
from openpi_cam.serving.server import RunningServer, start_server_in_thread


def robot(ws: ClientConnection, observations: list[dict[str, Any]], first: int, n: int, out: list) -> None:
    """Sends `n` requests back to back (observations from index `first` on); appends (latency ms, scene, actions)."""
    for i in range(n):
        scene = (first + i) % len(observations)
        t0 = time.perf_counter()
        ws.send(msgpack_numpy.packb(observations[scene]))
        reply = ws.recv()
        elapsed = (time.perf_counter() - t0) * 1e3
        if isinstance(reply, str):
            raise RuntimeError(reply)
        out.append((elapsed, scene, msgpack_numpy.unpackb(reply)["actions"]))


def run_fleet(port: int, observations: list[dict[str, Any]], clients: int, n: int) -> tuple[float, list]:
    """`clients` robots sending `n` requests each at once -> (wall seconds, [(latency, scene, actions)])."""
    results: list[list] = [[] for _ in range(clients)]
    with contextlib.ExitStack() as stack:
        sockets = [open_client(stack, port) for _ in range(clients)]
        threads = [
            threading.Thread(target=robot, args=(ws, observations, 7 * c, n, results[c]))
            for c, ws in enumerate(sockets)
        ]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
    answers = [r for per_robot in results for r in per_robot]
    if len(answers) != clients * n:
        raise RuntimeError(f"{clients * n - len(answers)} requests got no answer")
    return wall, answers


def batch_sizes(server: RunningServer) -> dict[str, int]:
    """Model calls per batch size so far, from the server's `/stats`."""
    with urllib.request.urlopen(f"{server.url.replace('ws://', 'http://')}/stats", timeout=10) as response:
        return json.loads(response.read())["batching"]["sizes"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 4, 10], help="fleet sizes")
    ap.add_argument("--requests", type=int, default=60, help="requests per robot and round")
    ap.add_argument("--rounds", type=int, default=3, help="rounds per fleet size (modes alternate who goes first)")
    ap.add_argument("--window-ms", type=float, default=5.0, help="the batched server's --batch-window-ms")
    ap.add_argument("--max-batch", type=int, default=16, help="the batched server's --max-batch")
    ap.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples")
    ap.add_argument("--scenes", type=int, default=50, help="distinct observations, sent in turn")
    args = ap.parse_args()

    load_before = os.getloadavg()
    policy, observations = demo_setup(args.scenes)
    sizes = tuple(1 << i for i in range(args.max_batch.bit_length()))
    policy.warm_up(sizes)
    reference = [policy.infer(obs)["actions"] for obs in observations]  # serial answers, per scene
    serial = start_server_in_thread(policy, close_policy_on_stop=False)
    batched = start_server_in_thread(
        policy, close_policy_on_stop=False, batch_window_ms=args.window_ms, max_batch=args.max_batch
    )
    ports = {"serial": serial.port, "batched": batched.port}
    rows: list[dict[str, Any]] = []
    mismatches = 0
    try:
        for clients in args.clients:
            latencies: dict[str, list[float]] = {"serial": [], "batched": []}
            walls = {"serial": 0.0, "batched": 0.0}
            counts = {"serial": 0, "batched": 0}
            before = dict(batch_sizes(batched))
            for r in range(args.rounds):
                for mode in ("serial", "batched") if r % 2 == 0 else ("batched", "serial"):
                    wall, answers = run_fleet(ports[mode], observations, clients, args.requests)
                    walls[mode] += wall
                    counts[mode] += len(answers)
                    latencies[mode] += [a[0] for a in answers]
                    mismatches += sum(not np.array_equal(a[2], reference[a[1]]) for a in answers)
            after = batch_sizes(batched)
            calls = {int(k): v - before.get(k, 0) for k, v in after.items()}
            mean_batch = sum(k * v for k, v in calls.items()) / max(1, sum(calls.values()))
            rows.append({"clients": clients, "lat": latencies, "walls": walls, "counts": counts, "mean": mean_batch})
    finally:
        serial.stop()
        batched.stop()
    load_after = os.getloadavg()

    rng = np.random.default_rng(0)
    print(machine_line(load_before, load_after))
    print(
        f"{args.requests} requests per robot and round, {args.rounds} rounds, back to back; batched: window "
        f"{args.window_ms:g} ms, max batch {args.max_batch}; {args.bootstrap} bootstrap resamples"
    )
    columns = ["robots", "mode", "answers/s", "p50 ms", "p99 ms", "throughput batched/serial"]
    columns += ["p50 batched/serial [95% CI]", "p99 batched/serial [95% CI]", "mean batch"]
    print("| " + " | ".join(columns) + " |")
    print("|" + " --- |" * len(columns))
    for row in rows:
        lat = {m: np.asarray(v) for m, v in row["lat"].items()}
        rate = {m: row["counts"][m] / row["walls"][m] for m in lat}
        r50, lo50, hi50 = bootstrap_ratio(lat["batched"], lat["serial"], 50, rng, args.bootstrap)
        r99, lo99, hi99 = bootstrap_ratio(lat["batched"], lat["serial"], 99, rng, args.bootstrap)
        for mode in ("serial", "batched"):
            cells = [str(row["clients"]), mode, f"{rate[mode]:.2f}"]
            cells += [f"{np.percentile(lat[mode], 50):.1f}", f"{np.percentile(lat[mode], 99):.1f}"]
            if mode == "serial":
                cells += ["", "", "", ""]
            else:
                cells += [f"{rate['batched'] / rate['serial']:.2f}", f"{r50:.3f} [{lo50:.3f}, {hi50:.3f}]"]
                cells += [f"{r99:.3f} [{lo99:.3f}, {hi99:.3f}]", f"{row['mean']:.2f}"]
            print("| " + " | ".join(cells) + " |")
    print(f"answers different from the serial policy's for the same observation: {mismatches}")


if __name__ == "__main__":
    main()
