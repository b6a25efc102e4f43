"""A kinematic simulator for the reaching task: the end effector follows the displacements it is given."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from openpi_cam.demo import task


@dataclasses.dataclass
class ReachSim:
    scene: task.Scene
    state: np.ndarray
    cfg: task.TaskConfig = dataclasses.field(default_factory=task.TaskConfig)
    steps: int = 0
    # what the robot's cameras and prompt make of the scene, when not what the task renders (`demo.perturb`)
    view: Callable[[task.Sample], task.Sample] | None = None

    @property
    def goal(self) -> np.ndarray:
        return task.block_center(self.scene.target_block, self.cfg.image_size)

    @property
    def success(self) -> bool:
        return float(np.linalg.norm(self.state - self.goal)) <= self.cfg.success_radius

    def observe(self) -> task.Sample:
        sample = task.observe(self.scene, self.state, self.cfg)
        return sample if self.view is None else self.view(sample)

    def execute(self, actions: np.ndarray, n: int | None = None) -> bool:
        """Apply the first `n` actions of a chunk (all by default); stop early on success. Returns success."""
        chunk = np.asarray(actions, np.float64)
        if chunk.ndim != 2 or chunk.shape[1] != 2:
            raise ValueError(f"expected an action chunk [T, 2], got {chunk.shape}")
        for a in chunk[: len(chunk) if n is None else n]:
            self.state = np.clip(self.state + a, -1.0, 1.0).astype(np.float32)
            self.steps += 1
            if self.success:
                return True
        return self.success


def new_episode(seed: int, cfg: task.TaskConfig | None = None) -> ReachSim:
    cfg = cfg or task.TaskConfig()
    rng = np.random.default_rng(seed)
    scene = task.random_scene(rng, cfg)
    return ReachSim(scene=scene, state=task.random_start(rng, scene, cfg), cfg=cfg)
