"""Closed-loop success of the bundled multi-task Meta-World models, per model, task and perturbation.

    python benchmarks/metaworld_success.py [--models pi05 pi0_fast pi05=DIR] [--tasks all held-out] [--episodes 40]
        [--perturb clean "prompt=open the door"] [--fovy DEGREES] [--wrist-camera NAME] [--workers N] [--out FILE]

Each (model, task, perturbation) runs the episodes `openpi-cam demo --sim metaworld --model M --task T --perturb P
--num-episodes N --no-explain` runs: scene seeds `--seed` .. `--seed` + N - 1, the task's own step budget, `execute`
actions of each chunk, both cameras at the demo's size. The policy is called in process rather than over the websocket
(the server returns the same actions; `tests/serving` holds that), so that the episodes can spread over `--workers`
processes, each with its own copy of the models on the CPU. Prints a markdown table with Wilson 95% intervals and
the machine, and writes the figures as JSON to `--out`. A model `FAMILY=DIR` is that family's bundled model with the
weights and tokenizers of DIR instead (a candidate before it ships); `--fovy` narrows the fixed camera's field of
view from Meta-World's 45 degrees for every model of the run (a candidate trained on frames of such a camera), and
`--wrist-camera` shows every model another of the scene's cameras as the wrist view (a candidate recorded with
`train_demo --record.wrist-camera`). Needs the `metaworld` extra.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import pathlib
import time

from bench_serving import machine_line

_POLICIES: dict[str, object] = {}


def _episode(job: tuple[str, str, str, int, int, float | None, str]) -> tuple[str, str, str, bool, int]:
    """One episode in a worker: (model, task, perturbation, seed, execute, fovy, wrist camera) -> (model, task,
    perturbation, success, steps)."""
    from openpi_cam.checkpoints import model_spec
    from openpi_cam.demo import bundled, metaworld_loop, metaworld_sim
    from openpi_cam.demo.run import METAWORLD_CAMERA_SIZE, METAWORLD_MODELS

    model, task, perturb, seed, execute, fovy, wrist_camera = job
    if model not in _POLICIES:
        family, _, assets = model.partition("=")
        folder = {"assets": pathlib.Path(assets)} if assets else {}
        _POLICIES[model] = model_spec.create_demo_policy(METAWORLD_MODELS[family], **folder)
    policy = _POLICIES[model]

    def infer(obs: dict) -> dict:
        return policy.infer(bundled.policy_input(obs))

    out = metaworld_loop.run_episode(
        infer,
        seed,
        metaworld_sim.Perturbation.parse(perturb),
        task=task,
        execute=execute,
        image_size=METAWORLD_CAMERA_SIZE,
        fovy=fovy,
        wrist_camera=wrist_camera,
    )
    return model, task, perturb, bool(out["success"]), int(out["steps"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="+", default=["pi05", "pi0_fast"], help="pi05, pi0_fast or FAMILY=DIR")
    parser.add_argument("--tasks", nargs="+", default=["all"], help="task names, or the groups all / held-out")
    parser.add_argument("--perturb", nargs="+", default=["clean"])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--execute", type=int, default=5)
    parser.add_argument("--fovy", type=float, default=None, help="the fixed camera's field of view, degrees")
    parser.add_argument("--wrist-camera", default=None, help="the scene's camera seen as the wrist view")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    from openpi_cam.cam.outcomes import wilson_interval

    for model in args.models:
        family, _, assets = model.partition("=")
        if family not in ("pi05", "pi0_fast") or (assets and not pathlib.Path(assets, "checkpoint").is_dir()):
            parser.error(f"--models {model}: pi05, pi0_fast, or FAMILY=DIR with a model folder (DIR/checkpoint)")
    from openpi_cam.demo.run import DemoOptions

    try:  # the demo's own reading of --task: groups expanded, an unknown name refused in one line
        tasks = DemoOptions(sim="metaworld", task=tuple(args.tasks)).tasks
    except ValueError as e:
        parser.error(str(e))
    from openpi_cam.demo import metaworld_sim

    wrist_camera = args.wrist_camera or metaworld_sim.WRIST_CAMERA
    try:
        metaworld_sim.require_camera(wrist_camera, tasks[0])
    except ValueError as e:
        parser.error(f"--wrist-camera {e}")
    # Episode-major, so that a run cut short has as many episodes of every row as it could.
    jobs = [
        (m, t, p, args.seed + e, args.execute, args.fovy, wrist_camera)
        for e in range(args.episodes)
        for m in args.models
        for t in tasks
        for p in args.perturb
    ]
    load_before, t0 = os.getloadavg(), time.time()
    # The tiny models run on the CPU, one thread per worker: the workers are the parallelism (on a machine with an
    # accelerator, every worker would otherwise claim its memory).
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    results = []
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        for result in pool.imap_unordered(_episode, jobs):
            results.append(result)
            if args.out:  # every episode as it ends: a run stopped early keeps what it measured
                with open(args.out, "w") as f:
                    json.dump({"episodes": results, "seed": args.seed, "wall_s": time.time() - t0}, f)
    wall = time.time() - t0
    rows = []
    print("| model | task | perturbation | successes | rate | 95% interval |")
    print("| --- | --- | --- | --- | --- | --- |")
    for m in args.models:
        for t in tasks:
            for p in args.perturb:
                wins = [r[3] for r in results if r[:3] == (m, t, p)]
                low, high = wilson_interval(sum(wins), len(wins))
                rows.append({"model": m, "task": t, "perturbation": p, "successes": sum(wins), "episodes": len(wins)})
                rate = sum(wins) / len(wins)
                print(f"| {m} | {t} | {p} | {sum(wins)}/{len(wins)} | {rate:.2f} | {low:.2f}-{high:.2f} |")
    machine = machine_line(load_before, os.getloadavg())
    print(f"\n{len(jobs)} episodes in {wall:.0f} s over {args.workers} workers; {machine}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(
                {
                    "rows": rows,
                    "episodes": results,
                    "seed": args.seed,
                    "fovy": args.fovy,
                    "wrist_camera": wrist_camera,
                    "wall_s": wall,
                    "machine": machine,
                },
                f,
            )


if __name__ == "__main__":
    main()
