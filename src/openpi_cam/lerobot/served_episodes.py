"""Served connections recorded as episodes of a LeRobot v3.0 dataset (`serve --record DIR`): what each robot sent and
got, in LeRobot's format, where upstream's `PolicyRecorder` pickles one file per request.

Each connection is one episode and each answered request one frame of it: the request's images (uint8 [H, W, 3];
[3, H, W] and float frames are converted as the side channel stores them) and its other numeric values, under their
keys with "/" written "." (LeRobot's feature names hold no "/"; `cam_extra/` values, e.g. `next.success`, are kept
the same way), the prompt as the frame's task, and the served chunk: its first row as `action` and the whole chunk
(row-major) as `action.chunk`. The features are the first recorded frame's (`lerobot.rollouts.RolloutRecorder`); a
later request whose values do not fit them (another camera size, a missing key) is answered as always and not
recorded, counted under `skipped_<Error>` in `/stats`.

Concurrency: the server calls `infer` / `infer_batch` on its inference thread and `connection_closed` on its event
loop. A request's frame is made after its answer is computed and kept per connection under a lock; a closed
connection's episode is handed to one writer thread, which saves the episodes in the order their connections closed.
`close` lets that thread finish and finalises the dataset, after the wrapped policy has closed.
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.counters import WarnOnceCounter
from openpi_cam.image_tools import client_frame_uint8
from openpi_cam.lerobot.dataset import DatasetError
from openpi_cam.lerobot.rollouts import RolloutRecorder
from openpi_cam.nested import flatten_dict
from openpi_cam.vocabulary import EXTRA_PREFIX

logger = logging.getLogger(__name__)

ACTION = "action"
ACTION_CHUNK = "action.chunk"
PROMPT_KEYS = ("prompt", "task")
DEFAULT_MAX_FRAMES = 2000  # frames kept per connection: the writer holds an episode in memory until it is saved


def feature_name(key: str) -> str:
    """A request key as a LeRobot feature name: `observation/state` -> `observation.state`, `cam_extra/x` -> `x`."""
    return (key[len(EXTRA_PREFIX) :] if key.startswith(EXTRA_PREFIX) else key).replace("/", ".")


def _is_image(value: np.ndarray) -> bool:
    return value.ndim == 3 and 3 in (value.shape[0], value.shape[-1])


def request_frame(obs: Mapping[str, Any], actions: Any) -> tuple[dict[str, np.ndarray], str]:
    """(the frame's values by feature name, its task) of one answered request."""
    frame: dict[str, np.ndarray] = {}
    task = ""
    for key, value in flatten_dict(obs).items():
        if key in PROMPT_KEYS:
            task = value.decode() if isinstance(value, bytes) else str(value)
            continue
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            continue
        frame[feature_name(key)] = client_frame_uint8(array) if _is_image(array) else array.reshape(-1)
    chunk = np.asarray(actions, np.float32)
    frame[ACTION] = chunk.reshape(len(chunk), -1)[0]
    frame[ACTION_CHUNK] = chunk.reshape(-1)
    return frame, task


class EpisodeRecorder:
    """What `serve --record DIR` serves: the wrapped served object, answering as it does, with every connection's
    requests recorded as an episode (module docstring)."""

    def __init__(self, served: Any, root: str | Path, *, fps: int, max_frames: int = DEFAULT_MAX_FRAMES) -> None:
        self._served = served
        self._recorder = RolloutRecorder(root, fps=fps, robot_type="openpi-cam serve")
        self._max_frames = max_frames
        self._frames: dict[str, list[tuple[dict[str, np.ndarray], str]]] = collections.defaultdict(list)
        self._lock = threading.Lock()
        self._events = WarnOnceCounter(logger, "recording served episodes")
        self._episodes: queue.Queue[list[tuple[dict[str, np.ndarray], str]] | None] = queue.Queue()
        self._writer = threading.Thread(target=self._write, name="episode-writer", daemon=True)
        self._writer.start()

    @property
    def root(self) -> Path:
        return self._recorder.root

    @property
    def metadata(self) -> dict[str, Any]:
        return self._served.metadata

    def infer(self, obs: dict[str, Any], context: object = None) -> dict[str, Any]:
        response = self._served.infer(obs, context)
        self._keep(obs, response, context)
        return response

    def infer_batch(self, observations: Sequence[dict[str, Any]], contexts: Sequence[object]) -> list[Any]:
        responses = self._served.infer_batch(observations, contexts)
        for obs, response, context in zip(observations, responses, contexts, strict=True):
            if not isinstance(response, Exception):
                self._keep(obs, response, context)
        return responses

    def _keep(self, obs: Mapping[str, Any], response: Mapping[str, Any], context: object) -> None:
        connection = str(getattr(context, "connection_id", "local"))
        try:
            frame = request_frame(obs, response["actions"])
        except Exception as e:  # never the client's problem: its answer is already computed
            self._events.count(f"skipped_{type(e).__name__}", f"a request not recorded: {e}")
            return
        with self._lock:
            frames = self._frames[connection]
            if len(frames) >= self._max_frames:
                self._events.count("skipped_episode_full", f"{connection}: over {self._max_frames} frames")
                return
            frames.append(frame)

    def connection_closed(self, connection_id: str) -> None:
        with self._lock:
            frames = self._frames.pop(connection_id, None)
        if frames:
            self._episodes.put(frames)
        closed = getattr(self._served, "connection_closed", None)  # the side channel's monitor ends its episode too
        if callable(closed):
            closed(connection_id)

    def _write(self) -> None:
        while (frames := self._episodes.get()) is not None:
            for values, task in frames:
                try:
                    self._recorder.step(values, task=task)
                except DatasetError as e:
                    self._events.count("skipped_DatasetError", str(e))
            try:
                if self._recorder.end_episode() is not None:
                    self._events.count("episodes")
            except (DatasetError, OSError) as e:
                self._events.count(f"failed_{type(e).__name__}", f"an episode could not be saved: {e}")

    def stats(self) -> dict[str, Any]:
        stats = getattr(self._served, "stats", None)
        with self._lock:
            open_frames = sum(len(f) for f in self._frames.values())
        recording = {**self._events.snapshot(), "open_frames": open_frames, "root": str(self.root)}
        return {**(stats() if callable(stats) else {}), "recording": recording}

    def begin_close(self, timeout: float | None = None) -> None:
        begin = getattr(self._served, "begin_close", None)
        if callable(begin):
            begin(timeout)

    def close(self, timeout: float | None = None) -> None:
        """Closes the wrapped policy, saves the episodes of connections still open, and finalises the dataset."""
        close = getattr(self._served, "close", None)
        if callable(close):
            close(timeout)
        with self._lock:
            remaining = [self._frames.pop(c) for c in list(self._frames)]
        for frames in remaining:
            self._episodes.put(frames)
        self._episodes.put(None)
        self._writer.join()
        self._recorder.close()
