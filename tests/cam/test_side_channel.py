"""The Grad-CAM side channel in serving: same actions, complete run directories, failures that stay inside.

The tiny upstream DROID model never writes `Action: `; `FixedGeneration` (tests/fixed_generation.py) swaps in
upstream's hand-made well-formed generation so there are action tokens to explain.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from client_env import collect, spawn_client
from fixed_generation import FixedGeneration
from openpi_cam.cam.engine import explain
from openpi_cam.cam.reader import load_run
from openpi_cam.cam.wrapper import CAMOptions, wrap_policy_with_cam
from paths import REPO_ROOT
from test_serving import CLIENT_PRELUDE, get_stats, read_packed

from openpi_cam.cam.records import model_frame_uint8
from openpi_cam.serving import RequestContext, msgpack_numpy
from openpi_cam.serving.server import start_server_in_thread


class GatedModel:
    """The real model whose Grad-CAM waits for a gate (a slow worker) or raises (a failing one)."""

    def __init__(self, model: Any, *, fail: bool = False):
        self.model, self.fail = model, fail
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.config = model.config

    def gradcam_for_action_token(self, *args, **kwargs):
        self.entered.set()
        if self.fail:
            raise RuntimeError("injected Grad-CAM failure")
        assert self.gate.wait(60)
        return self.model.gradcam_for_action_token(*args, **kwargs)


@pytest.fixture(scope="module")
def hand_tokens(golden_dir) -> np.ndarray:
    return np.load(golden_dir / "tiny_policy_droid" / "droid_case.npz")["hand/generated_tokens"]


@pytest.fixture(scope="module")
def hand_policy(tiny_droid_policy, hand_tokens):
    return FixedGeneration(tiny_droid_policy, hand_tokens)


def droid_obs(seed: int, size=(180, 320)) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observation/exterior_image_1_left": rng.integers(0, 256, (*size, 3), dtype=np.uint8),
        "observation/wrist_image_left": rng.integers(0, 256, (*size, 3), dtype=np.uint8),
        "observation/joint_position": rng.uniform(-1, 1, 7),
        "observation/gripper_position": rng.uniform(0, 1, 1),
        "prompt": "pick up the red block",
    }


def strip_timing(response: dict) -> dict:
    return {k: v for k, v in response.items() if k not in ("policy_timing", "server_timing")}


CAM_ROUND_TRIP = r"""
policy = connect()
rng = np.random.RandomState(ARGS["seed"])
for i in range(ARGS["n"]):
    obs = droid_obs(rng, size=(180, 320))
    obs["cam_extra/target_box"] = np.array([1, 2, 3, 4])
    write(ARGS["out"] + f"/obs{i}.msgpack", obs)
    write(ARGS["out"] + f"/response{i}.msgpack", policy.infer(obs))
done(n=ARGS["n"])
"""


def test_real_client_side_channel_on_same_actions_and_complete_run(tmp_path, tiny_droid_policy, hand_policy):
    options = CAMOptions(every_k=1, cam_dir=tmp_path / "cam", save_frames="both", target="action-token", action_index=2)
    wrapped = wrap_policy_with_cam(hand_policy, options, run_config={"config": "pi0_fast_droid"}, checkpoint="tiny")
    server = start_server_in_thread(wrapped)
    out = tmp_path / "client"
    out.mkdir()
    try:
        n = 3
        collect(
            spawn_client(
                CLIENT_PRELUDE + CAM_ROUND_TRIP, json.dumps({"port": server.port, "out": str(out), "seed": 1, "n": n})
            )
        )
        stats = get_stats(server.port)
    finally:
        server.stop()  # closes the wrapper: drains the queue and writes the final manifest
    # Actions bit-identical to plain in-process inference on the same decoded observations.
    for i in range(n):
        obs = read_packed(out / f"obs{i}.msgpack")
        obs = {k: v for k, v in obs.items() if not k.startswith("cam_extra/")}
        served = read_packed(out / f"response{i}.msgpack")
        np.testing.assert_array_equal(served["actions"], tiny_droid_policy.infer(obs)["actions"])
    assert stats["policy"]["gradcam"]["scheduled"] == n  # counters reach the server's /stats
    assert wrapped.stats()["gradcam"]["completed"] == n

    run = load_run(wrapped.run_dir)
    assert [s.meta["step"] for s in run.steps] == list(range(n))
    assert run.manifest["counters"]["external"]["completed"] == n
    steps = hand_policy.tokenizer.action_token_steps(hand_policy.tokens)
    for i, step in enumerate(run.steps):
        obs = {k: v for k, v in read_packed(out / f"obs{i}.msgpack").items() if not k.startswith("cam_extra/")}
        _, trace = tiny_droid_policy.infer_traced(obs)
        direct = tiny_droid_policy.model.gradcam_for_action_token(trace.observation, hand_policy.tokens, int(steps[2]))
        for cam in ("base_0_rgb", "base_1_rgb", "wrist_0_rgb"):
            logged = step.maps[cam]
            assert logged.dtype == np.float32 and logged.shape == (16, 16)
            np.testing.assert_allclose(logged, direct.maps[cam][0], rtol=0, atol=1e-5 * (np.abs(logged).max() + 1e-12))
            logged = step.gradnorm_maps[cam]
            assert logged.dtype == np.float32 and logged.shape == (16, 16)
            np.testing.assert_allclose(logged, direct.gradnorm_maps[cam][0], rtol=0, atol=1e-5 * (logged.max() + 1e-12))
            np.testing.assert_array_equal(step.model_frames[cam], model_frame_uint8(trace.observation.images[cam]))
        np.testing.assert_array_equal(step.frames["base_0_rgb"], obs["observation/exterior_image_1_left"])
        np.testing.assert_array_equal(step.frames["wrist_0_rgb"], obs["observation/wrist_image_left"])
        assert "base_1_rgb" not in step.frames  # DROID synthesises that camera: no client frame exists
        meta = step.meta
        assert meta["token_ids"] == [int(hand_policy.tokens[steps[2]])]
        assert meta["decode_steps"] == [int(steps[2])] and meta["action_indices"] == [2]
        assert meta["cameras"]["base_0_rgb"]["obs_key"] == "observation/exterior_image_1_left"
        assert meta["cameras"]["base_1_rgb"]["obs_key"] is None
        geometry = meta["cameras"]["base_0_rgb"]["geometry"]
        assert (geometry["orig_h"], geometry["orig_w"], geometry["resized_h"], geometry["pad_top"]) == (
            180,
            320,
            126,
            49,
        )
        assert meta["extra"] == {"target_box": [1, 2, 3, 4]}
        assert meta["prompt"] == obs["prompt"] and meta["connection"].startswith("conn")


def test_side_channel_off_returns_plain_bytes(tiny_droid_policy, tmp_path):
    wrapped = wrap_policy_with_cam(tiny_droid_policy, CAMOptions(every_k=0, cam_dir=tmp_path))
    obs = droid_obs(0)
    plain = msgpack_numpy.packb(strip_timing(tiny_droid_policy.infer(obs)))
    assert msgpack_numpy.packb(strip_timing(wrapped.infer(obs))) == plain
    on = wrap_policy_with_cam(tiny_droid_policy, CAMOptions(every_k=1, cam_dir=tmp_path))
    assert msgpack_numpy.packb(strip_timing(on.infer(obs))) == plain
    on.close(30)
    wrapped.close(1)


def test_schedule_is_per_connection_and_every_k(hand_policy, tmp_path):
    wrapped = wrap_policy_with_cam(hand_policy, CAMOptions(every_k=2, cam_dir=tmp_path, save_frames="none"))
    for i in range(3):
        for conn in ("a", "b"):
            wrapped.infer(droid_obs(i), RequestContext(conn, i))
    wrapped.close(120)
    run = load_run(wrapped.run_dir)
    assert sorted((s.meta["connection"], s.meta["step"]) for s in run.steps) == [("a", 0), ("a", 2), ("b", 0), ("b", 2)]
    assert all(not s.frames and not s.model_frames for s in run.steps)


def test_multi_token_and_chunk_targets(hand_policy, tmp_path):
    steps = hand_policy.tokenizer.action_token_steps(hand_policy.tokens)
    _, trace = hand_policy.infer_traced(droid_obs(3))
    stack = explain(
        hand_policy.model, hand_policy.tokenizer, trace.observation, trace.generated_tokens, target="all-action-tokens"
    )
    assert stack.maps["base_0_rgb"].shape == (len(steps), 16, 16)
    assert stack.decode_steps == [int(s) for s in steps] and stack.action_indices == list(range(len(steps)))
    single = explain(
        hand_policy.model,
        hand_policy.tokenizer,
        trace.observation,
        trace.generated_tokens,
        target="action-token",
        action_index=5,
    )
    scale = np.abs(single.maps["wrist_0_rgb"]).max()
    np.testing.assert_allclose(stack.maps["wrist_0_rgb"][5], single.maps["wrist_0_rgb"], atol=1e-4 * scale)
    chunk = explain(hand_policy.model, hand_policy.tokenizer, trace.observation, trace.generated_tokens, target="chunk")
    assert chunk.maps["base_0_rgb"].shape == (16, 16) and isinstance(chunk.score, float) and chunk.score < 0


def test_failures_stay_inside_the_side_channel(tiny_droid_policy, hand_tokens, tmp_path):
    obs = droid_obs(4)
    expected = tiny_droid_policy.infer(obs)["actions"]
    # Grad-CAM raising.
    failing = FixedGeneration(tiny_droid_policy, hand_tokens, GatedModel(tiny_droid_policy.model, fail=True))
    wrapped = wrap_policy_with_cam(failing, CAMOptions(every_k=1, cam_dir=tmp_path / "a"))
    for _ in range(2):
        np.testing.assert_array_equal(wrapped.infer(obs)["actions"], expected)
    wrapped.close(30)
    assert wrapped.stats()["gradcam"]["failed_RuntimeError"] == 2
    assert load_run(wrapped.run_dir).steps == []
    # A generation without action tokens (the random model's own): skipped and counted, never an error.
    plain = wrap_policy_with_cam(tiny_droid_policy, CAMOptions(every_k=1, cam_dir=tmp_path / "b"))
    np.testing.assert_array_equal(plain.infer(obs)["actions"], expected)
    plain.close(30)
    assert plain.stats()["gradcam"]["skipped_no_action_tokens"] == 1
    # An unwritable run directory: serving goes on with the side channel disabled.
    (tmp_path / "file").write_text("not a directory")
    disabled = wrap_policy_with_cam(tiny_droid_policy, CAMOptions(every_k=1, cam_dir=tmp_path / "file" / "cam"))
    np.testing.assert_array_equal(disabled.infer(obs)["actions"], expected)
    assert disabled.stats()["gradcam"]["disabled_logger_unavailable"] == 1
    disabled.close(1)


def test_slow_worker_and_full_queue_never_block_responses(tiny_droid_policy, hand_tokens, tmp_path):
    gated = GatedModel(tiny_droid_policy.model)
    wrapped = wrap_policy_with_cam(
        FixedGeneration(tiny_droid_policy, hand_tokens, gated), CAMOptions(every_k=1, cam_dir=tmp_path, queue_size=1)
    )
    obs = droid_obs(5)
    wrapped.infer(obs)
    assert gated.entered.wait(60)  # the worker now holds job 1, blocked
    for _ in range(3):  # job 2 fills the queue, jobs 3-4 are dropped; every response comes back meanwhile
        wrapped.infer(obs)
    counters = wrapped.stats()["gradcam"]
    assert counters["scheduled"] == 4 and counters["dropped_queue_full"] == 2 and counters.get("completed", 0) == 0
    gated.gate.set()
    wrapped.close(120)
    counters = wrapped.stats()["gradcam"]
    assert counters["completed"] == 2
    assert load_run(wrapped.run_dir).manifest["counters"]["external"]["dropped_queue_full"] == 2


def test_disk_failure_mid_run_is_counted_and_earlier_steps_survive(hand_policy, tmp_path):
    wrapped = wrap_policy_with_cam(hand_policy, CAMOptions(every_k=1, cam_dir=tmp_path, save_frames="none"))
    wrapped.infer(droid_obs(6))
    deadline = time.time() + 120
    while wrapped.stats()["gradcam"].get("completed", 0) < 1 and time.time() < deadline:
        time.sleep(0.1)
    steps_dir = wrapped.run_dir / "steps"
    saved = sorted(steps_dir.iterdir())
    moved = tmp_path / "moved_steps"
    steps_dir.rename(moved)
    steps_dir.write_text("the disk went away")  # a file where the directory was: writes now fail for real
    wrapped.infer(droid_obs(7))
    wrapped.close(120)
    counters = wrapped.stats()["gradcam"]
    assert counters["completed"] == 1 and counters["not_logged"] == 1
    assert sum(counters["logger"]["io_errors"].values()) >= 1
    assert [p.name for p in sorted(moved.iterdir())] == [p.name for p in saved]


KILL_SCRIPT = r"""
import sys, time, numpy as np
sys.path.insert(0, sys.argv[3])
from fixed_generation import FixedGeneration
from test_cam_wrapper import droid_obs
from openpi_cam.cam.wrapper import CAMOptions, wrap_policy_with_cam
from openpi_cam.policies.policy import create_policy
golden = sys.argv[1]
policy = create_policy(
    "pi0_fast_droid", golden + "/checkpoint", paligemma_tokenizer=golden + "/paligemma_tokenizer_tiny.model",
    fast_tokenizer=golden + "/fast_tokenizer", dtype="float32",
)
tokens = np.load(golden + "/droid_case.npz")["hand/generated_tokens"]
options = CAMOptions(every_k=1, cam_dir=sys.argv[2], queue_size=64)
wrapped = wrap_policy_with_cam(FixedGeneration(policy, tokens), options)
print(wrapped.run_dir, flush=True)
i = 0
while True:
    wrapped.infer(droid_obs(i)); i += 1
"""


def test_kill_9_mid_run_leaves_every_completed_step_readable(golden_dir, tmp_path):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            KILL_SCRIPT,
            str(golden_dir / "tiny_policy_droid"),
            str(tmp_path),
            str(REPO_ROOT / "tests" / "support"),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
    )
    try:
        run_dir = Path(proc.stdout.readline().strip())
        deadline = time.time() + 240
        while time.time() < deadline and len(list((run_dir / "steps").glob("*.npz"))) < 3:
            time.sleep(0.2)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    written = sorted((run_dir / "steps").glob("*.npz"))
    assert len(written) >= 3
    run = load_run(run_dir)
    assert [s.seq for s in run.steps] == list(range(len(written)))
    for step in run.steps:
        assert step.maps["base_0_rgb"].shape == (16, 16) and np.isfinite(step.maps["base_0_rgb"]).all()


def test_float_channels_first_client_images_are_logged_as_uint8_frames(hand_policy, tmp_path):
    wrapped = wrap_policy_with_cam(hand_policy, CAMOptions(every_k=1, cam_dir=tmp_path, save_frames="raw"))
    obs = droid_obs(8, size=(224, 224))
    as_float_chw = {
        **obs,
        "observation/exterior_image_1_left": np.moveaxis(obs["observation/exterior_image_1_left"], -1, 0) / 255.0,
    }
    wrapped.infer(as_float_chw)
    wrapped.infer(obs)
    wrapped.close(120)
    assert wrapped.stats()["gradcam"]["completed"] == 2
    first, second = load_run(wrapped.run_dir).steps
    np.testing.assert_array_equal(first.frames["base_0_rgb"], obs["observation/exterior_image_1_left"])
    np.testing.assert_array_equal(second.frames["base_0_rgb"], obs["observation/exterior_image_1_left"])
