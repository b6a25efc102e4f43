"""Observations of the bundled demo robot, a pure function of a seed (the demo policy's actions depend on them)."""

from __future__ import annotations

from typing import Any

import numpy as np


def demo_observation(seed: int) -> dict[str, Any]:
    """What the demo robot sends for a random scene and start, without the `cam_extra/` ground-truth entries."""
    from openpi_cam.demo import bundled, task

    rng = np.random.default_rng(seed)
    scene = task.random_scene(rng)
    return bundled.policy_input(bundled.client_observation(task.observe(scene, task.random_start(rng, scene))))
