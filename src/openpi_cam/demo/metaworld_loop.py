"""The Meta-World robot's closed loop: observe, ask the policy for a chunk, execute its first actions one step at a
time, repeat until the button is pressed or the call budget is spent; every executed step can go to a rollout sink
as `lerobot-eval` records evaluation episodes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from openpi_cam.cam.records import EXTRA_PREFIX
from openpi_cam.demo import metaworld_data
from openpi_cam.demo.client import RolloutSink
from openpi_cam.demo.metaworld_sim import CLEAN, Frame, MetaWorldSim, Perturbation
from openpi_cam.policies.demo_reach import IMAGE_KEY, LEROBOT_TARGET_BOX, STATE_KEY, WRIST_KEY

MAX_CALLS = 30  # 150 steps at 5 executed actions per call: about twice what the expert needs
EXECUTE = 5


def client_observation(frame: Frame) -> dict[str, Any]:
    """What the Meta-World robot sends; `cam_extra/target_box` is the box's bounding box in the fixed camera."""
    return {
        IMAGE_KEY: frame.base_image,
        WRIST_KEY: frame.wrist_image,
        STATE_KEY: frame.state.astype(np.float64),
        "prompt": frame.prompt,
        EXTRA_PREFIX + "target_box": np.asarray(frame.target_box, np.int32),
    }


def recorded_frame(frame: Frame, action: np.ndarray, perturbation: int = 0) -> dict[str, np.ndarray]:
    """A recorded step by LeRobot feature name, with the box's bounding box in the fixed camera and the index of the
    episode's perturbation."""
    return {
        metaworld_data.BASE_FEATURE: frame.base_image,
        metaworld_data.WRIST_FEATURE: frame.wrist_image,
        metaworld_data.STATE_FEATURE: frame.state,
        metaworld_data.ACTION_FEATURE: np.asarray(action, np.float32),
        LEROBOT_TARGET_BOX: np.asarray(frame.target_box, np.float32),
        PERTURBATION_FEATURE: np.array([perturbation], np.int64),
    }


PERTURBATION_FEATURE = "perturbation"  # a recorded frame's index into the run's perturbations


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
            chunk = np.asarray(infer(client_observation(frame))["actions"])[:execute]
            calls += 1
            for j, action in enumerate(chunk):
                success = sim.step(action)
                if sink is not None:
                    done = success or (calls == max_calls and j == len(chunk) - 1)
                    sink.step(
                        recorded_frame(frame, action, perturbation_index),
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
