"""The Meta-World demo's training data: the scripted expert's episodes, step by step as a LeRobot dataset records
them, and those episodes back in memory as training samples (action chunks cut from each episode's actions).

The expert drives with noise added to the actions it executes (DART: the recorded action is the expert's own, at a
state the noise pushed it to), so the demonstrations cover the states a policy that drifts off the expert's path
reaches and say how to get back. Episodes stop a few steps after the button is pressed, so chunks near the end show
the press held rather than a cut-off.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from collections.abc import Iterator
from typing import Any

import numpy as np

from openpi_cam.demo import metaworld_sim, task
from openpi_cam.policies.demo_reach import IMAGE_KEY, LEROBOT_KEYS, STATE_KEY, WRIST_KEY

BASE_FEATURE = LEROBOT_KEYS[IMAGE_KEY]
WRIST_FEATURE = LEROBOT_KEYS[WRIST_KEY]
STATE_FEATURE = LEROBOT_KEYS[STATE_KEY]
ACTION_FEATURE = LEROBOT_KEYS["actions"]
FPS = 80  # Meta-World's control rate: 5 physics steps of 2.5 ms per action
HOLD_STEPS = 5  # steps recorded after the press succeeds


@dataclasses.dataclass(frozen=True)
class ExpertStep:
    frame: dict[str, np.ndarray]  # by LeRobot feature name: both cameras, the state and the expert's action
    prompt: str
    success: bool  # after this step's action


def expert_episode(
    seed: int,
    noise: float,
    *,
    task: str = metaworld_sim.TASK,
    prompt: str | None = None,
    image_size: int = metaworld_sim.IMAGE_SIZE,
    fovy: float | None = None,
    wrist_camera: str = metaworld_sim.WRIST_CAMERA,
) -> Iterator[ExpertStep]:
    """One expert episode of `task` in scene `seed`, instructed by `prompt` (None: the task's first); the executed
    action is the expert's plus Gaussian noise of std `noise` (the recorded one is the expert's). Ends `HOLD_STEPS`
    after success, or at the task's step budget. `fovy` and `wrist_camera`: `MetaWorldSim`'s."""
    rng = np.random.default_rng([seed, 1])
    with metaworld_sim.MetaWorldSim(
        seed, task=task, image_size=image_size, prompt=prompt, fovy=fovy, wrist_camera=wrist_camera
    ) as sim:
        hold, max_steps = 0, sim.spec.max_steps
        while sim.steps < max_steps and hold < HOLD_STEPS:
            frame = sim.frame(with_target=False)
            action = sim.expert_action()
            success = sim.step(action + noise * rng.standard_normal(action.shape))
            hold += success
            yield ExpertStep(
                {
                    BASE_FEATURE: frame.base_image,
                    WRIST_FEATURE: frame.wrist_image,
                    STATE_FEATURE: frame.state,
                    ACTION_FEATURE: action,
                },
                frame.prompt,
                success,
            )


@dataclasses.dataclass(frozen=True)
class Demonstrations:
    """Recorded episodes in memory, one row per frame, rows of an episode consecutive and in order."""

    base_image: np.ndarray  # [N, S, S, 3] uint8
    wrist_image: np.ndarray  # [N, S, S, 3] uint8
    state: np.ndarray  # [N, STATE_DIM] float32
    actions: np.ndarray  # [N, ACTION_DIM] float32
    episode_index: np.ndarray  # [N] int
    prompt: np.ndarray  # [N] str
    # [N]: how often each row is drawn for training, relative to the others (None: every row alike).
    weight: np.ndarray | None = None

    @classmethod
    def from_frames(cls, frames: list[dict[str, Any]], prompts: list[str]) -> Demonstrations:
        """From frames by LeRobot feature name (as the dataset reader yields them) and each frame's task."""

        def stack(name: str, dtype: Any) -> np.ndarray:
            return np.stack([np.asarray(f[name]) for f in frames]).astype(dtype)

        return cls(
            base_image=stack(BASE_FEATURE, np.uint8),
            wrist_image=stack(WRIST_FEATURE, np.uint8),
            state=stack(STATE_FEATURE, np.float32),
            actions=stack(ACTION_FEATURE, np.float32),
            episode_index=np.array([int(f["episode_index"]) for f in frames]),
            prompt=np.array(prompts),
        )

    def __len__(self) -> int:
        return len(self.state)

    @functools.cached_property
    def digest(self) -> str:
        """A digest of every row (frames, prompts and draw weights included): what tells two training sets apart."""
        h = hashlib.blake2b(digest_size=16)
        for name in ("base_image", "wrist_image", "state", "actions", "episode_index", "prompt", "weight"):
            value = getattr(self, name)
            h.update(name.encode())
            if value is not None:
                h.update(str((value.dtype, value.shape)).encode())
                h.update(np.ascontiguousarray(value).data)
        return h.hexdigest()

    def chunk(self, row: int, horizon: int) -> np.ndarray:
        """The actions of `horizon` frames from `row` on; past the episode's end its last action repeats (LeRobot's
        loader clamps the frame index at the episode's end the same way)."""
        episode = self.episode_index[row]
        last = row + int(np.searchsorted(self.episode_index[row:], episode, side="right")) - 1
        return self.actions[np.minimum(np.arange(row, row + horizon), last)]

    def all_chunks(self, horizon: int) -> np.ndarray:
        """Every frame's chunk (`chunk`) -> [N, horizon, ACTION_DIM]."""
        return np.stack([self.chunk(row, horizon) for row in range(len(self))])

    def sample(self, row: int, horizon: int) -> task.Sample:
        return task.Sample(
            base_image=self.base_image[row],
            wrist_image=self.wrist_image[row],
            state=self.state[row],
            prompt=str(self.prompt[row]),
            actions=self.chunk(row, horizon),
            target_box=(0, 0, 0, 0),  # not needed for training
        )

    def samples(self, rng: np.random.Generator, n: int, horizon: int) -> list[task.Sample]:
        if self.weight is None:
            rows = rng.integers(len(self), size=n)
        else:
            rows = rng.choice(len(self), size=n, p=self.weight / self.weight.sum())
        return [self.sample(int(r), horizon) for r in rows]

    def tasks(self) -> np.ndarray:
        """[N] str: each row's Meta-World task, by its instruction ("" where the instruction is no task's)."""
        names = {p: metaworld_sim.task_of(p) or "" for p in np.unique(self.prompt)}
        return np.array([names[p] for p in self.prompt])

    def weighted(self, task_weights: dict[str, float]) -> Demonstrations:
        """These rows, those of each task in `task_weights` drawn that many times as often as the others (a task's
        share of the draws grows with its weight and with its share of the frames); a ValueError names a weighted
        task no row shows."""
        tasks = self.tasks()
        if absent := sorted(set(task_weights) - set(tasks)):
            raise ValueError(f"no episodes of {', '.join(absent)} in the expert data")
        return dataclasses.replace(self, weight=np.array([task_weights.get(t, 1.0) for t in tasks]))

    def task_shares(self) -> dict[str, float]:
        """Each task's expected share of the training draws."""
        weight = np.ones(len(self)) if self.weight is None else self.weight
        tasks = self.tasks()
        return {t: float(weight[tasks == t].sum() / weight.sum()) for t in dict.fromkeys(tasks)}
