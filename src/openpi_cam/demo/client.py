"""The robot's side: a minimal client of the policy server (the openpi-client protocol: msgpack-numpy over
websockets), and where a robot records its rollouts (`RolloutSink`)."""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import Any, Protocol

from websockets.sync.client import ClientConnection, connect

from openpi_cam.serving import msgpack_numpy


class PolicyClient:
    """Connects, reads the server's metadata frame, then answers `infer(obs)` with the server's action dict."""

    def __init__(self, url: str, *, open_timeout: float = 30.0) -> None:
        self._stack = contextlib.ExitStack()
        self._ws: ClientConnection = self._stack.enter_context(
            connect(url, compression=None, max_size=None, open_timeout=open_timeout)
        )
        self.metadata: dict[str, Any] = msgpack_numpy.unpackb(self._ws.recv())

    def infer(self, obs: dict[str, Any]) -> dict[str, Any]:
        self._ws.send(msgpack_numpy.packb(obs))
        reply = self._ws.recv()
        if isinstance(reply, str):  # the server sends errors as text frames
            raise RuntimeError(f"policy server error: {reply}")
        return msgpack_numpy.unpackb(reply)

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> PolicyClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RolloutSink(Protocol):
    """Where a recorded rollout goes, a step at a time (`lerobot.rollouts.RolloutRecorder`, composed by the command
    line): per executed action, the frame the robot saw before it (by LeRobot feature name, the action included) and
    what followed it, as lerobot-eval records evaluation episodes."""

    def step(self, frame: Mapping[str, Any], *, task: str, reward: float, success: bool, done: bool) -> None: ...

    def end_episode(self) -> int | None: ...
