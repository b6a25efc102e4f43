"""The maps bench: every map kind on policies and tasks the kinds were not tuned on, on a split chosen in advance.

    python benchmarks/maps_bench.py --out DIR [--split test] [--tasks reach-pi0_fast ...] [--kinds gradnorm ...]

For each bench task (a bundled policy on its simulator, `BENCH_TASKS`) and split, with the commands a user runs:

1. closed-loop rollouts of the policy through the websocket server under clean and perturbed scenes (`perturb`),
   recorded as a LeRobot v3.0 dataset with the target's box in the base camera, as `openpi-cam demo --record` does
   (driven here through the same library calls, since the one-task Meta-World model is not a demo choice);
2. `openpi-cam explain-dataset ROLLOUTS --config C --maps KINDS --every-k K --check-patches 0 --extra
   observation.target_box=target_box`: every K-th frame explained by every kind;
3. `openpi-cam faithfulness MAPS`: each explained frame re-served and re-scored under interventions (deletion
   against the single-patch optimum, top-1 and Spearman agreement with single-patch occlusion, model randomisation,
   pointing where the target is in view);
4. each kind's cost in backward-pass equivalents: the wall time to explain one frame with that kind alone divided by
   the time of the gradient kinds' one backward pass (`gradnorm`), both measured here on fresh scenes of the task in
   one process after compilation (median of `COST_FRAMES` frames).

The split is fixed here, before anything was measured: the scenes of split `dev` start at seed `SPLITS["dev"]`,
those of `test` at `SPLITS["test"]`; the two ranges are disjoint from each other and from every training or
evaluation seed of the bundled models (their expert data starts at 100000, the demos' own episodes at 0, the
training evaluations at 10000). Methods, thresholds and defaults are chosen on `dev`; `test` is reported.
A default must hold on every task: median deletion k=1 >= `HOLDS_DELETION` of the optimum and top-1 agreement with
occlusion >= `HOLDS_TOP1`, on both cameras (`holds`).

Writes OUT/<split>/<task>/{rollouts, maps} and OUT/<split>/bench.json, and prints the table as markdown. Stages
already done are reused (delete a folder to redo it).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import statistics
import time
from collections.abc import Sequence
from typing import Any

from bench_serving import machine_line

from openpi_cam import cli
from openpi_cam.cam.batching import explain_traces
from openpi_cam.checkpoints.model_spec import BUNDLED_CONFIGS, ModelSpec
from openpi_cam.demo import bundled, metaworld_sim, sim
from openpi_cam.demo.perturb import Perturbation
from openpi_cam.demo.run import ROLLOUT_FPS, ROLLOUT_FPS_METAWORLD, run_episodes, run_metaworld_episodes
from openpi_cam.lerobot.rollouts import RolloutRecorder
from openpi_cam.policies import demo_metaworld, demo_reach
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.vocabulary import MAP_KINDS, ExplainOptions

SPLITS = {"dev": 20_000, "test": 30_000}
HOLDS_DELETION = 0.9
HOLDS_TOP1 = 0.6
COST_FRAMES = 8
REACH_PERTURB = ("clean", "distractors=2", "hue=45", "shift=32", "dim=0.3")
METAWORLD_PERTURB = ("clean", "hue=45", "dim=0.75", "shift=0.05", "distractors=5")
MT_PERTURB = ("clean", "hue=45", "dim=0.75")


@dataclasses.dataclass(frozen=True)
class BenchTask:
    """A bundled policy on its simulator, and how many rollouts and frames a split gives it."""

    name: str
    model: str  # `model_spec.BUNDLED_CONFIGS` key
    perturb: tuple[str, ...]
    scenes: int  # scenes per split; every (task, perturbation) meets each
    every_k: int  # explain every k-th recorded frame (the robot asks every 5 steps)
    metaworld_tasks: tuple[str, ...] = ()  # empty: the reaching task
    camera_size: int = 64

    @property
    def episodes(self) -> int:
        return self.scenes * len(self.perturb) * max(1, len(self.metaworld_tasks))

    @property
    def config(self) -> str:
        return BUNDLED_CONFIGS[self.model].name


BENCH_TASKS = (
    BenchTask("reach-pi0_fast", "pi0_fast", REACH_PERTURB, scenes=4, every_k=5),
    BenchTask("reach-pi05", "pi05", REACH_PERTURB, scenes=4, every_k=5),
    BenchTask(
        "metaworld-button-pi05", "metaworld", METAWORLD_PERTURB, 2, every_k=25, metaworld_tasks=(metaworld_sim.TASK,)
    ),
    BenchTask(
        "metaworld-mt-pi05",
        "metaworld_mt_pi05",
        MT_PERTURB,
        scenes=1,
        every_k=25,
        metaworld_tasks=metaworld_sim.TRAINED_TASKS,
        camera_size=demo_metaworld.MT_IMAGE_SIZE,
    ),
    BenchTask(
        "metaworld-mt-pi0_fast",
        "metaworld_mt_pi0_fast",
        MT_PERTURB,
        scenes=1,
        every_k=25,
        metaworld_tasks=metaworld_sim.TRAINED_TASKS,
        camera_size=demo_metaworld.MT_IMAGE_SIZE,
    ),
)


def record(task: BenchTask, seed: int, out: pathlib.Path) -> list[dict[str, Any]]:
    """The task's rollouts of one split, recorded at `out` (reused when present)."""
    episodes_file = out / "meta" / "bench_episodes.json"
    if episodes_file.is_file():
        return json.loads(episodes_file.read_text())
    policy = ModelSpec.demo(task.model).create()
    server = start_server_in_thread(policy, metadata=policy.metadata)
    metaworld = bool(task.metaworld_tasks)
    fps, robot = (ROLLOUT_FPS_METAWORLD, demo_metaworld.ASSET_ID) if metaworld else (ROLLOUT_FPS, demo_reach.ASSET_ID)
    try:
        with RolloutRecorder(out, fps=fps, robot_type=robot) as recorder:
            if metaworld:
                perturbations = [metaworld_sim.Perturbation.parse(p) for p in task.perturb]
                episodes = run_metaworld_episodes(
                    server.url,
                    task.episodes,
                    seed=seed,
                    max_calls=None,
                    execute=5,
                    perturbations=perturbations,
                    tasks=task.metaworld_tasks,
                    image_size=task.camera_size,
                    sink=recorder,
                )
            else:
                perturbations = [Perturbation.parse(p) for p in task.perturb]
                episodes = run_episodes(
                    server.url,
                    task.episodes,
                    seed=seed,
                    max_calls=6,
                    execute=5,
                    perturbations=perturbations,
                    sink=recorder,
                )
    finally:
        server.stop()
    episodes_file.write_text(json.dumps(episodes, indent=2))
    return episodes


def explain(task: BenchTask, rollouts: pathlib.Path, out: pathlib.Path, kinds: Sequence[str]) -> float:
    """`openpi-cam explain-dataset` of every k-th frame with every kind; its wall time (nan when reused)."""
    if (out / "meta" / "summary.json").is_file():
        return math.nan
    t0 = time.perf_counter()
    argv = ["explain-dataset", str(rollouts), "--out", str(out), "--config", task.config, "--maps", *kinds]
    argv += ["--every-k", str(task.every_k), "--check-patches", "0", "--no-progress"]
    cli.main([*argv, "--extra", "observation.target_box=target_box"])  # a failure raises SystemExit
    return time.perf_counter() - t0


def faithfulness(maps: pathlib.Path) -> dict[str, Any]:
    """`openpi-cam faithfulness MAPS` over every explained frame; its report."""
    report = maps / "meta" / "faithfulness.json"
    if not report.is_file():
        cli.main(["faithfulness", str(maps), "--no-progress"])
    return json.loads(report.read_text())


def fresh_traces(task: BenchTask, policy: Any, seed: int, n: int) -> list[Any]:
    """Traced calls of `policy` on the first frames of `n` fresh scenes of the task (cost timing only)."""
    traces = []
    for i in range(n):
        if task.metaworld_tasks:
            name = task.metaworld_tasks[i % len(task.metaworld_tasks)]
            with metaworld_sim.MetaWorldSim(seed + i, task=name, image_size=task.camera_size) as world:
                observation = bundled.client_observation(world.frame(with_target=False))
        else:
            observation = bundled.client_observation(sim.new_episode(seed + i).observe())
        traces.append(policy.infer_traced(bundled.policy_input(observation))[1])
    return traces


def costs(task: BenchTask, kinds: Sequence[str], seed: int) -> dict[str, float]:
    """Each kind's median explain time per frame (alone, after compilation) over the gradient kinds' pass."""
    policy = ModelSpec.demo(task.model).create()
    traces = fresh_traces(task, policy, seed, COST_FRAMES + 1)
    times = {}
    for kind in dict.fromkeys(["gradnorm", *kinds]):
        request = ExplainOptions(maps=(kind,), check_patches=0)
        elapsed = []
        for i, trace in enumerate(traces):
            t0 = time.perf_counter()
            explain_traces(policy.explainer, [trace], request)
            if i:  # the first call compiles
                elapsed.append(time.perf_counter() - t0)
        times[kind] = statistics.median(elapsed)
    return {k: t / times["gradnorm"] for k, t in times.items()}


def holds(entry: dict[str, Any]) -> bool:
    """Whether a kind meets the bar on one camera (median deletion k=1, mean top-1 agreement)."""
    deletion = (entry.get("deletion_k1") or {}).get("median")
    top1 = (entry.get("top1_occlusion") or {}).get("mean")
    return deletion is not None and top1 is not None and deletion >= HOLDS_DELETION and top1 >= HOLDS_TOP1


def _f(value: Any, digits: int = 2) -> str:
    return "-" if value is None or (isinstance(value, float) and not math.isfinite(value)) else f"{value:.{digits}f}"


def _stat(entry: dict[str, Any], key: str, stat: str = "median") -> Any:
    return (entry.get(key) or {}).get(stat)


def table(results: dict[str, Any], kinds: Sequence[str]) -> list[str]:
    """Markdown: per task, camera and kind the bench's figures."""
    columns = ["task", "camera", "kind", "del k=1", "k=2", "k=4", "top-1 = occl.", "Spearman", "pointing (chance)"]
    columns += ["rand rho (null)", "cost"]
    lines = ["| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
    for name, result in results.items():
        for camera, data in result["faithfulness"]["cameras"].items():
            for kind in [*kinds, "random"]:
                e = data["kinds"].get(kind)
                if e is None:
                    continue
                pointing = "-"
                if _stat(e, "pointing", "mean") is not None:
                    pointing = f"{_stat(e, 'pointing', 'mean'):.0%} ({e['pointing_chance']:.0%})"
                rand = f"{_f(_stat(e, 'randomisation_abs_spearman'))} ({_f(_stat(e, 'null_abs_spearman'))})"
                top1 = _stat(e, "top1_occlusion", "mean")
                cells = [name, camera, kind, *(_f(_stat(e, f"deletion_k{k}")) for k in (1, 2, 4))]
                cells += ["-" if top1 is None else f"{top1:.0%}", _f(_stat(e, "spearman_occlusion")), pointing, rand]
                cells.append(_f(result["cost"].get(kind), 1))
                lines.append("| " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--split", choices=tuple(SPLITS), default="dev")
    parser.add_argument("--tasks", nargs="+", default=[t.name for t in BENCH_TASKS])
    parser.add_argument("--kinds", nargs="+", default=list(MAP_KINDS))
    args = parser.parse_args()
    chosen = [t for t in BENCH_TASKS if t.name in args.tasks]
    load_before = os.getloadavg()
    seed = SPLITS[args.split]
    results: dict[str, Any] = {}
    for task in chosen:
        folder = args.out / args.split / task.name
        episodes = record(task, seed, folder / "rollouts")
        seconds = explain(task, folder / "rollouts", folder / "maps", args.kinds)
        report = faithfulness(folder / "maps")
        results[task.name] = {
            "episodes": len(episodes),
            "successes": sum(bool(e["success"]) for e in episodes),
            "explain_seconds": seconds,
            "frames": report["steps_evaluated"],
            "faithfulness": report,
            "cost": costs(task, args.kinds, seed + 5_000),
        }
        print(f"{task.name}: {report['steps_evaluated']} frames", flush=True)
    holding = {
        kind: all(
            holds(result["faithfulness"]["cameras"][c]["kinds"].get(kind, {}))
            for result in results.values()
            for c in result["faithfulness"]["cameras"]
        )
        for kind in args.kinds
    }
    summary = {"split": args.split, "seed": seed, "tasks": results, "holds": holding}
    summary["machine"] = machine_line(load_before, os.getloadavg())
    (args.out / args.split / "bench.json").write_text(json.dumps(summary, indent=2, default=float))
    print("\n".join(table(results, args.kinds)))
    print(f"\nholds on every task and camera (deletion k=1 >= {HOLDS_DELETION}, top-1 >= {HOLDS_TOP1:.0%}):")
    print(", ".join(k for k, ok in holding.items() if ok) or "none")
    print(summary["machine"])


if __name__ == "__main__":
    main()
