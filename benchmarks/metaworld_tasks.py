"""Which Meta-World task for the demo? The evidence: does the scripted expert solve it with its actions clipped to the
action space, how many steps it needs, and how fast the simulator steps and renders here.

    python benchmarks/metaworld_tasks.py [--episodes 10]

Per task: successes of `metaworld.policies`' expert over episodes whose scene is drawn from the task's own reset range
(as `demo.metaworld_sim` draws it), the steps to success, the largest action it asks for before clipping. Then, for
the demo's task, steps per second with both 64 px cameras and the segmentation render, shadows off and on. Needs the
`metaworld` extra.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from bench_serving import machine_line

from openpi_cam.demo import metaworld_sim

TASKS = (
    "button-press-topdown-v3",
    "button-press-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "door-open-v3",
    "plate-slide-v3",
    "push-v3",
    "reach-v3",
)


def expert_figures(task: str, episodes: int) -> dict:
    env_class = metaworld_sim._environment_class(task)
    expert = metaworld_sim.expert_policy(task)
    wins, steps, largest = 0, [], 0.0
    for seed in range(episodes):
        env = env_class()
        space = env._random_reset_space
        metaworld_sim.set_scene(env, np.random.default_rng(seed).uniform(space.low, space.high))
        obs, _ = env.reset()
        for k in range(metaworld_sim.MAX_STEPS):
            action = expert.get_action(obs)
            largest = max(largest, float(np.abs(action).max()))
            obs, _, _, _, info = env.step(np.clip(action, -1.0, 1.0))
            if info["success"]:
                wins += 1
                steps.append(k + 1)
                break
        env.close()
    return {"wins": wins, "steps": steps, "largest": largest}


def sim_speed(steps: int = 100, shadows: bool = False) -> float:
    with metaworld_sim.MetaWorldSim(0) as sim:
        if shadows:
            sim.env.model.light_castshadow[:] = 1
        t0 = time.perf_counter()
        for _ in range(steps):
            sim.frame()
            sim.step(sim.expert_action())
        return steps / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    load_before = os.getloadavg()
    print("| task | expert successes | steps to success (min-max) | largest action asked |")
    print("| --- | --- | --- | --- |")
    for task in TASKS:
        f = expert_figures(task, args.episodes)
        span = f"{min(f['steps'])}-{max(f['steps'])}" if f["steps"] else "-"
        print(f"| {task} | {f['wins']}/{args.episodes} | {span} | {f['largest']:.1f} |")
    off, on = sim_speed(), sim_speed(shadows=True)
    print(
        f"\n{metaworld_sim.TASK}: {off:.1f} steps/s with both cameras and the segmentation (shadows off), {on:.1f} on"
    )
    print(machine_line(load_before, os.getloadavg()))


if __name__ == "__main__":
    main()
