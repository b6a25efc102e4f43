"""The websocket server against the real `openpi-client` (PyPI, in its own numpy<2 venv) and real policies.

Every client below is a small script run with `.venv-client/bin/python` against a server on 127.0.0.1 with an
OS-assigned port, the way a robot computer would talk to us. Whatever checks that a client got *its* actions runs on
the bundled demo policy, whose actions depend on the observation (`demo_observations` asserts they differ); upstream's
tiny DROID policy answers every request with the same fallback chunk, so with it the served model output is compared
instead."""

from __future__ import annotations

import asyncio
import itertools
import json
import threading
from typing import Any

import numpy as np
import pytest
from client_env import collect, run_client
from real_clients import (
    N_CLIENTS,
    REQUESTS_PER_CLIENT,
    client_script,
    read_packed,
    responses,
    round_trip,
    send_observations,
    serve_concurrent_clients,
    wrong_answers,
)
from serving_support import GatedPolicy, TracingPolicy, assert_same_response

from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.policies import demo_reach
from openpi_cam.serving import msgpack_numpy
from openpi_cam.serving.server import (
    PolicyServer,
    RunningServer,
    start_server_in_thread,
)


def test_real_client_gets_metadata_and_its_own_actions(server, demo_policy, demo_observations, metadata, tmp_path):
    collect(send_observations(server.port, tmp_path, demo_observations))
    got = read_packed(tmp_path / "metadata.msgpack")
    assert set(got) == set(metadata)
    assert got["probe_array"].dtype == np.dtype(">i2")
    np.testing.assert_array_equal(got["probe_array"], metadata["probe_array"])
    assert type(got["probe_scalar"]) is np.float32 and got["probe_scalar"] == 0.5

    served = responses(tmp_path, len(demo_observations))
    for response, obs in zip(served, demo_observations, strict=True):
        assert_same_response(response, demo_policy.infer(obs))
    first, second = served[:2]
    assert first["actions"].shape == (demo_reach.ACTION_HORIZON, 2)
    # Like upstream: only the second request on a connection knows the previous request's total time.
    assert set(first["server_timing"]) == {"infer_ms"}
    assert set(second["server_timing"]) == {"infer_ms", "prev_total_ms"}
    assert second["server_timing"]["prev_total_ms"] >= first["server_timing"]["infer_ms"] > 0


def test_real_client_bytes_equal_ours(tmp_path):
    """Our packer writes the same bytes as openpi-client's for what it sends (maps keep key order)."""
    body = r"""
obs = aloha_obs(np.random.RandomState(3))
obs.update(scalar=np.float32(1.5), flag=np.bool_(True), count=np.int64(-7), text=np.str_("hi"), nested=[1, {"a": b"x"}])
write(ARGS["out"] + "/obs.msgpack", obs)
done(ok=True)
"""
    run_client(client_script(body), json.dumps({"out": str(tmp_path)}))
    client_bytes = (tmp_path / "obs.msgpack").read_bytes()
    decoded = msgpack_numpy.unpackb(client_bytes)
    assert type(decoded["scalar"]) is np.float32 and decoded["images"]["cam_high"].shape == (3, 224, 224)
    assert msgpack_numpy.packb(decoded) == client_bytes


def test_golden_droid_observation_through_the_wire(tiny_droid_policy, golden_dir, tmp_path):
    """Upstream's recorded DROID case, sent by the real client, reaches the model intact: the served generation is
    upstream's 256 tokens (which depend on the observation), and the actions upstream's."""
    case = np.load(golden_dir / "tiny_policy_droid" / "droid_case.npz")
    raw_prompt = "Pick up the red_block and put it in the bowl"
    assert json.loads((golden_dir / "tiny_policy_droid" / "case.json").read_text())["prompt"] == raw_prompt
    obs = {
        "observation/exterior_image_1_left": case["raw/exterior_image_1_left"],
        "observation/wrist_image_left": case["raw/wrist_image_left"],
        "observation/joint_position": case["raw/joint_position"],
        "observation/gripper_position": case["raw/gripper_position"],
        "prompt": raw_prompt,
    }
    # A changed observation (the exterior image mirrored) gives another generation, so matching it means something.
    mirrored = {
        **obs,
        "observation/exterior_image_1_left": np.ascontiguousarray(obs["observation/exterior_image_1_left"][:, ::-1]),
    }
    assert not np.array_equal(tiny_droid_policy.infer_traced(mirrored)[1].output, case["generated_tokens"])
    tracing = TracingPolicy(tiny_droid_policy)
    running = start_server_in_thread(tracing, close_policy_on_stop=False)
    try:
        collect(send_observations(running.port, tmp_path, [obs]))
    finally:
        running.stop()
    (output,) = tracing.outputs
    np.testing.assert_array_equal(output, case["generated_tokens"])
    (served,) = responses(tmp_path, 1)
    # Upstream computed these in float64 from the same float32 model output; 1e-6 allows float32 rounding only.
    np.testing.assert_allclose(served["actions"], case["policy_output/actions"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("env", ["libero", "aloha"])
def test_example_client_observations_for_other_robots(env, env_policies, tmp_path):
    """Upstream's example clients' observations (random images, ALOHA's channel-first) reach the model as sent: the
    served generations are the in-process ones for the decoded observations, and differ between the two requests.
    (Their random model writes no actions, so only shapes and dtypes are checked on the responses.)"""
    pol = env_policies[env]
    tracing = TracingPolicy(pol)
    running = start_server_in_thread(tracing, metadata=pol.metadata, close_policy_on_stop=False)
    try:
        collect(round_trip(running.port, tmp_path, env=env, seed=2, n=2))
    finally:
        running.stop()
    assert not np.array_equal(tracing.outputs[0], tracing.outputs[1])
    for i, served in enumerate(responses(tmp_path, 2)):
        local, trace = pol.infer_traced(read_packed(tmp_path / f"obs{i}.msgpack"))
        np.testing.assert_array_equal(tracing.outputs[i], trace.output)
        assert_same_response(served, local)
        assert served["actions"].shape == {"libero": (10, 7), "aloha": (32, 14)}[env]


def test_concurrent_clients_each_get_their_own_answer(demo_policy, demo_observations, tmp_path):
    alone = [demo_policy.infer(obs)["actions"] for obs in demo_observations]  # pairwise different (fixture)
    recorder = GatedPolicy(demo_policy)  # gate open: records which connection each request came from
    running = start_server_in_thread(recorder, close_policy_on_stop=False)
    try:
        received = serve_concurrent_clients(running.port, tmp_path, demo_observations)
    finally:
        running.stop()
    assert wrong_answers(received, alone) == []
    # The requests really overlapped: the policy saw the connections interleaved, not one after the other.
    order = [c.connection_id for c in recorder.contexts]
    assert len(order) == N_CLIENTS * REQUESTS_PER_CLIENT and len(set(order)) == N_CLIENTS
    switches = sum(a != b for a, b in itertools.pairwise(order))
    assert switches > N_CLIENTS - 1, order


class SwappingServer(PolicyServer):
    """Deliberately broken: connections 0 and 1 (2 and 3, ...) receive each other's reply to their k-th request."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._pairs: dict[tuple[int, int], dict] = {}

    async def _answer(self, frame, context, prev_total_ms, executor):
        reply, infer_ms = await super()._answer(frame, context, prev_total_ms, executor)
        me = int(context.connection_id.removeprefix("conn"))
        slot = self._pairs.setdefault((me // 2, context.request_index), {})
        slot[me] = reply
        done = slot.setdefault("both", asyncio.get_running_loop().create_future())
        if me ^ 1 in slot and not done.done():
            done.set_result(None)
        try:
            await asyncio.wait_for(asyncio.shield(done), 60)
        except TimeoutError:
            return reply, infer_ms
        return slot[me ^ 1], infer_ms


def _run_in_thread(server: PolicyServer) -> RunningServer:
    ready = threading.Event()
    thread = threading.Thread(target=lambda: asyncio.run(server.run(on_ready=lambda _: ready.set())), daemon=True)
    thread.start()
    assert ready.wait(30) and server.bound_port is not None
    return RunningServer(server=server, host="127.0.0.1", port=server.bound_port, thread=thread)


def test_the_concurrency_check_catches_a_server_that_swaps_replies(demo_policy, demo_observations, tmp_path):
    """The check above fails for a server that hands two connections each other's replies."""
    alone = [demo_policy.infer(obs)["actions"] for obs in demo_observations]
    running = _run_in_thread(SwappingServer(demo_policy, host="127.0.0.1", port=0, close_policy_on_stop=False))
    try:
        received = serve_concurrent_clients(running.port, tmp_path, demo_observations)
    finally:
        running.stop()
    assert len(wrong_answers(received, alone)) == N_CLIENTS * REQUESTS_PER_CLIENT


def test_side_channel_leaves_the_response_bytes_alone(demo_policy, demo_observations, tmp_path):
    """Through the real client, the responses of a server with the side channel off (every_k=0) and on
    (every_k=1) are byte for byte those of plain serving, timings aside."""
    plain_cam = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=0, dir=tmp_path / "cam_off"))
    on_cam = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=1, dir=tmp_path / "cam_on"))
    results = {}
    for name, served in (("plain", demo_policy), ("off", plain_cam), ("on", on_cam)):
        running = start_server_in_thread(served, close_policy_on_stop=False)
        try:
            results[name] = collect(send_observations(running.port, tmp_path / name, demo_observations))["keys"]
        finally:
            running.stop()
    on_cam.close(60)
    n = len(demo_observations)
    untimed = {name: [(tmp_path / name / f"untimed{i}.msgpack").read_bytes() for i in range(n)] for name in results}
    assert len(set(untimed["plain"])) == n  # different observations, different responses
    assert untimed["off"] == untimed["plain"] and untimed["on"] == untimed["plain"]
    assert results["off"] == results["plain"] == results["on"]  # same keys in the same order, timings included
    assert results["plain"][0] == ["actions", "policy_timing", "server_timing"]
    # The side channel did run: one explained step per request.
    assert len(load_run(on_cam.run_dir).steps) == n
