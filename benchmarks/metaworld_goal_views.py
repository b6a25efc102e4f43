"""How well each Meta-World camera can tell where the reach task's goal is, before any model reads it.

    python benchmarks/metaworld_goal_views.py [--size 96] [--noise 0 1 1.5] [--goals 100000]

Goals are drawn uniformly from `reach-v3`'s own reset range; each camera (at its pose in the task's first frame:
the hand's cameras move with the hand later) projects every goal's centre to a pixel position. An ideal reader that
knows that position up to Gaussian noise of `--noise` pixels, and the goal range, estimates the goal by its posterior
mean (importance weights over a reference half of the draws); a goal out of the camera's view tells it nothing (the
range's mean). Printed per camera and for each pair a robot can carry (a fixed camera beside a hand camera): the
share of goals it places within reach's success radius of 5 cm, and, per camera, the share in view and how far the
image moves for a centimetre along each axis. The cameras are the task model's own (fixed ones hang off the world
body, hand ones off the hand). Occlusion by the arm is ignored: a ceiling, not an estimate of a policy. Needs the
`metaworld` extra.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Callable
from typing import Any

import numpy as np

TASK = "reach-v3"
SUCCESS_RADIUS = 0.05  # m: its success, the hand's distance to the goal


def projector(model: Any, data: Any, camera: str, size: int) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Pixel offsets from the image centre (x right, y up) and the depth of world points, for one camera."""
    cid = model.camera(camera).id
    origin, axes = data.cam_xpos[cid].copy(), data.cam_xmat[cid].reshape(3, 3).copy()
    focal = 0.5 * size / np.tan(np.deg2rad(model.cam_fovy[cid]) / 2)

    def project(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = (points - origin) @ axes  # MuJoCo cameras look down their -z axis
        depth = -local[:, 2]
        return focal * local[:, :2] / depth[:, None], depth

    return project


def placed(pixels: np.ndarray, seen: np.ndarray, goals: np.ndarray, noise: float, rng: np.random.Generator) -> float:
    """The share of the second half of `goals` that the ideal reader places within the success radius."""
    from scipy.spatial import cKDTree

    half = len(goals) // 2
    ref, ref_goals = pixels[:half], goals[:half]
    query = pixels[half:] + rng.normal(0.0, noise, pixels[half:].shape)
    width = max(noise, 0.25)  # a floor for the exact reader: its posterior is the reference draws nearest the pixel
    _, nearest = cKDTree(ref).query(query, k=256)
    squared = ((ref[nearest] - query[:, None]) ** 2).sum(-1)
    # Shifted by each query's nearest draw so that a query far from every draw keeps finite weights.
    weight = np.exp(-(squared - squared.min(1, keepdims=True)) / (2 * width**2))
    estimate = (ref_goals[nearest] * weight[..., None]).sum(1) / weight.sum(1)[:, None]
    estimate[~seen[half:]] = goals.mean(0)
    return float((np.linalg.norm(estimate - goals[half:], axis=1) < SUCCESS_RADIUS).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=96, help="image side in pixels (the multi-task models' 96)")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 1.0, 1.5], help="pixel noise std")
    parser.add_argument("--goals", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from openpi_cam.demo import metaworld_sim

    rng = np.random.default_rng(args.seed)
    with metaworld_sim.MetaWorldSim(args.seed, task=TASK, image_size=args.size) as sim:
        env = sim.env
        low, high = env._random_reset_space.low[-3:], env._random_reset_space.high[-3:]
        goals = rng.uniform(low, high, (args.goals, 3))
        model = env.model
        cameras = metaworld_sim.camera_names(model)
        fixed = [c for c in cameras if model.cam_bodyid[model.camera(c).id] == 0]  # body 0: the world
        views = {}
        centre = ((low + high) / 2)[None]
        print(f"{TASK}: goals in x {low[0]:.2f}..{high[0]:.2f}, y {low[1]:.2f}..{high[1]:.2f}, "
              f"z {low[2]:.2f}..{high[2]:.2f} m; {args.size} px cameras\n")  # fmt: skip
        within = " | ".join(f"within {SUCCESS_RADIUS * 100:.0f} cm, {n} px" for n in args.noise)
        print(f"| camera | in view | px per cm (x; y; z) | {within} |")
        print("| --- | --- | --- | " + " | ".join("---" for _ in args.noise) + " |")
        for camera in cameras:
            project = projector(model, env.data, camera, args.size)
            pixels, depth = project(goals)
            seen = (depth > 0) & (np.abs(pixels) < args.size / 2).all(1)
            views[camera] = (pixels, seen)
            steps = [project(centre + 0.01 * np.eye(3)[i])[0] - project(centre)[0] for i in range(3)]
            per_cm = "; ".join(f"{np.linalg.norm(s):.2f}" for s in steps)
            shares = [placed(pixels, seen, goals, n, rng) for n in args.noise]
            print(f"| {camera} | {seen.mean():.2f} | {per_cm} | " + " | ".join(f"{s:.2f}" for s in shares) + " |")
        print(f"\n| fixed + hand camera | {within} |")
        print("| --- | " + " | ".join("---" for _ in args.noise) + " |")
        # A goal out of one camera's view reads from the other's pixels alone: out of view is one far-off pixel.
        away = 10.0 * args.size
        for base, hand in itertools.product(fixed, [c for c in cameras if c not in fixed]):
            (a, seen_a), (b, seen_b) = views[base], views[hand]
            pixels = np.concatenate([np.where(seen_a[:, None], a, away), np.where(seen_b[:, None], b, away)], 1)
            shares = [placed(pixels, seen_a | seen_b, goals, n, rng) for n in args.noise]
            print(f"| {base} + {hand} | " + " | ".join(f"{s:.2f}" for s in shares) + " |")


if __name__ == "__main__":
    main()
