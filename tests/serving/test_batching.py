"""Batched fleet serving (`--batch-window-ms`): several connections' requests in one model call, each row answered
exactly as serving it alone answers it.

Every identity check runs on inputs whose answers differ (`demo_observations` asserts it for the bundled pi0-FAST
policy; the pi0.5 check below asserts it too), so a server that mixed up rows, or answered every row with one row's
actions, fails.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import pytest
from demo_inputs import demo_observation
from real_clients import N_CLIENTS, REQUESTS_PER_CLIENT, get_stats, serve_concurrent_clients, wrong_answers
from websockets.sync.client import connect

from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.errors import InvalidRequest
from openpi_cam.policies.policy import batch_bucket
from openpi_cam.serving import RequestContext, msgpack_numpy
from openpi_cam.serving.server import start_server_in_thread

# Long enough that the clients' simultaneous requests (released together by a barrier) land in one window even on a
# loaded 2-core machine; the batch closes early once full anyway.
WINDOW_MS = 300.0


def test_batch_buckets_are_powers_of_two():
    assert [batch_bucket(n) for n in (1, 2, 3, 4, 5, 8, 9)] == [1, 2, 4, 4, 8, 8, 16]
    with pytest.raises(ValueError, match="at least one request"):
        batch_bucket(0)


def test_real_clients_served_in_batches_get_what_serving_alone_gives(demo_policy, demo_observations, tmp_path):
    alone = [demo_policy.infer(obs)["actions"] for obs in demo_observations]  # pairwise different (fixture)
    running = start_server_in_thread(
        demo_policy, close_policy_on_stop=False, batch_window_ms=WINDOW_MS, max_batch=N_CLIENTS
    )
    try:
        received = serve_concurrent_clients(running.port, tmp_path, demo_observations)
        batching = get_stats(running.port)["batching"]
    finally:
        running.stop()
    assert wrong_answers(received, alone) == []
    # The requests really were served together: fewer model calls than requests, and some of more than one row.
    assert batching["requests"] == N_CLIENTS * REQUESTS_PER_CLIENT
    assert batching["batches"] < batching["requests"] and max(int(s) for s in batching["sizes"]) > 1, batching


def test_a_bad_request_in_a_batch_gets_its_own_error_and_the_others_their_actions(demo_policy, demo_observations):
    observations = [demo_observations[0], {"state": "not an observation"}, demo_observations[1], 7]
    results = demo_policy.infer_batch_traced(observations)
    assert isinstance(results[1], Exception) and isinstance(results[3], InvalidRequest)
    for i in (0, 2):
        np.testing.assert_array_equal(results[i][0]["actions"], demo_policy.infer(observations[i])["actions"])


def test_the_side_channel_passes_a_bad_batch_row_to_the_policy_to_refuse(demo_policy, demo_observations, tmp_path):
    """Through the side channel too, a row that is not an observation gets the policy's named error (not an internal
    one), and the rows around it their own actions and steps."""
    cam = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=1, dir=tmp_path))
    contexts = [RequestContext(f"conn{i}", 0) for i in range(3)]
    try:
        results = cam.infer_batch([demo_observations[0], 7, demo_observations[1]], contexts)
    finally:
        cam.close(120)
    assert isinstance(results[1], InvalidRequest) and "must be a dict" in str(results[1])
    for i, obs in ((0, demo_observations[0]), (2, demo_observations[1])):
        np.testing.assert_array_equal(results[i]["actions"], demo_policy.infer(obs)["actions"])
    assert sorted(s.meta.connection for s in load_run(cam.run_dir).steps) == ["conn0", "conn2"]


def test_flow_matching_batches_keep_each_requests_noise_and_the_rng_stream():
    """pi0.5 draws noise per request: row i of a batch uses the noise request i would have drawn served i-th, and the
    policy's rng ends where serving the requests one by one leaves it (the next single request gets the same noise).
    Batched matrix products round differently, so actions agree to float32 rounding: measured max |difference| 6.4e-8
    on these requests (actions of size ~0.1); bound 1e-6, far below the ~1e-2 that a wrong noise row produces."""
    serial, batched = (model_spec.create_demo_policy(model="pi05") for _ in range(2))
    observations = [demo_observation(seed) for seed in range(5)]
    one_by_one = [serial.infer_traced(obs) for obs in observations]
    together = batched.infer_batch_traced(observations)
    actions = [r[0]["actions"] for r in one_by_one]
    assert min(np.abs(a - b).max() for i, a in enumerate(actions) for b in actions[:i]) > 1e-3
    for (response, trace), result in zip(one_by_one, together, strict=True):
        assert not isinstance(result, Exception)
        np.testing.assert_array_equal(result[1].sample_inputs["noise"], trace.sample_inputs["noise"])
        np.testing.assert_allclose(result[0]["actions"], response["actions"], rtol=0, atol=1e-6)
    after = observations[0]
    np.testing.assert_array_equal(serial.infer(after)["actions"], batched.infer(after)["actions"])


def test_side_channel_explains_batched_requests_per_connection(demo_policy, demo_observations, tmp_path):
    """Batched rows are explained like single requests: every request of every connection has its step, numbered
    per connection, and each step's generation is that request's own."""
    cam = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=1, dir=tmp_path / "runs", queue_size=64))
    running = start_server_in_thread(cam, batch_window_ms=WINDOW_MS, max_batch=N_CLIENTS)
    try:
        serve_concurrent_clients(running.port, tmp_path, demo_observations)
    finally:
        running.stop()
    run = load_run(cam.run_dir)
    steps = sorted((s.meta.connection, s.meta.step) for s in run.steps)
    assert steps == sorted((f"conn{c:04d}", j) for c in range(N_CLIENTS) for j in range(REQUESTS_PER_CLIENT))
    # Client i sends observation (i + j) % 4 as its j-th request: each observation is served three times.
    own = [demo_policy.infer_traced(obs)[1].output.tobytes() for obs in demo_observations]
    explained = collections.Counter(s.arrays().inputs["output"].tobytes() for s in run.steps)
    assert explained == collections.Counter({o: REQUESTS_PER_CLIENT for o in own})


def test_a_lone_robot_does_not_wait_for_the_window(demo_policy, demo_observations):
    """With one connection open nobody could join its batch: it is served at once, not after the window (5 s here,
    against ~0.1 s of inference; the bound leaves 2.5 s for a loaded machine)."""
    running = start_server_in_thread(demo_policy, close_policy_on_stop=False, batch_window_ms=5000.0, max_batch=4)
    try:
        with connect(running.url, max_size=None, compression=None) as ws:
            ws.recv()  # metadata
            for obs in demo_observations[:2]:
                start = time.monotonic()
                ws.send(msgpack_numpy.packb(obs))
                reply = msgpack_numpy.unpackb(ws.recv())
                assert time.monotonic() - start < 2.5
                np.testing.assert_array_equal(reply["actions"], demo_policy.infer(obs)["actions"])
    finally:
        running.stop()


def test_serve_refuses_a_batch_size_that_is_not_a_power_of_two(capsys):
    from openpi_cam.cli.serve import main

    assert main(batch_window_ms=5.0, max_batch=6) == 2
    assert "--max-batch a power of two" in capsys.readouterr().err
