"""Closed-loop rollouts recorded as a LeRobot v3.0 dataset, the way `lerobot-eval --eval.recording=true` records
evaluation episodes: one frame per step, holding what the robot observed before it, the action it executed and the
step's outcome (`next.reward`, `next.success`, `next.done`: `lerobot_writer.OUTCOME_FEATURES`).

The features are declared from the first frame recorded: a uint8 [H, W, 3] array is a camera (AV1 video, or PNG
images), any other array a numeric feature of its dtype and shape (a scalar as shape [1]), and the outcome features
are declared when the first step gives an outcome. Every later frame must carry the same features.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.lerobot.dataset import dataset_error
from openpi_cam.lerobot.writer import (
    DONE,
    OUTCOME_FEATURES,
    REWARD,
    SUCCESS,
    DatasetWriter,
    Feature,
    create_dataset,
)


def frame_features(frame: Mapping[str, Any], *, video: bool = True) -> dict[str, Feature]:
    """The features a frame's values declare (see the module docstring)."""
    features = {}
    for name, value in frame.items():
        array = np.asarray(value)
        if array.dtype == np.uint8 and array.ndim == 3 and array.shape[-1] == 3:
            features[name] = Feature.camera(array.shape[0], array.shape[1], video=video)
        elif array.ndim <= 1 and array.dtype.kind in "biuf":
            features[name] = Feature(array.dtype.name, (max(1, array.size),))
        else:
            raise dataset_error(
                f"a frame value is a camera (uint8 [H, W, 3]) or a vector, got {array.dtype} {list(array.shape)}",
                feature=name,
            )
    return features


class RolloutRecorder:
    """Records rollouts into a new dataset at `root` (made at the first frame); a context manager that finalizes it.

    `step` adds a frame to the current episode, `end_episode` saves it. An episode left unsaved when the recorder
    closes is dropped (the saved ones stay readable)."""

    def __init__(self, root: str | Path, *, fps: int, robot_type: str | None = None, video: bool = True) -> None:
        self.root = Path(root)
        self.fps = fps
        self.robot_type = robot_type
        self.video = video
        self._writer: DatasetWriter | None = None
        self._outcomes = False

    @property
    def episodes(self) -> int:
        return 0 if self._writer is None else self._writer.num_episodes

    def step(
        self,
        frame: Mapping[str, Any],
        *,
        task: str,
        reward: float | None = None,
        success: bool | None = None,
        done: bool | None = None,
    ) -> None:
        """One step: `frame` holds the observation and action by feature name; the outcome, when given, is what
        followed the action (all three or none)."""
        given = [x is not None for x in (reward, success, done)]
        if any(given) and not all(given):
            raise dataset_error("an outcome is reward, success and done together", file=self.root)
        if self._writer is None:
            self._outcomes = all(given)
            features = frame_features(frame, video=self.video) | (OUTCOME_FEATURES if self._outcomes else {})
            self._writer = create_dataset(self.root, fps=self.fps, features=features, robot_type=self.robot_type)
        values = {name: np.asarray(value) for name, value in frame.items()}
        for name, value in values.items():
            if value.ndim == 0:
                values[name] = value.reshape(1)
        if self._outcomes != all(given):
            raise dataset_error(
                "every step gives an outcome, or none does (as the first step did)",
                file=self.root,
                episode=self.episodes,
            )
        if self._outcomes:
            values |= {
                REWARD: np.array([reward], np.float32),
                SUCCESS: np.array([bool(success)]),
                DONE: np.array([bool(done)]),
            }
        self._writer.add_frame(values, task=task)

    def end_episode(self) -> int | None:
        """Saves the frames since the last call as an episode; returns its index (None: no frame was added)."""
        if self._writer is None or not self._writer.pending_frames:
            return None
        return self._writer.save_episode()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.clear_episode()
            self._writer.finalize()

    def __enter__(self) -> RolloutRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
