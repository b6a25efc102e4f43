"""The Meta-World robot's closed loop: observe, ask the policy for a chunk, execute its first actions one step at a
time, repeat until the button is pressed or the call budget is spent; every executed step can go to a rollout sink
as `lerobot-eval` records evaluation episodes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from openpi_cam.demo import bundled
from openpi_cam.demo.client import RolloutSink
from openpi_cam.demo.metaworld_sim import CLEAN, MetaWorldSim, Perturbation

MAX_CALLS = 30  # 150 steps at 5 executed actions per call: about twice what the expert needs
EXECUTE = 5


def run_episode(
    infer: Callable[[dict[str, Any]], dict[str, Any]],
    seed: int,
    perturbation: Perturbation = CLEAN,
    *,
    max_calls: int = MAX_CALLS,
    execute: int = EXECUTE,
    sink: RolloutSink | None = None,
    perturbation_index: int = 0,
) -> dict[str, Any]:
    """One closed-loop episode; `infer` takes the client observation (with its `cam_extra/` entries) and returns the
    server's reply. Recorded frames carry `perturbation_index` (the perturbation's place in the run's list)."""
    calls = 0
    with MetaWorldSim(seed, perturbation) as sim:
        while calls < max_calls and not sim.success:
            frame = sim.frame()
            chunk = np.asarray(infer(bundled.client_observation(frame))["actions"])[:execute]
            calls += 1
            for j, action in enumerate(chunk):
                success = sim.step(action)
                if sink is not None:
                    done = success or (calls == max_calls and j == len(chunk) - 1)
                    sink.step(
                        bundled.recorded_frame(frame, action, perturbation_index),
                        task=frame.prompt,
                        reward=float(success),
                        success=success,
                        done=done,
                    )
                if success:
                    break
                frame = sim.frame()
        if sink is not None:
            sink.end_episode()
        return {
            "seed": seed,
            "perturbation": perturbation.name,
            "prompt": sim.prompt,
            "success": sim.success,
            "calls": calls,
            "steps": sim.steps,
        }
