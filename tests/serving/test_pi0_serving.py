"""pi0.5 served to the real `openpi-client`, with the side channel off and on.

The client (openpi-client 0.1.2 from PyPI, in its own venv) sends upstream's recorded DROID observations; the server's
policy draws its noise from its rng stream, one split per call, as upstream's. The same stream in-process gives the
same actions; two different observations give different actions (checked first, so that the identity checks compare
input-dependent answers); with the side channel on the actions are bit-identical to off and every request leaves a
step whose maps explain the returned chunk from the same noise.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from client_env import run_client
from paths import GOLDEN_DIR

from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.policies.policy import create_policy
from openpi_cam.serving.server import start_server_in_thread

ROOT = GOLDEN_DIR / "tiny_policy_pi05_droid"
REQUESTS = ("case_1", "case_2", "case_1")  # the repeat gets new noise from the stream: other actions again

CLIENT = r"""
import json, sys
import numpy as np
from openpi_client import websocket_client_policy
args = json.loads(sys.argv[1])
client = websocket_client_policy.WebsocketClientPolicy(host="127.0.0.1", port=args["port"])
out = {}
for i, path in enumerate(args["observations"]):
    with np.load(path) as npz:
        obs = {k: npz[k] for k in npz.files if k != "prompt"}
        obs["prompt"] = str(npz["prompt"])
    out[f"actions_{i}"] = client.infer(obs)["actions"]
np.savez(args["out"], **out)
print(json.dumps({"ok": True}))
"""


def make_policy():
    tokenizer = ROOT / "paligemma_tokenizer_tiny.model"
    return create_policy(
        "pi05_droid", ROOT / "checkpoint", paligemma_tokenizer=tokenizer, dtype="float32", rng=jax.random.key(3)
    )


def observation(case: str) -> dict:
    with np.load(ROOT / f"{case}.npz") as npz:
        obs = {"observation/" + k[len("raw/") :]: npz[k] for k in npz.files if k.startswith("raw/")}
    prompt = json.loads((ROOT / "case.json").read_text())["cases"][case]["prompt"]
    return {**obs, "prompt": prompt}


@pytest.fixture(scope="module")
def observation_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("obs")
    paths = []
    for i, case in enumerate(REQUESTS):
        path = folder / f"{i}.npz"
        np.savez(path, **observation(case))
        paths.append(str(path))
    return paths


def serve_and_ask(served, metadata: dict, files: list[str], out) -> list[np.ndarray]:
    server = start_server_in_thread(served, metadata=metadata)
    try:
        run_client(CLIENT, json.dumps({"port": server.port, "observations": files, "out": str(out)}))
    finally:
        server.stop()
    with np.load(out) as npz:
        return [npz[f"actions_{i}"] for i in range(len(files))]


def test_real_client_gets_upstream_stream_actions_with_the_side_channel_off_and_on(observation_files, tmp_path):
    policy = make_policy()
    in_process_policy = make_policy()
    traced = [in_process_policy.infer_traced(observation(case)) for case in REQUESTS]
    expected = [response["actions"] for response, _ in traced]
    assert np.abs(expected[0] - expected[1]).max() > 0.1 and np.abs(expected[0] - expected[2]).max() > 0.1

    off = serve_and_ask(policy, policy.metadata, observation_files, tmp_path / "off.npz")
    for got, want in zip(off, expected, strict=True):
        np.testing.assert_array_equal(got, want)

    options = CAMOptions(
        maps=("gradcam", "gradnorm"),
        every_k=1,
        dir=tmp_path / "cam",
        save_frames="model",
        target="action",
        action_index=2,
        action_dim_index=1,
        queue_size=8,
    )
    cam = wrap_policy_with_cam(make_policy(), options)
    on = serve_and_ask(cam, policy.metadata, observation_files, tmp_path / "on.npz")
    for got, want in zip(on, expected, strict=True):
        np.testing.assert_array_equal(got, want)

    run = load_run(cam.run_dir)
    assert len(run.steps) == len(REQUESTS)
    for step, (_, trace) in zip(run.steps, traced, strict=True):
        assert step.meta.target == "action" and step.meta.action_index == (2, 1)
        assert set(step.maps_of("gradnorm")) == {"base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"}
        assert step.maps_of("gradnorm")["base_0_rgb"].shape == (16, 16)
        assert not step.maps_of("gradnorm")["right_wrist_0_rgb"].any()  # the masked blank camera: exactly zero
        assert step.maps_of("gradnorm")["base_0_rgb"].max() > 0
        # The step holds this call's own noise and raw output, and the explanation re-ran the denoising from that
        # noise: its x_0 is the returned chunk to float32 re-evaluation error (5e-5 of the largest value, as in
        # tests/model/test_pi0.py).
        np.testing.assert_array_equal(step.inputs["noise"], trace.sample_inputs["noise"])
        np.testing.assert_array_equal(step.inputs["output"], trace.output)
        assert step.meta.details["replay_max_abs_diff"] <= 5e-5 * np.abs(trace.output).max()
