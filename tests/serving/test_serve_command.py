"""`openpi-cam serve` as a process: start-up mistakes in one line, the bundled model, the side channel from its flags,
and SIGTERM with stalled peers or an explanation still running, within a container's stop grace period."""

from __future__ import annotations

import datetime as dt
import json
import signal
import subprocess
import time

import numpy as np
import pytest
from client_env import collect, spawn_client
from demo_inputs import demo_observation
from paths import REPO_ROOT
from real_clients import (
    client_script,
    get_stats,
    read_packed,
    responses,
    send_observations,
)
from serve_process import serve_cmd as _serve_cmd
from serve_process import serve_subprocess
from serve_process import stop as _stop
from serving_support import ROBOT, assert_same_response, run_dirs, stalled_peer

from openpi_cam.cam.batching import explain_traces
from openpi_cam.cam.run_format import MANIFEST_JSON, load_run, read_json
from openpi_cam.checkpoints import model_spec
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.policies import demo_reach
from openpi_cam.serving.server import (
    PEER_TIMEOUT_S,
)
from openpi_cam.vocabulary import ExplainOptions


def test_serve_reports_missing_files_without_traceback(tiny_policy_files, tmp_path):
    missing_checkpoint = tmp_path / "no_such_checkpoint"
    missing_tokenizer = tmp_path / "no_such_tokenizer.model"
    for args, missing in [
        (
            [
                "--checkpoint-dir",
                str(missing_checkpoint),
                "--paligemma-tokenizer",
                str(tiny_policy_files.paligemma_tokenizer),
                "--fast-tokenizer",
                str(tiny_policy_files.fast_tokenizer),
            ],
            missing_checkpoint,
        ),
        (
            [
                "--checkpoint-dir",
                str(tiny_policy_files.checkpoint),
                "--paligemma-tokenizer",
                str(missing_tokenizer),
                "--fast-tokenizer",
                str(tiny_policy_files.fast_tokenizer),
            ],
            missing_tokenizer,
        ),
    ]:
        proc = subprocess.run(_serve_cmd(*args), capture_output=True, text=True, timeout=120, cwd=REPO_ROOT)
        assert proc.returncode != 0
        assert str(missing) in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr, proc.stderr


@pytest.mark.slow
def test_serve_without_a_checkpoint_serves_the_bundled_model_in_the_dtype_asked(demo_policy, tmp_path):
    """No --checkpoint-dir: the bundled demo model. `--dtype bfloat16` must reach it: on scenes where bf16 changes
    the actions (about 1 in 12 demo scenes), the served actions are the in-process bf16 policy's, not float32's."""
    bf16 = model_spec.create_demo_policy(dtype="bfloat16")
    observations = []
    for seed in range(100, 400):
        obs = demo_observation(seed)
        if not np.array_equal(bf16.infer(obs)["actions"], demo_policy.infer(obs)["actions"]):
            observations.append(obs)
            if len(observations) == 2:
                break
    assert len(observations) == 2, "no demo scene whose actions bfloat16 changes"
    with serve_subprocess(tmp_path, "--dtype", "bfloat16") as (proc, port, log_path):
        collect(send_observations(port, tmp_path / "client", observations))
        _stop(proc, log_path)
    assert read_packed(tmp_path / "client" / "metadata.msgpack") == {}  # demo_reach declares no metadata
    for served, obs in zip(responses(tmp_path / "client", 2), observations, strict=True):
        assert_same_response(served, bf16.infer(obs))  # the same program on this machine: bit for bit
        assert not np.array_equal(served["actions"], demo_policy.infer(obs)["actions"])


def test_serve_with_cam_flags_writes_an_explained_closed_run(demo_observations, tmp_path):
    """A checkpoint given by flags, and the side channel on: the client gets the policy's actions, and after SIGTERM
    the run directory holds one explained step per request (the maps of that request) and a closed manifest."""
    cam_dir = tmp_path / "cam"
    files = [
        "--checkpoint-dir", str(demo_reach.CHECKPOINT), "--config", demo_reach.DEMO_CONFIG.name, "--dtype", "float32",
        "--paligemma-tokenizer", str(demo_reach.PALIGEMMA_TOKENIZER),
        "--fast-tokenizer", str(demo_reach.FAST_TOKENIZER),
    ]  # fmt: skip
    cam = ["--cam.every-k", "1", "--cam.dir", str(cam_dir), "--cam.target", "action-token", "--cam.action-index", "2"]
    cam += ["--cam.per-connection", "4", "--cam.settle-ms", "5", "--cam.check-patches", "2"]
    cam += ["--cam.maps", "gradcam", "gradnorm"]
    # The side channel explains in the client's pauses and at shutdown; the first explanation compiles (seconds on a
    # loaded 2-core machine), more than the 5 s default drain of a container stop: this test wants every step.
    cam += ["--drain-timeout", "120"]
    observations = demo_observations[:3]
    with serve_subprocess(tmp_path, *files, *cam) as (proc, port, log_path):
        # Compiled before /healthz answered (tests/cam checks that the first request then compiles nothing).
        assert "warmed up inference and the action-token explanation with its spot check in" in log_path.read_text()
        collect(send_observations(port, tmp_path / "client", observations))
        _stop(proc, log_path)
    # In process, the policy exactly as `serve` builds it from those flags (one ModelSpec, as every command).
    policy = ModelSpec(
        demo_reach.CHECKPOINT,
        demo_reach.DEMO_CONFIG.name,
        paligemma_tokenizer=demo_reach.PALIGEMMA_TOKENIZER,
        fast_tokenizer=demo_reach.FAST_TOKENIZER,
        dtype="float32",
    ).create()
    (run_dir,) = run_dirs(cam_dir)
    manifest = read_json(run_dir / MANIFEST_JSON)
    assert manifest is not None and manifest["closed"] is True and manifest["num_steps"] == len(observations)
    options = manifest["options"]
    assert (options["per_connection"], options["settle_ms"], options["check_patches"]) == (4, 5.0, 2)  # flags arrived
    run = load_run(run_dir)
    assert [(s.meta.connection, s.meta.step) for s in run.steps] == [("conn0000", i) for i in range(3)]
    request = ExplainOptions("action-token", 2, maps=("gradcam", "gradnorm"))
    for step, obs, served in zip(run.steps, observations, responses(tmp_path / "client", 3), strict=True):
        local, trace = policy.infer_traced(obs)
        assert_same_response(served, local)
        np.testing.assert_array_equal(step.inputs["output"], trace.output)  # the step is this request's
        assert step.meta.target == "action-token" and step.meta.action_indices == (2,)
        assert step.meta.malformed is None
        assert all(len(c.random_patches) == 2 for c in step.meta.check.cameras.values())
        (explanation,) = explain_traces(policy.explainer, [trace], request)
        for kind in ("gradcam", "gradnorm"):
            logged = step.maps_of(kind)
            assert sorted(logged) == ["base_0_rgb", "wrist_0_rgb"]
            for camera, want in explanation.maps[kind].items():
                assert logged[camera].shape == (4, 4)
                np.testing.assert_allclose(logged[camera], want, rtol=1e-6, atol=1e-6 * np.abs(want).max())


# A container stop (docker stop, Kubernetes): SIGTERM, then SIGKILL after this grace period.
CONTAINER_GRACE_S = 10.0


@pytest.mark.slow
def test_sigterm_with_stalled_peers_exits_within_the_deadline_and_closes_the_run(demo_observations, tmp_path):
    """A container stop with three peers that stopped answering and explanations still queued: SIGTERM starts the
    side channel's drain at once, closes every connection at once (each gets PEER_TIMEOUT_S to answer the close
    frame), and exits before the grace period's SIGKILL with every queued step written and the manifest closed.

    Before: the closes ran one after another (10 s each: 30.7 s with three peers, killed mid-way, no manifest);
    then the drain waited for the closes, so the closed manifest came >= PEER_TIMEOUT_S after the signal. Now it is
    written as soon as the queue is empty, while the stalled peers are still being waited for: the bound checked is
    half of PEER_TIMEOUT_S after the signal (an empty-queue drain takes milliseconds; the first jobs here are drained
    before the signal)."""
    cam_dir = tmp_path / "cam"
    cam = ["--cam.every-k", "1", "--cam.dir", str(cam_dir), "--drain-timeout", "5"]
    with serve_subprocess(tmp_path, "--dtype", "float32", *cam) as (proc, port, log_path):
        collect(send_observations(port, tmp_path / "client", demo_observations[:2]))
        deadline = time.monotonic() + 120
        while get_stats(port)["policy"]["explanations"].get("completed", 0) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        collect(send_observations(port, tmp_path / "client2", demo_observations[2:]))  # may be queued at the signal
        peers = [stalled_peer(port) for _ in range(3)]
        signalled_at = time.time()
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            exit_code = proc.wait(CONTAINER_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            log = log_path.read_text()
            raise AssertionError(f"still running {CONTAINER_GRACE_S} s after SIGTERM:\n{log}") from None
        elapsed = time.monotonic() - start
        for peer in peers:
            peer.close()
    assert exit_code == 0, log_path.read_text()
    assert elapsed < PEER_TIMEOUT_S + 5, (elapsed, log_path.read_text())  # closes, then exit; drain in parallel
    (run_dir,) = run_dirs(cam_dir)
    manifest = read_json(run_dir / MANIFEST_JSON)
    assert manifest is not None and manifest["closed"] is True and manifest["num_steps"] == 4, manifest
    closed_at = dt.datetime.fromisoformat(manifest["updated_at"].replace("Z", "+00:00")).timestamp()
    assert closed_at - signalled_at < PEER_TIMEOUT_S / 2, (closed_at - signalled_at, log_path.read_text())


def test_sigterm_during_a_long_explanation_exits_cleanly_with_the_run_closed(tiny_policy_files, tmp_path):
    """An explanation longer than `--drain-timeout` (exhaustive occlusion on the tiny DROID checkpoint's 3 x 256
    patches: seconds per step) is still computing when the drain deadline passes. The server writes the closed
    manifest, says so, and exits with 0 without the interpreter's teardown: a teardown under a running XLA computation
    can abort the process ("terminate called after throwing an instance of ..."; seen at the end of a demo run whose
    drain passed its deadline), and whether it does depends on timing, so the log line is what is checked."""
    cam_dir = tmp_path / "cam"
    files = [
        "--checkpoint-dir", str(tiny_policy_files.checkpoint), "--dtype", "float32",
        "--paligemma-tokenizer", str(tiny_policy_files.paligemma_tokenizer),
        "--fast-tokenizer", str(tiny_policy_files.fast_tokenizer),
        "--cam.every-k", "1", "--cam.dir", str(cam_dir), "--cam.maps", "occlusion", "--drain-timeout", "0.5",
        "--no-warm-up",
    ]  # fmt: skip
    with serve_subprocess(tmp_path, *files) as (proc, port, log_path):
        assert collect(spawn_client(client_script(ROBOT), json.dumps({"port": port, "n": 1})))["shapes"] == [[10, 8]]
        time.sleep(1.0)  # the explanation (and its compilation) is under way
        proc.send_signal(signal.SIGTERM)
        exit_code = proc.wait(CONTAINER_GRACE_S)
    log = log_path.read_text()
    assert exit_code == 0, log
    assert "exiting with an explanation still computing" in log
    (run_dir,) = run_dirs(cam_dir)
    manifest = read_json(run_dir / MANIFEST_JSON)
    assert manifest is not None and manifest["closed"] is True and manifest["num_steps"] == 0
    assert manifest["counters"]["external"]["unfinished_at_shutdown"] == 1


def test_serve_records_each_connection_as_an_episode_of_a_lerobot_dataset(demo_observations, tmp_path):
    """`serve --record DIR`: two robots' connections become two episodes of a LeRobot v3.0 dataset, each frame holding
    what its request sent (frames, state, the `cam_extra/` box, the prompt as its task) and the chunk it got; our
    reader opens it (LeRobot's own reader is checked outside CI: benchmarks/check_lerobot_reads.py)."""
    from openpi_cam.lerobot.dataset import open_dataset

    root = tmp_path / "served"
    boxed = [
        obs | {"cam_extra/target_box": np.arange(4, dtype=np.float32) + i} for i, obs in enumerate(demo_observations)
    ]
    sent = [boxed[:3], boxed[3:] + boxed[:1]]
    with serve_subprocess(tmp_path, "--record", str(root), "--record-fps", "5") as (proc, port, log_path):
        for i, observations in enumerate(sent):  # one connection after the other: episode i
            collect(send_observations(port, tmp_path / f"robot{i}", observations))
        _stop(proc, log_path)
    dataset = open_dataset(root)
    assert dataset.fps == 5 and dataset.episodes == [0, 1]
    assert {"observation.image", "observation.wrist_image", "observation.state", "target_box", "action"} <= set(
        dataset.features
    )
    for episode, observations in enumerate(sent):
        frames = list(dataset.frames(episode))
        answers = responses(tmp_path / f"robot{episode}", len(observations))
        assert len(frames) == len(observations)
        for frame, obs, answer in zip(frames, observations, answers, strict=True):
            assert frame["task"] == obs["prompt"]
            np.testing.assert_allclose(frame["observation.state"], obs["observation/state"], rtol=1e-6)
            np.testing.assert_allclose(frame["target_box"], obs["cam_extra/target_box"], rtol=1e-6)
            np.testing.assert_array_equal(frame["action"], np.asarray(answer["actions"], np.float32)[0])
            np.testing.assert_array_equal(frame["action.chunk"], np.asarray(answer["actions"], np.float32).ravel())
            # AV1 video: a lossy copy of the frame sent (the LeRobot-written datasets differ by 2.7 of 255 on average).
            error = np.abs(frame["observation.image"].astype(float) - obs["observation/image"].astype(float)).mean()
            assert error < 8.0, error
