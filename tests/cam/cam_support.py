"""Helpers of the cam tests: demo-robot observations, a policy seen through another explainer, gated and failing
explainers, and the openpi-client script that replays packed observations over the wire.

The bundled demo policy is the workhorse here: it is cheap, well formed, and its actions depend on the observation,
so "same actions" checks can tell one request's response from another's.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.demo import bundled, task
from openpi_cam.policies.family import Explainer
from openpi_cam.serving import msgpack_numpy


def demo_obs(seed: int) -> dict[str, Any]:
    """What the demo robot sends for a fresh scene (with its `cam_extra/` ground truth)."""
    rng = np.random.default_rng(seed)
    scene = task.random_scene(rng)
    return bundled.client_observation(task.observe(scene, task.random_start(rng, scene)), scene)


def policy_part(obs: dict[str, Any]) -> dict[str, Any]:
    """The observation without its `cam_extra/` keys (what the policy itself receives)."""
    return {k: v for k, v in obs.items() if not k.startswith("cam_extra/")}


def strip_timing(response: dict) -> dict:
    return {k: v for k, v in response.items() if k not in ("policy_timing", "server_timing")}


def assert_pairwise_different(actions: list[np.ndarray]) -> None:
    """The precondition of every identity check: no two observations share their actions."""
    for i in range(len(actions)):
        for j in range(i + 1, len(actions)):
            assert not np.array_equal(actions[i], actions[j]), f"observations {i} and {j} gave the same actions"


class WithExplainer:
    """A real policy served as is, whose side-channel explainer is replaced (a gated or failing one)."""

    def __init__(self, policy: Any, explainer: Explainer) -> None:
        self.inner = policy
        self.explainer = explainer

    @property
    def metadata(self) -> dict:
        return self.inner.metadata

    def infer(self, obs: dict, context: object = None) -> dict:
        return self.inner.infer(obs, context)

    def infer_traced(self, obs: dict) -> tuple[dict, Any]:
        return self.inner.infer_traced(obs)

    def stats(self) -> dict:
        return self.inner.stats()

    def close(self, timeout: float | None = None) -> None:
        pass


class TimedPolicy(WithExplainer):
    """A real policy served as is, recording when each of its inferences ran (`time.monotonic()` intervals)."""

    def __init__(self, policy: Any) -> None:
        super().__init__(policy, policy.explainer)
        self.intervals: list[tuple[float, float]] = []

    def infer(self, obs: dict, context: object = None) -> dict:
        start = time.monotonic()
        try:
            return self.inner.infer(obs, context)
        finally:
            self.intervals.append((start, time.monotonic()))

    def infer_traced(self, obs: dict) -> tuple[dict, Any]:
        start = time.monotonic()
        try:
            return self.inner.infer_traced(obs)
        finally:
            self.intervals.append((start, time.monotonic()))


class GatedExplainer:
    """The policy's real explainer, held at a gate (a slow worker) or raising (a failing one)."""

    def __init__(self, inner: Explainer, *, fail: bool = False) -> None:
        self.inner, self.fail = inner, fail
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.calls = 0

    @property
    def camera_grid(self) -> tuple[int, int]:
        return self.inner.camera_grid

    @property
    def family(self) -> str:
        return self.inner.family

    @property
    def targets(self) -> tuple[str, ...]:
        return self.inner.targets

    @property
    def default_target(self) -> str:
        return self.inner.default_target

    def on_mesh(self, mesh: Any) -> GatedExplainer:
        return self

    def explain(self, observation: Any, outputs: Any, request: Any, sample_inputs: Any) -> list:
        self.calls += 1
        self.entered.set()
        if self.fail:
            raise RuntimeError("injected explainer failure")
        assert self.gate.wait(120), "the test never opened the gate"
        return self.inner.explain(observation, outputs, request, sample_inputs)


def write_packed(path: Path, value: Any) -> None:
    path.write_bytes(msgpack_numpy.packb(value))


# Run in the client venv (numpy<2, the real openpi-client): sends every packed observation in ARGS["dir"], in order,
# on one connection, and writes each response next to it.
REPLAY_CLIENT = r"""
import json, pathlib, sys
from openpi_client import msgpack_numpy, websocket_client_policy

ARGS = json.loads(sys.argv[1])
folder = pathlib.Path(ARGS["dir"])
policy = websocket_client_policy.WebsocketClientPolicy(host="127.0.0.1", port=ARGS["port"])
for i in range(ARGS["n"]):
    obs = msgpack_numpy.unpackb((folder / f"obs{i}.msgpack").read_bytes())
    (folder / f"response{i}.msgpack").write_bytes(msgpack_numpy.packb(policy.infer(obs)))
print(json.dumps({"sent": ARGS["n"]}))
"""
