"""The Meta-World robot's closed loop: observe, ask the policy for a chunk, execute its first actions one step at a
time, repeat until the button is pressed or the call budget is spent; every executed step can go to a rollout sink
as `lerobot-eval` records evaluation episodes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from openpi_cam.demo import bundled
from openpi_cam.demo.client import RolloutSink
from openpi_cam.demo.metaworld_sim import CLEAN, TASK, TASKS, WRIST_CAMERA, MetaWorldSim, Perturbation

EXECUTE = 5
MAX_CALLS = TASKS[TASK].max_steps // EXECUTE  # the button task's: about twice the steps the expert needs


def max_calls_of(task: str, execute: int = EXECUTE) -> int:
    """The calls an episode of `task` may make: its step budget (`TaskSpec.max_steps`) at `execute` actions each."""
    return TASKS[task].max_steps // execute


def run_episode(
    infer: Callable[[dict[str, Any]], dict[str, Any]],
    seed: int,
    perturbation: Perturbation = CLEAN,
    *,
    task: str = TASK,
    max_calls: int | None = None,
    execute: int = EXECUTE,
    sink: RolloutSink | None = None,
    perturbation_index: int = 0,
    image_size: int | None = None,
    fovy: float | None = None,
    wrist_camera: str = WRIST_CAMERA,
) -> dict[str, Any]:
    """One closed-loop episode of `task`; `infer` takes the client observation (with its `cam_extra/` entries) and
    returns the server's reply. `max_calls` None: the task's budget (`max_calls_of`); `image_size` and `fovy` (the
    fixed camera's field of view) None: the simulator's defaults; `wrist_camera`: `MetaWorldSim`'s. Recorded frames
    carry `perturbation_index` (the perturbation's place in the run's list)."""
    calls = 0
    max_calls = max_calls_of(task, execute) if max_calls is None else max_calls
    size = {} if image_size is None else {"image_size": image_size}
    with MetaWorldSim(seed, perturbation, task=task, fovy=fovy, wrist_camera=wrist_camera, **size) as sim:
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
            "task": task,
            "perturbation": perturbation.name,
            "prompt": sim.prompt,
            "success": sim.success,
            "calls": calls,
            "steps": sim.steps,
        }
