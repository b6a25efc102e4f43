"""The side channel in serving: the very actions the policy serves, complete run directories whose maps are the
model's maps of the served call, failures explained or kept inside.

Identity checks run on the bundled demo policy, whose actions depend on the observation (asserted first in each
test), so that a side channel answering with another request's response fails them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cam_support import (
    REPLAY_CLIENT,
    GatedExplainer,
    TimedPolicy,
    WithExplainer,
    assert_pairwise_different,
    demo_obs,
    policy_part,
    strip_timing,
    write_packed,
)
from client_env import run_client
from paths import REPO_ROOT
from real_clients import get_stats, read_packed

from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.model import pi0_fast_maps
from openpi_cam.model.config import EOS_TOKEN
from openpi_cam.serving import RequestContext, msgpack_numpy
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.viz.render import RenderOptions, render_run
from openpi_cam.vocabulary import ONE_PASS_KINDS as ONE_PASS

DEMO_CAMERAS = ("base_0_rgb", "wrist_0_rgb")


def _assert_maps_close(logged: np.ndarray, direct: np.ndarray) -> None:
    """Logged vs directly computed maps of the same inputs through the same compiled program. Measured: bit-identical
    on the demo and tiny DROID models; 1e-5 of the map's peak leaves room for a different XLA fusion order only."""
    assert logged.dtype == np.float32 and logged.shape == direct.shape
    np.testing.assert_allclose(logged, direct, rtol=0, atol=1e-5 * (np.abs(direct).max() + 1e-30))


def test_real_client_side_channel_on_same_actions_and_complete_run(tmp_path, demo_policy):
    """Four different observations through the real openpi-client, with the side channel explaining each: every
    response equals in-process inference on that observation, and every logged step holds the maps of that call."""
    n = 4
    observations = [demo_obs(100 + i) for i in range(n)]
    plain = [demo_policy.infer(policy_part(o)) for o in observations]
    assert_pairwise_different([p["actions"] for p in plain])

    options = CAMOptions(
        maps=ONE_PASS,
        every_k=1,
        dir=tmp_path / "cam",
        save_frames="both",
        target="action-token",
        action_index=2,
    )
    wrapped = wrap_policy_with_cam(demo_policy, options, run_config={"config": "demo_reach"}, checkpoint="demo")
    server = start_server_in_thread(wrapped, metadata=demo_policy.metadata)
    wire = tmp_path / "wire"
    wire.mkdir()
    for i, obs in enumerate(observations):
        write_packed(wire / f"obs{i}.msgpack", obs)
    try:
        run_client(REPLAY_CLIENT, json.dumps({"port": server.port, "dir": str(wire), "n": n}))
        stats = get_stats(server.port)
    finally:
        server.stop()  # closes the wrapper: drains the queue and writes the final manifest

    for i in range(n):
        served = read_packed(wire / f"response{i}.msgpack")
        local = strip_timing(plain[i])
        assert set(strip_timing(served)) == set(local)
        for key, value in local.items():
            assert served[key].dtype == np.asarray(value).dtype, key
            np.testing.assert_array_equal(served[key], value, err_msg=f"response {i}, {key}")
    assert stats["policy"]["explanations"]["scheduled"] == n  # side-channel counters reach the server's /stats
    assert wrapped.stats()["explanations"]["completed"] == n

    run = load_run(wrapped.run_dir)
    assert [s.meta.step for s in run.steps] == list(range(n))
    assert run.manifest["closed"] and run.manifest["counters"]["external"]["completed"] == n
    model = demo_policy.explainer.model
    for obs, step in zip(observations, run.steps, strict=True):
        _, trace = demo_policy.infer_traced(policy_part(obs))
        generated = np.asarray(trace.output)
        # The logged model inputs are those of this very request.
        np.testing.assert_array_equal(step.inputs["output"], generated)
        np.testing.assert_array_equal(
            step.inputs["tokenized_prompt"], np.asarray(trace.observation.tokenized_prompt)[0]
        )
        np.testing.assert_array_equal(step.inputs["state"], np.asarray(trace.observation.state)[0])
        action_steps = demo_policy.explainer.tokenizer.action_token_steps(generated)
        assert len(action_steps) > 2
        direct = pi0_fast_maps.gradcam_for_action_token(model, trace.observation, generated[None], int(action_steps[2]))
        assert set(step.map_kinds) == {"gradcam", "gradnorm"}
        for cam in DEMO_CAMERAS:
            _assert_maps_close(step.maps_of("gradcam")[cam], direct.by_kind["gradcam"][cam][0])
            _assert_maps_close(step.maps_of("gradnorm")[cam], direct.by_kind["gradnorm"][cam][0])
            assert step.maps_of("gradcam")[cam].shape == (4, 4)
        # 64 px client images are the model's images (no resize): raw and model frames both equal what was sent.
        for cam, key in (("base_0_rgb", "observation/image"), ("wrist_0_rgb", "observation/wrist_image")):
            np.testing.assert_array_equal(step.frames[cam], obs[key])
            np.testing.assert_array_equal(step.model_frames[cam], obs[key])
            assert step.meta.cameras[cam].obs_key == key
        meta = step.meta
        assert meta.target == "action-token" and meta.malformed is None
        assert meta.decode_steps == (int(action_steps[2]),) and meta.action_indices == (2,)
        assert meta.token_ids == (int(generated[action_steps[2]]),)
        assert meta.score == pytest.approx(float(direct.score[0]), rel=1e-5)
        assert meta.prompt == obs["prompt"] and meta.connection.startswith("conn")
        # Numeric arrays are stored as arrays (dtype and shape kept), the rest as JSON in meta.
        assert meta.extra_arrays == ("block_boxes", "target_box")
        assert "target_box" not in meta.extra and meta.extra["block_colors"] == obs["cam_extra/block_colors"]
        for key in ("target_box", "block_boxes"):
            sent, stored = obs[f"cam_extra/{key}"], step.extra[key]
            assert stored.dtype == sent.dtype and stored.shape == sent.shape
            np.testing.assert_array_equal(stored, sent)


@pytest.mark.parametrize("every_k", [0, 1, 2])
def test_side_channel_on_or_off_serves_the_plain_bytes(tmp_path, demo_policy, every_k):
    """In process, each of several different observations gets exactly the bytes the plain policy sends, whether
    the call is explained (traced path) or not (plain path)."""
    observations = [policy_part(demo_obs(200 + i)) for i in range(4)]
    plain = [msgpack_numpy.packb(strip_timing(demo_policy.infer(o))) for o in observations]
    assert len(set(plain)) == len(plain)
    wrapped = wrap_policy_with_cam(
        demo_policy, CAMOptions(maps=ONE_PASS, every_k=every_k, dir=tmp_path, save_frames="none")
    )
    try:
        for obs, expected in zip(observations, plain, strict=True):
            assert msgpack_numpy.packb(strip_timing(wrapped.infer(obs))) == expected
    finally:
        wrapped.close(120)
    scheduled = {0: 0, 1: 4, 2: 2}[every_k]
    assert wrapped.stats()["explanations"].get("scheduled", 0) == scheduled
    assert len(load_run(wrapped.run_dir).steps) == scheduled


def test_schedule_is_per_connection_and_every_k(demo_policy, tmp_path):
    wrapped = wrap_policy_with_cam(demo_policy, CAMOptions(maps=ONE_PASS, every_k=2, dir=tmp_path, save_frames="none"))
    for i in range(3):
        for conn in ("a", "b"):
            wrapped.infer(demo_obs(i), RequestContext(conn, i))
    wrapped.close(120)
    run = load_run(wrapped.run_dir)
    assert sorted((s.meta.connection, s.meta.step) for s in run.steps) == [("a", 0), ("a", 2), ("b", 0), ("b", 2)]
    assert all(not s.frames and not s.model_frames for s in run.steps)


@pytest.mark.slow
def test_multi_token_and_chunk_targets_log_the_models_maps(demo_policy, tmp_path):
    """`all-action-tokens` logs one map per action token and `chunk` one map of the summed log-probabilities, equal
    to direct calls of the model's map functions on the call's exact inputs."""
    obs = demo_obs(3)
    _, trace = demo_policy.infer_traced(policy_part(obs))
    generated = np.asarray(trace.output)
    steps = demo_policy.explainer.tokenizer.action_token_steps(generated)
    assert len(steps) == 20  # the demo's FAST chunks are 20 ids
    model = demo_policy.explainer.model
    # `logits=False` as the side channel calls it: the direct maps come from the program that served the logged ones.
    direct = {
        "all-action-tokens": pi0_fast_maps.maps_for_steps(
            model, trace.observation, generated[None], steps, logits=False
        ),
        "chunk": pi0_fast_maps.maps_for_chunk(model, trace.observation, generated[None], steps),
    }
    for target, want in direct.items():
        options = CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path / target, save_frames="none", target=target)
        wrapped = wrap_policy_with_cam(demo_policy, options)
        wrapped.infer(obs)
        wrapped.close(300)
        (step,) = load_run(wrapped.run_dir).steps
        assert step.meta.target == target and step.meta.decode_steps == tuple(int(s) for s in steps)
        assert step.meta.action_indices == tuple(range(20))
        for cam in DEMO_CAMERAS:
            _assert_maps_close(step.maps_of("gradcam")[cam], want.by_kind["gradcam"][cam][0])
            _assert_maps_close(step.maps_of("gradnorm")[cam], want.by_kind["gradnorm"][cam][0])
        if target == "chunk":
            assert step.maps_of("gradcam")["base_0_rgb"].shape == (4, 4)
            assert step.meta.score == pytest.approx(float(want.score[0]), rel=1e-5) and step.meta.score < 0
        else:
            assert step.maps_of("gradcam")["base_0_rgb"].shape == (20, 4, 4)
            np.testing.assert_allclose(step.meta.score, want.score[0], rtol=1e-5)


def test_failures_stay_inside_the_side_channel(demo_policy, tmp_path):
    observations = [policy_part(demo_obs(300 + i)) for i in range(2)]
    expected = [demo_policy.infer(o)["actions"] for o in observations]
    assert_pairwise_different(expected)
    # The explainer raising: counted, nothing logged, responses untouched.
    failing = GatedExplainer(demo_policy.explainer, fail=True)
    wrapped = wrap_policy_with_cam(
        WithExplainer(demo_policy, failing), CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path / "a")
    )
    for obs, want in zip(observations, expected, strict=True):
        np.testing.assert_array_equal(wrapped.infer(obs)["actions"], want)
    wrapped.close(30)
    assert failing.calls == 2 and wrapped.stats()["explanations"]["failed_RuntimeError"] == 2
    assert load_run(wrapped.run_dir).steps == []
    # An unwritable run directory: serving goes on with the side channel disabled.
    (tmp_path / "file").write_text("not a directory")
    disabled = wrap_policy_with_cam(demo_policy, CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path / "file" / "cam"))
    for obs, want in zip(observations, expected, strict=True):
        np.testing.assert_array_equal(disabled.infer(obs)["actions"], want)
    assert disabled.run_dir is None and disabled.stats()["explanations"]["disabled_logger_unavailable"] == 1
    disabled.close(1)


def test_malformed_generation_is_explained_logged_and_reported(tmp_path, tiny_droid_policy):
    """Issue #15: the upstream tiny DROID model never writes `Action: `. Served through the real server and client
    with the side channel on every request, each request still leaves a readable step: maps of the generated tokens
    (target `generated-tokens`), the policy's reason in `malformed`, and the step under "failures" in the report."""
    rng = np.random.default_rng(15)
    observations = [
        {
            "observation/exterior_image_1_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
            "observation/wrist_image_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
            "observation/joint_position": rng.uniform(-1, 1, 7),
            "observation/gripper_position": rng.uniform(0, 1, 1),
            "prompt": "pick up the red block",
        }
        for _ in range(2)
    ]
    wire = tmp_path / "wire"
    wire.mkdir()
    for i, obs in enumerate(observations):
        write_packed(wire / f"obs{i}.msgpack", obs)
    options = CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path / "cam", save_frames="model", target="action-token")
    wrapped = wrap_policy_with_cam(tiny_droid_policy, options)
    server = start_server_in_thread(wrapped, metadata=tiny_droid_policy.metadata)
    try:
        run_client(REPLAY_CLIENT, json.dumps({"port": server.port, "dir": str(wire), "n": len(observations)}))
        stats = get_stats(server.port)
    finally:
        server.stop()
    counters = wrapped.stats()["explanations"]
    assert counters["completed"] == 2 and counters["explained_malformed"] == 2

    run = load_run(wrapped.run_dir)
    assert len(run.steps) == 2 and not run.problems
    model = tiny_droid_policy.explainer.model
    for obs, step in zip(observations, run.steps, strict=True):
        _, trace = tiny_droid_policy.infer_traced(obs)
        assert trace.malformed_reason is not None
        assert step.meta.malformed == trace.malformed_reason
        assert trace.malformed_reason in stats["policy"]["malformed"]  # the reason the policy counted
        assert step.meta.target == "generated-tokens"
        generated = np.asarray(trace.output)
        np.testing.assert_array_equal(step.inputs["output"], generated)
        # Every emitted token, up to and including the first EOS (all of them when there is none).
        eos = np.flatnonzero(generated == EOS_TOKEN)
        emitted = np.arange(eos[0] + 1 if eos.size else generated.size)
        assert step.meta.decode_steps == tuple(emitted.tolist())
        direct = pi0_fast_maps.maps_for_chunk(model, trace.observation, generated[None], emitted)
        for cam in ("base_0_rgb", "base_1_rgb", "wrist_0_rgb"):
            assert step.maps_of("gradcam")[cam].shape == (16, 16)
            _assert_maps_close(step.maps_of("gradcam")[cam], direct.by_kind["gradcam"][cam][0])
            _assert_maps_close(step.maps_of("gradnorm")[cam], direct.by_kind["gradnorm"][cam][0])
        assert step.meta.score == pytest.approx(float(direct.score[0]), rel=1e-5)
        assert run.manifest["steps"][step.seq]["malformed"] == trace.malformed_reason

    result = render_run(run, tmp_path / "render", RenderOptions(videos=False, progress=False))
    doc = result.report.read_text()
    failures = doc[doc.index('<section class="failures"') : doc.index("</section>", doc.index('id="failures"'))]
    assert "failures (2)" in failures
    for step in run.steps:
        assert f'href="#step-{step.seq}"' in failures
        assert f'<section class="step failure" id="step-{step.seq}"' in doc
    assert f'<code class="reason">{run.steps[0].meta.malformed}</code>' in failures
    assert '<code class="target">generated-tokens</code>' in failures
    assert "2 of 2 steps" in doc


def test_slow_worker_and_full_queue_never_block_responses(demo_policy, tmp_path):
    gated = GatedExplainer(demo_policy.explainer)
    wrapped = wrap_policy_with_cam(
        WithExplainer(demo_policy, gated),
        CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, queue_size=1),
    )
    observations = [policy_part(demo_obs(400 + i)) for i in range(4)]
    expected = [demo_policy.infer(o)["actions"] for o in observations]
    assert_pairwise_different(expected)
    np.testing.assert_array_equal(wrapped.infer(observations[0])["actions"], expected[0])
    assert gated.entered.wait(60)  # the worker now holds job 1, blocked
    for obs, want in zip(observations[1:], expected[1:], strict=True):
        # job 2 fills the queue, jobs 3 and 4 each push out the older one pending; every response comes back
        # meanwhile, and it is its own
        np.testing.assert_array_equal(wrapped.infer(obs)["actions"], want)
    counters = wrapped.stats()["explanations"]
    assert counters["scheduled"] == 4 and counters["dropped_queue_full"] == 2 and counters.get("completed", 0) == 0
    gated.gate.set()
    wrapped.close(120)
    counters = wrapped.stats()["explanations"]
    assert counters["completed"] == 2
    run = load_run(wrapped.run_dir)
    assert [s.meta.step for s in run.steps] == [0, 3]  # the newest job was kept
    assert run.manifest["counters"]["external"]["dropped_queue_full"] == 2


def _wait_completed(wrapped, n: int, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while wrapped.stats()["explanations"].get("completed", 0) < n and time.monotonic() < deadline:
        time.sleep(0.01)
    assert wrapped.stats()["explanations"].get("completed", 0) >= n, f"{n} steps not written within {timeout} s"


@pytest.mark.parametrize("settle_ms", [0.0, 5.0])
def test_the_worker_never_starts_a_job_while_an_inference_runs(demo_policy, tmp_path, settle_ms):
    """Issue 19, "a side channel the robot cannot feel": a robot-like caller infers with short pauses while the
    worker explains. The side channel's own timings say when each explanation and each step's write began; none began
    inside an inference interval recorded by the policy itself (which `CAMPolicy.infer`'s bracket encloses), nor
    within `settle_ms` after one ended. An inference may still begin while an explanation runs: an explanation is one
    compiled call, not pre-emptible.

    Checked against the rule's absence (settle_ms=0, pauses of 1-3 ms only): with the worker's wait for "no inference
    in flight" before a job removed (it then takes its next job as soon as it finishes one), this test failed in 4 of
    4 runs, 6 or more of the 48 explanations starting mid-inference; with the wait before the write also removed,
    most writes did."""
    timed = TimedPolicy(demo_policy)
    options = CAMOptions(
        maps=ONE_PASS,
        every_k=1,
        dir=tmp_path,
        save_frames="none",
        queue_size=64,
        per_connection=None,
        settle_ms=settle_ms,
    )
    wrapped = wrap_policy_with_cam(timed, options)
    observations = [policy_part(demo_obs(500 + i)) for i in range(4)]
    n = 48
    try:
        wrapped.infer(observations[0], RequestContext("warm-up", 0))  # compiles the explanation before the loop
        _wait_completed(wrapped, 1)
        for i in range(n):
            wrapped.infer(observations[i % 4], RequestContext("robot", i))
            # Pauses shorter than an explanation: the worker gets gaps and a backlog, and its jobs end at varied
            # points of the next inference. Every 8th pause is longer than the settle time, so the check below
            # is not vacuous with one either.
            time.sleep(0.03 if settle_ms and i % 8 == 7 else 0.001 * (1 + i % 3))
        last_end = timed.intervals[-1][1]
    finally:
        wrapped.close(120)
    timings = [t for t in wrapped.timings() if t.connection == "robot"]
    assert len(timings) == n and all(t.written is not None for t in timings)  # every job explained and written
    assert len(timed.intervals) == n + 1
    settle_s = settle_ms / 1000.0
    inside = [
        (t.step, phase)
        for t in timings
        for phase, at in (("explain", t.started), ("write", t.writing))
        if any(start < at < end + settle_s for start, end in timed.intervals)
    ]
    assert inside == [], f"phases begun while an inference ran or within settle_ms after: {inside}"
    # Not vacuous: the worker worked between the inferences, not only in the drain after the last one.
    assert sum(t.started < last_end for t in timings) >= 2


@pytest.mark.parametrize("per_connection", [None, 1])
def test_a_flooding_connection_cannot_starve_a_quiet_one(demo_policy, tmp_path, per_connection):
    """Issue 19: with the worker busy (held at a gate), one connection sends ten requests and another one; the quiet
    connection's step is still explained, and pending jobs are served oldest first. By default (no per-connection
    limit) the full queue drops the flooder's oldest job each time; with `per_connection=1` each of the flooder's jobs
    supersedes the one before.

    This test (the default case) fails on the side channel before this rule (commit 825f2c2: one FIFO queue that
    dropped whatever arrived when full): the flooder's jobs 1-2 filled the queue, the quiet connection's job was
    dropped and only flood 0-2 were logged."""
    gated = GatedExplainer(demo_policy.explainer)
    options = CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, save_frames="none", queue_size=2)
    if per_connection is not None:
        options = dataclasses.replace(options, per_connection=per_connection)
    wrapped = wrap_policy_with_cam(WithExplainer(demo_policy, gated), options)
    observations = [policy_part(demo_obs(600 + i)) for i in range(2)]
    try:
        wrapped.infer(observations[0], RequestContext("flood", 0))
        assert gated.entered.wait(60)  # the worker holds flood's job 0: every later job stays pending
        for i in range(1, 6):
            wrapped.infer(observations[i % 2], RequestContext("flood", i))
        wrapped.infer(observations[0], RequestContext("quiet", 0))
        for i in range(6, 10):
            wrapped.infer(observations[i % 2], RequestContext("flood", i))
        pending = wrapped.stats()["explanations"]
    finally:
        gated.gate.set()
        wrapped.close(120)
    logged = [(s.meta.connection, s.meta.step) for s in load_run(wrapped.run_dir).steps]
    assert ("quiet", 0) in logged, f"the quiet connection starved: {logged}"
    assert logged == [("flood", 0), ("quiet", 0), ("flood", 9)]  # quiet's inference ended before flood 9's
    # Default: flood 3-9 and quiet 0 each arrived at the cap, each time pushing out flood's oldest pending job.
    # per_connection=1: flood 2-9 each superseded the one before; never more than 2 pending, so nothing dropped.
    reason, other = (
        ("dropped_queue_full", "superseded") if per_connection is None else ("superseded", "dropped_queue_full")
    )
    assert pending["queued"] == 2 and pending[reason] == 8 and other not in pending


def test_a_full_queue_drops_the_oldest_job_of_the_busiest_connection(demo_policy, tmp_path):
    """Without a per-connection limit, a job arriving at the cap removes the oldest pending job of the connection
    holding the most (the arriving job counts; ties go to the connection whose oldest job is oldest), so the flooder
    pays for its own surplus and the quiet connection keeps both its jobs."""
    gated = GatedExplainer(demo_policy.explainer)
    options = CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, save_frames="none", queue_size=3, per_connection=None)
    wrapped = wrap_policy_with_cam(WithExplainer(demo_policy, gated), options)
    observations = [policy_part(demo_obs(700 + i)) for i in range(2)]
    try:
        wrapped.infer(observations[0], RequestContext("flood", 0))
        assert gated.entered.wait(60)
        for i in range(1, 7):  # flood 1-3 fill the queue; 4, 5, 6 push out 1, 2, 3
            wrapped.infer(observations[i % 2], RequestContext("flood", i))
        wrapped.infer(observations[0], RequestContext("quiet", 0))  # flood holds 3 of 4: its job 4 goes
        wrapped.infer(observations[1], RequestContext("quiet", 1))  # 2 each: flood's job 5 is the older, it goes
        pending = wrapped.stats()["explanations"]
    finally:
        gated.gate.set()
        wrapped.close(120)
    logged = [(s.meta.connection, s.meta.step) for s in load_run(wrapped.run_dir).steps]
    assert logged == [("flood", 0), ("flood", 6), ("quiet", 0), ("quiet", 1)]
    assert pending["queued"] == 3 and pending["dropped_queue_full"] == 5 and "superseded" not in pending


def test_stats_report_the_explanation_lag_and_the_oldest_pending_job(demo_policy, tmp_path):
    """`/stats` says how far behind the served inferences the run is: the age of the oldest pending job, and the lag
    from an inference's end to its step on disk (p50 / p99 / max over the last written steps). Bounds come from the
    test's own clock: a job pending 50 ms (the gate held shut) is at least 50 ms old, and nothing is older than the
    test."""
    gated = GatedExplainer(demo_policy.explainer)
    wrapped = wrap_policy_with_cam(
        WithExplainer(demo_policy, gated),
        CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, save_frames="none"),
    )
    observations = [policy_part(demo_obs(800 + i)) for i in range(2)]
    start = time.monotonic()
    try:
        idle = wrapped.stats()["explanations"]
        wrapped.infer(observations[0], RequestContext("a", 0))
        assert gated.entered.wait(60)  # a's job is held: b's stays pending
        t0 = time.monotonic()
        wrapped.infer(observations[1], RequestContext("b", 0))
        time.sleep(0.05)
        waiting = wrapped.stats()["explanations"]
        t1 = time.monotonic()
    finally:
        gated.gate.set()
        wrapped.close(120)
    end = time.monotonic()
    assert idle["queued"] == 0 and idle["lag_ms"] is None and idle["oldest_pending_ms"] is None
    assert waiting["queued"] == 1 and waiting["lag_ms"] is None  # nothing written yet
    assert 50.0 <= waiting["oldest_pending_ms"] <= (t1 - t0) * 1000.0
    done = wrapped.stats()["explanations"]
    assert done["completed"] == 2 and done["queued"] == 0 and done["oldest_pending_ms"] is None
    lags = sorted(t.lag_ms for t in wrapped.timings())
    lag = done["lag_ms"]
    assert lag["window"] == 2 and lag["max"] == lags[-1] and lag["p50"] == pytest.approx(float(np.median(lags)))
    assert lag["p50"] <= lag["p99"] <= lag["max"]
    assert lags[0] >= 50.0 and lags[-1] <= (end - start) * 1000.0  # both jobs waited out the shut gate


def test_disk_failure_mid_run_is_counted_and_earlier_steps_survive(demo_policy, tmp_path):
    wrapped = wrap_policy_with_cam(demo_policy, CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, save_frames="none"))
    wrapped.infer(demo_obs(6))
    deadline = time.time() + 120
    while wrapped.stats()["explanations"].get("completed", 0) < 1 and time.time() < deadline:
        time.sleep(0.05)
    steps_dir = wrapped.run_dir / "steps"
    saved = {p.name: p.read_bytes() for p in steps_dir.iterdir()}
    assert len(saved) == 1
    moved = tmp_path / "moved_steps"
    steps_dir.rename(moved)
    steps_dir.write_text("the disk went away")  # a file where the directory was: writes now fail for real
    wrapped.infer(demo_obs(7))
    wrapped.close(120)
    counters = wrapped.stats()["explanations"]
    assert counters["completed"] == 1 and counters["not_logged"] == 1
    assert counters["logger"]["io_errors"] == {"not_a_directory": 1}
    assert {p.name: p.read_bytes() for p in moved.iterdir()} == saved


# The loop pauses like a robot executing its chunk: the side channel explains only in pauses (settle_ms).
KILL_SCRIPT = r"""
import sys
import time
sys.path.insert(0, sys.argv[2])
from cam_support import demo_obs
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
options = CAMOptions(maps=("gradcam", "gradnorm"), every_k=1, dir=sys.argv[1], queue_size=64)
wrapped = wrap_policy_with_cam(model_spec.create_demo_policy(), options)
print(wrapped.run_dir, flush=True)
i = 0
while True:
    wrapped.infer(demo_obs(i)); i += 1
    time.sleep(0.03)
"""


def test_kill_9_mid_run_leaves_every_completed_step_readable(tmp_path):
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen(
        [sys.executable, "-c", KILL_SCRIPT, str(tmp_path), str(Path(__file__).parent)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
        env=env,
    )
    try:
        run_dir = Path(proc.stdout.readline().strip())
        deadline = time.time() + 240
        while time.time() < deadline and len(list((run_dir / "steps").glob("*.npz"))) < 3:
            time.sleep(0.1)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    written = sorted((run_dir / "steps").glob("*.npz"))
    assert len(written) >= 3
    run = load_run(run_dir)
    assert [s.seq for s in run.steps] == list(range(len(written))) and not run.problems
    logged_steps = [s.meta.step for s in run.steps]
    assert logged_steps == sorted(set(logged_steps))  # in order; a full queue drops the oldest, so there may be gaps
    for step in run.steps:
        for kind in ("gradcam", "gradnorm"):
            m = step.maps_of(kind)["base_0_rgb"]
            assert m.shape == (4, 4) and np.isfinite(m).all()


def test_float_channels_first_client_images_are_logged_as_uint8_frames(demo_policy, tmp_path):
    wrapped = wrap_policy_with_cam(demo_policy, CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, save_frames="raw"))
    obs = demo_obs(8)
    image = obs["observation/image"]
    as_float_chw = {**obs, "observation/image": np.moveaxis(image, -1, 0) / 255.0}
    wrapped.infer(as_float_chw)
    wrapped.infer(obs)
    wrapped.close(120)
    assert wrapped.stats()["explanations"]["completed"] == 2
    first, second = load_run(wrapped.run_dir).steps
    np.testing.assert_array_equal(first.frames["base_0_rgb"], image)
    np.testing.assert_array_equal(second.frames["base_0_rgb"], image)


def test_cam_extra_values_are_bounded_per_value_and_per_step(tmp_path, demo_policy):
    """A client cannot make the server store megabytes per request through `cam_extra/`: values over the limits are
    dropped, named in the step's `extra_dropped` and counted; the rest is kept; the response is the policy's."""
    obs = demo_obs(300)
    big = {"cam_extra/blob": "x" * 1_000_000, "cam_extra/huge_array": np.zeros(100_000, np.float32)}
    options = CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path, save_frames="none", max_extra_kb=2_000 / 1024)
    wrapped = wrap_policy_with_cam(demo_policy, options)
    filler = {f"cam_extra/note{i}": "y" * 400 for i in range(8)}  # 8 x ~410 bytes: the last ones pass 2,000 bytes
    try:
        response = wrapped.infer({**obs, **big, **filler})
    finally:
        wrapped.close()
    np.testing.assert_array_equal(response["actions"], demo_policy.infer(policy_part(obs))["actions"])
    (step,) = load_run(wrapped.run_dir).steps
    extra = step.extra
    np.testing.assert_array_equal(extra["target_box"], obs["cam_extra/target_box"])  # small values kept as sent
    assert "blob" not in extra and "huge_array" not in extra and step.meta.extra_arrays == ("block_boxes", "target_box")
    kept_notes = [k for k in extra if k.startswith("note")]
    assert 0 < len(kept_notes) < 8 and extra["extra_dropped"][:2] == ["blob", "huge_array"]
    assert set(extra["extra_dropped"][2:]) == {f"note{i}" for i in range(8)} - set(kept_notes)
    assert wrapped.stats()["explanations"]["extra_dropped"] == 1
    assert "/" not in wrapped.stats()["explanations"]["run"]  # /stats names the run, not the server's paths


# Counts the XLA compilations of the first request and its explanation in a fresh interpreter (the compiled-program
# caches of this test process are warm already).
_FIRST_REQUEST_COMPILES = r"""
import json, sys, tempfile
import jax.monitoring
compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: compiles.append(name) if name.endswith("backend_compile_duration") else None
)
from demo_inputs import demo_observation
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.serving import RequestContext

one_pass = CAMOptions(maps=("gradcam", "gradnorm"), every_k=1, dir=tempfile.mkdtemp())
cam = wrap_policy_with_cam(model_spec.create_demo_policy(), one_pass)
warmed = None if sys.argv[1] == "cold" else cam.warm_up((1, 2, 4) if sys.argv[1] == "warm-batched" else (1,))
before = len(compiles)
cam.infer(demo_observation(5))
single = len(compiles) - before
# Then three robots at once, as batched serving calls it (three rows run at batch size 4).
cam.infer_batch([demo_observation(s) for s in (6, 7, 8)], [RequestContext(f"conn{i}", 0) for i in range(3)])
batch = len(compiles) - before - single
cam.close(120)
print(json.dumps({"warmed": warmed, "single": single, "batch": batch, "stats": cam.stats()["explanations"]}))
"""


@pytest.mark.slow
def test_warm_up_compiles_what_the_first_request_and_its_explanation_need():
    """`serve` warms up before listening: after `CAMPolicy.warm_up()` the first request and its explanation compile
    nothing, and with batched serving's sizes warmed (1, 2, 4) neither does a batch of three. Without the warm-up the
    same script counts compilations (18 + 4 measured), and a batch size that was not warmed compiles, so each check
    can fail."""
    counts = {}
    for mode in ("cold", "warm", "warm-batched"):
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(REPO_ROOT / "tests" / "support"), str(REPO_ROOT / "src")]),
        }
        proc = subprocess.run(
            [sys.executable, "-c", _FIRST_REQUEST_COMPILES, mode], capture_output=True, text=True, env=env, timeout=300
        )
        assert proc.returncode == 0, proc.stderr
        counts[mode] = json.loads(proc.stdout.strip().splitlines()[-1])
        assert counts[mode]["stats"]["completed"] == 4, counts[mode]  # every request was explained in every mode
    assert counts["cold"]["single"] > 0, counts
    assert counts["warm"]["warmed"] == "inference and the action-token explanation with its spot check", counts
    assert counts["warm"]["single"] == 0 and counts["warm"]["batch"] > 0, counts
    assert counts["warm-batched"]["single"] == 0 and counts["warm-batched"]["batch"] == 0, counts


def test_warm_up_leaves_the_served_rng_stream_and_counters_alone():
    """pi0.5 draws its noise from the policy's rng: a warmed-up policy serves the first request exactly as a fresh one
    does (the same observation served twice gives different actions, so a consumed rng split would show)."""

    obs = policy_part(demo_obs(7))
    warmed, fresh = model_spec.create_demo_policy(model="pi05"), model_spec.create_demo_policy(model="pi05")
    assert warmed.warm_up() is not None
    first = fresh.infer(obs)["actions"]
    assert not np.array_equal(fresh.infer(obs)["actions"], first)  # the stream moves between calls
    np.testing.assert_array_equal(warmed.infer(obs)["actions"], first)
    assert warmed.stats() == {"requests": 1, "malformed": {}}


# Two host devices: the side channel explains on device 1 while an inference on device 0 is held in flight.
_CAM_DEVICE = r"""
import json, sys, tempfile, threading, time
sys.path[:0] = sys.argv[1:2]
import jax, numpy as np
from cam_support import WithExplainer, demo_obs, policy_part
from openpi_cam.cam.batching import explain_traces
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.vocabulary import ONE_PASS_KINDS as ONE_PASS
from openpi_cam.vocabulary import ExplainOptions


class HeldPolicy(WithExplainer):
    # The real policy; its plain (unscheduled) inference waits at a gate, so an inference stays in flight.
    def __init__(self, policy):
        super().__init__(policy, policy.explainer)
        self.gate, self.entered = threading.Event(), threading.Event()

    def infer(self, obs, context=None):
        self.entered.set()
        self.gate.wait(120)
        return self.inner.infer(obs, context)


policy = model_spec.create_demo_policy()
results = {}
for mode in sys.argv[2:]:  # each mode wraps the same policy anew
    held = HeldPolicy(policy)
    options = CAMOptions(maps=ONE_PASS, every_k=2, dir=tempfile.mkdtemp(), device=1 if mode == "device" else None)
    cam = wrap_policy_with_cam(held, options)
    observation = policy_part(demo_obs(3))
    served = cam.infer(observation)  # step 0: explained (every_k=2)
    in_flight = threading.Thread(target=cam.infer, args=(policy_part(demo_obs(4)),))  # step 1: not explained, held
    in_flight.start()
    held.entered.wait(60)
    # Long enough to compile and explain on a loaded machine (the shared device's worker is waiting, not slow).
    deadline = time.monotonic() + (240 if mode == "device" else 15)
    while time.monotonic() < deadline and cam.stats()["explanations"].get("completed", 0) < 1:
        time.sleep(0.05)
    completed_while_held = cam.stats()["explanations"].get("completed", 0)
    held.gate.set()
    in_flight.join(120)
    cam.close(120)
    param_devices = {d.id for leaf in jax.tree.leaves(cam._explainer.model.params) for d in leaf.devices()}
    _, trace = policy.infer_traced(observation)
    (reference,) = explain_traces(policy.explainer, [trace], options.explanation)
    from openpi_cam.cam.run_format import load_run
    (step,) = load_run(cam.run_dir).steps
    results[mode] = {
        "devices": len(jax.devices()),
        "completed_while_held": completed_while_held,
        "param_devices": sorted(param_devices),
        "same_actions": bool(np.array_equal(served["actions"], policy.infer(observation)["actions"])),
        "max_map_diff": max(float(np.abs(step.maps_of(k)[c] - reference.maps[k][c]).max())
                            for k in reference.maps for c in reference.maps[k]),
    }
print(json.dumps(results))
"""


@pytest.mark.slow
def test_cam_device_explains_on_its_own_device_while_inference_runs():
    """`--cam.device 1` (two host devices here): the explainer's parameters live on device 1 only, an explanation
    completes while an inference is held in flight (on the shared device the worker waits for it, which the same
    script shows), served actions are the plain policy's and the maps those of the served device's explainer."""
    env = os.environ | {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    # Both modes in one process (one start, and the shared mode reuses the programs the first compiled on device 0):
    # the shared mode's worker has nothing left to compile, so only its wait for the held inference can keep it back.
    proc = subprocess.run(
        [sys.executable, "-c", _CAM_DEVICE, str(Path(__file__).parent), "device", "shared"],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    device, shared = results["device"], results["shared"]
    assert device["devices"] == 2 and device["param_devices"] == [1], device
    assert device["completed_while_held"] == 1 and shared["completed_while_held"] == 0, results
    assert device["same_actions"] and shared["same_actions"], results
    # Measured: 0 (the same program on another host device); maps are O(1e-2..1): 1e-5 would flag a different map.
    assert device["max_map_diff"] <= 1e-5, device


def test_serve_refuses_a_cam_device_the_machine_lacks(tmp_path, capsys):
    from openpi_cam.cli.serve import SideChannelFlags, main

    assert main(cam=SideChannelFlags(every_k=1, dir=tmp_path / "runs", device=7), warm_up=False) == 2
    assert "explanation device 7 requested, this machine has 1" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()  # refused before a run directory was created
