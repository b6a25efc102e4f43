"""Hostile clients against a served process: memory, log and disk stay within stated bounds while a paced robot
keeps being served."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from client_env import collect, spawn_client
from real_clients import (
    client_script,
    get_stats,
)
from serve_process import serve_subprocess
from serve_process import stop as _stop
from serving_support import BAD_REQUEST_EXPECTATIONS, BAD_REQUESTS, MAX_ERROR_CHARS, ROBOT, droid_obs_bytes, run_dirs
from websockets.sync.client import connect

from openpi_cam.cam.run_format import load_run


def _proc_status_bytes(pid: int, field: str) -> int:
    """A memory figure of a process from /proc (VmRSS: resident now; VmHWM: peak resident since start or reset)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(field)


# Requests that try to make the server store or hold a lot: cam_extra/ bloat, then a flood of frames near the size
# limit on a connection that never reads its replies.
HOSTILE_EXTRA = r"""
policy = connect()
good = droid_obs(np.random.RandomState(2), size=(64, 96))
shapes = []
for extra in ({"cam_extra/blob": "x" * 8_000_000}, {"cam_extra/array": np.zeros(1_000_000, np.float32)}):
    shapes.append(list(policy.infer({**good, **extra})["actions"].shape))
# 15 million empty maps in 15 MB: decoded whole, ~2 GB of Python objects; the decoder stops at its container budget.
maps = b"\xdd" + (15_000_000).to_bytes(4, "big") + b"\x80" * 15_000_000
error = error_of(lambda: infer_raw(policy, b"\x81\xa4junk" + maps))
done(shapes=shapes, error=error)
"""


# The valid observations the hostile clients send besides their bad requests (BAD_REQUESTS' and HOSTILE_EXTRA's
# `good`; the flood's is sent by the test itself), served once before any peak is measured: each explanation's replay
# length is bucketed by the step it explains (`pi0_fast_maps.replay_length`), and the first observation of a new
# bucket compiles its programs in the side channel's worker. That is a property of valid requests, not hostile ones.
WARM_OTHERS = r"""
policy = connect()
for seed in (0, 2):
    policy.infer(droid_obs(np.random.RandomState(seed), size=(64, 96)))
done()
"""

FLOOD_FRAMES = 10
WARM_DEADLINE_S = 600
# The robot's requests in each phase: enough that the hostile phase's run spans the flood and most of the bad requests.
ROBOT_REQUESTS = 15
HOSTILE_EXTRA_PEAK_FRAMES = 12  # what the hostile probes may add to plain serving's peak, in message-limit units


@pytest.mark.slow
def test_hostile_clients_against_a_served_process_stay_within_memory_log_and_disk_bounds(tiny_policy_files, tmp_path):
    """`openpi-cam serve` (tiny DROID checkpoint, side channel on, 16 MiB message limit), first serving a robot alone,
    then the same robot while every hostile probe runs at once: the 19 bad-request classes (amplifying frames, deep
    nesting, megabyte strings, unsendable dtypes), cam_extra bloat (an 8 MB string, a 4 MB array), 15 million empty
    maps in one 15 MB frame (~2 GB of objects if decoded whole), and a peer sending 10 frames of ~14.5 MiB without
    ever reading its replies. The valid observations the hostile clients also send are served once beforehand
    (`WARM_OTHERS`), so that neither phase includes a first-use compilation. The side channel runs without its spot
    check: its re-runs would only lengthen each explanation, and what is bounded here is what clients make the server
    hold. Bounds, against measurements on the 2-core machine:
    - the server's peak resident memory in the hostile phase exceeds plain serving's by less than 12 message limits
      (192 MiB; plain serving's own peak, the explanation's working set, measured 138-305 MB above the idle server
      since the replay stops at the explained step; the hostile phase 241-290 MB, 102-104 MB above it run alone and
      146 MB in a full suite run on both cores; a server that buffered the flood's 10 undecoded frames would add
      145 MiB more than that; with the spot check on, its first re-scoring programs can compile inside the plain
      window and hide the hostile growth behind a peak of over 1 GB);
    - the server log grows by less than 32 KiB (measured about 4.2 KB: one line per rejected request, each quoting at
      most 60 characters of a client value);
    - no step file is more than 64 KiB (the cam_extra limit) above the largest step of a request without extras;
    - the robot on its own connection gets all 15 answers meanwhile, and every bad request its short named error."""
    limit_mb = 16
    cam_dir = tmp_path / "cam"
    files = [
        "--checkpoint-dir", str(tiny_policy_files.checkpoint), "--dtype", "float32",
        "--paligemma-tokenizer", str(tiny_policy_files.paligemma_tokenizer),
        "--fast-tokenizer", str(tiny_policy_files.fast_tokenizer),
        "--max-message-mb", str(limit_mb), "--cam.every-k", "1", "--cam.dir", str(cam_dir),
        "--cam.save-frames", "none", "--cam.check-patches", "0",
    ]  # fmt: skip
    with serve_subprocess(tmp_path, *files) as (proc, port, log_path):

        def reset_peak() -> int:
            Path(f"/proc/{proc.pid}/clear_refs").write_text("5")  # VmHWM := VmRSS: the next peak is this phase's
            return _proc_status_bytes(proc.pid, "VmRSS")

        robot_args = json.dumps({"port": port, "n": ROBOT_REQUESTS})
        # ~14.5 MiB: a 2250 x 2250 image, under the limit; packed as the client would.
        flood_obs = droid_obs_bytes(np.random.default_rng(3), size=(2250, 2250))
        assert 14 * 2**20 < len(flood_obs) < limit_mb * 2**20
        collect(spawn_client(client_script(WARM_OTHERS), json.dumps({"port": port})))
        with connect(f"ws://127.0.0.1:{port}", max_size=None) as warm:  # the flood's observation, once, read
            warm.recv(timeout=10)
            warm.send(flood_obs)
            warm.recv(timeout=60)
        # A hang guard, not a bound: first-use compilations slow down several-fold when a whole tier shares the cores.
        deadline = time.monotonic() + WARM_DEADLINE_S
        while get_stats(port)["policy"]["explanations"].get("completed", 0) < 3:  # all three explained and written
            assert time.monotonic() < deadline, get_stats(port)
            time.sleep(0.2)
        # Plain serving first: the robot alone (its explanations' working set is part of any peak).
        rss = reset_peak()
        plain_robot = collect(spawn_client(client_script(ROBOT), robot_args))
        plain_growth = _proc_status_bytes(proc.pid, "VmHWM") - rss
        log_before = log_path.stat().st_size
        flooder = connect(f"ws://127.0.0.1:{port}", max_size=None)
        flooder.recv(timeout=10)  # the metadata frame; replies are never read from here on
        rss = reset_peak()
        flood = threading.Thread(target=lambda: [flooder.send(flood_obs) for _ in range(FLOOD_FRAMES)], daemon=True)
        flood.start()
        clients = [
            spawn_client(client_script(ROBOT), robot_args),
            spawn_client(client_script(BAD_REQUESTS), json.dumps({"port": port})),
            spawn_client(client_script(HOSTILE_EXTRA), json.dumps({"port": port})),
        ]
        robot_result, bad_result, bloat_result = (collect(c) for c in clients)
        flood.join(120)
        deadline = time.monotonic() + 120
        expected = 3 + 2 * ROBOT_REQUESTS + 2 * len(BAD_REQUEST_EXPECTATIONS) + 3 + FLOOD_FRAMES
        while get_stats(port)["requests"] < expected:
            assert time.monotonic() < deadline, get_stats(port)
            time.sleep(0.2)
        hostile_growth = _proc_status_bytes(proc.pid, "VmHWM") - rss
        log_growth = log_path.stat().st_size - log_before
        flooder.close()
        _stop(proc, log_path)

    print(
        f"peak growth: plain {plain_growth / 2**20:.1f} MB, hostile {hostile_growth / 2**20:.1f} MB; log {log_growth} B"
    )
    assert plain_robot["shapes"] == [[10, 8]] * ROBOT_REQUESTS
    assert robot_result["shapes"] == [[10, 8]] * ROBOT_REQUESTS
    assert all(r["after_shape"] == [10, 8] for r in bad_result["results"].values()), bad_result
    assert all(r["error"] is not None and len(r["error"]) <= MAX_ERROR_CHARS for r in bad_result["results"].values())
    assert bloat_result["shapes"] == [[10, 8]] * 2 and "more than 10000 maps and lists" in bloat_result["error"]
    assert hostile_growth - plain_growth < HOSTILE_EXTRA_PEAK_FRAMES * limit_mb * 2**20, (hostile_growth, plain_growth)
    assert log_growth < 32 * 1024, log_growth
    (run_dir,) = run_dirs(cam_dir)
    run = load_run(run_dir, load_arrays=False)
    sizes = {s.seq: s.file.stat().st_size for s in run.steps}
    plain = max(sizes[s.seq] for s in run.steps if not s.meta.extra and not s.meta.extra_arrays)
    assert max(sizes.values()) <= plain + 64 * 1024, sizes
