"""Frames explained per second when explaining a LeRobot dataset: the local engine and Ray with 1 and 2 workers.

    python benchmarks/bench_dataset.py [--dataset demo_reach_v30_video --rounds 1]
    python benchmarks/bench_dataset.py --batch-sizes 1 4 16 --dataset rollouts [--rounds 3]

The bundled demo model (pi0-FAST, float32) explains every episode of a LeRobot-written demo dataset from
`../shared/lerobot` (gradcam + gradnorm of the first action token, the default spot check), each engine in a fresh
process, so each job pays its own start: the model loaded once per worker, its programs made ready during each
worker's first episode (by default read from a JAX compilation cache that a warm-up job fills first, as a cluster with
a shared cache would; `--cold`: compiled by every worker), and for Ray a local instance started and stopped. Printed
per engine:

- first episode done: seconds from the job's start to the end of each worker's first episode (median over workers):
  start, model load, compilation and one episode;
- end to end: frames / wall time of the whole job, all of the above included (what a user waits for on a dataset this
  small, where compilation dominates);
- steady: each worker's frames after its first episode over the time from its first episode's end to its last one's
  (episode ends as the driver receives them), summed over the workers: the rate once everything is compiled,
  with the per-episode overhead of the engine (Ray's dispatch and result return) included;
- the steady cost per frame split into decode, inference, explanation and writing (`JobSummary.seconds`): worker time
  summed over workers (with 2 workers it can exceed the wall time per frame). For Ray, each worker's episodes after
  its first (the engine's per-episode debug records); for the local engine, a second pass over the dataset with the
  same, now compiled, policy (`run_local` reports no per-episode split).

With `--batch-sizes`, the local engine alone at each batch size (frames explained per model call, within an
episode), each in a fresh process, steady phases as above; `--dataset rollouts` records closed-loop demo rollouts
first (8 episodes of 30 frames: long enough for batches of 16). With `--rounds` above 1 the engines (batch sizes) run
in a rotated order each round and the medians are printed. The machine line
gives the load average before and after: on a shared machine the workers compete with everything else for the cores.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Iterator
from typing import Any

from bench_serving import machine_line

SHARED_LEROBOT = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "lerobot"
ENGINES = (("local", 1), ("ray", 1), ("ray", 2))
PHASES = ("decode", "inference", "explanation", "writing")


def _job(spec: dict[str, Any], out: pathlib.Path) -> Any:
    from openpi_cam.checkpoints.model_spec import ModelSpec
    from openpi_cam.maps.explain import DatasetJob, dataset_keys
    from openpi_cam.vocabulary import ExplainOptions

    keys, nested = dataset_keys(ModelSpec(), {})
    options = ExplainOptions(target="action-token", maps=("gradcam", "gradnorm"))
    batch = spec.get("batch_size", 8)
    return DatasetJob(pathlib.Path(spec["source"]), out, ModelSpec(), options, keys, batch, nested_keys=nested)


def run_local_job(spec: dict[str, Any]) -> dict[str, Any]:
    from openpi_cam.checkpoints.model_spec import ModelSpec
    from openpi_cam.maps import dataset as fmt
    from openpi_cam.maps.explain import run_local

    t0 = time.perf_counter()
    ends: list[tuple[int, float]] = []

    def timed(episodes: Iterable[int], total: int) -> Iterator[int]:
        # run_local asks for the next episode once the previous one is written.
        for episode in episodes:
            if ends:
                ends[-1] = (ends[-1][0], time.perf_counter() - t0)
            ends.append((episode, float("nan")))
            yield episode
        ends[-1] = (ends[-1][0], time.perf_counter() - t0)

    out = pathlib.Path(spec["out"])
    policy = ModelSpec().create()
    summary = run_local(_job(spec, out / "cold"), policy=policy, progress=timed)
    wall = time.perf_counter() - t0
    maps = fmt.open_maps_dataset(out / "cold")
    episodes = [
        {"episode": e, "worker": "local", "frames": maps.table(e).num_rows, "done_at": at, "seconds": None}
        for e, at in ends
    ]
    warm = run_local(_job(spec, out / "warm"), policy=policy)
    return {
        "wall": wall,
        "frames": summary.counts["explained"],
        "episodes": episodes,
        "steady_seconds": warm.seconds,
        "steady_frames": warm.counts["explained"],
    }


def run_ray_job(spec: dict[str, Any]) -> dict[str, Any]:
    from openpi_cam.maps import ray_engine

    records: list[tuple[dict[str, Any], float]] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if hasattr(record, ray_engine.EPISODE_RECORD):
                records.append((getattr(record, ray_engine.EPISODE_RECORD), record.created))

    logger = logging.getLogger(ray_engine.__name__)
    logger.setLevel(logging.DEBUG)
    logger.addHandler(Collect())
    start = time.time()
    t0 = time.perf_counter()
    summary = ray_engine.run_ray(_job(spec, pathlib.Path(spec["out"]) / "cold"), workers=spec["workers"])
    wall = time.perf_counter() - t0
    episodes = [
        {
            "episode": r["episode"],
            "worker": r["worker"],
            "frames": r["counts"].get("explained", 0),
            "done_at": r["finished_at"] - start,  # the worker's clock, the driver's here (a local Ray instance)
            "received_at": created - start,
            "seconds": r["seconds"],
        }
        for r, created in records
    ]
    firsts: dict[str, int] = {}
    for e in sorted(episodes, key=lambda e: e["done_at"]):
        firsts.setdefault(e["worker"], e["episode"])
    later = [e for e in episodes if firsts[e["worker"]] != e["episode"]]
    steady = {p: sum(e["seconds"][p] for e in later) for p in PHASES}
    return {
        "wall": wall,
        "frames": summary.counts["explained"],
        "episodes": episodes,
        "steady_seconds": steady,
        "steady_frames": sum(e["frames"] for e in later),
    }


def spawn(spec: dict[str, Any], log: pathlib.Path) -> dict[str, Any]:
    """Runs one engine in a fresh Python process, so that nothing compiled or started by another engine is reused."""
    with log.open("w") as err:
        proc = subprocess.run(
            [sys.executable, __file__, "--child", json.dumps(spec)], stdout=subprocess.PIPE, stderr=err, text=True
        )
    if proc.returncode != 0:
        raise RuntimeError(
            f"{spec['engine']} x{spec['workers']} failed (exit {proc.returncode}):\n{log.read_text()[-3000:]}"
        )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def figures(run: dict[str, Any]) -> dict[str, float]:
    by_worker: dict[str, list[dict[str, Any]]] = {}
    for e in sorted(run["episodes"], key=lambda e: e["done_at"]):
        by_worker.setdefault(e["worker"], []).append(e)
    # A worker that did one episode only (still compiling while the others finished the rest) adds no steady rate.
    steady_fps = sum(
        sum(e["frames"] for e in done[1:]) / (done[-1]["done_at"] - done[0]["done_at"])
        for done in by_worker.values()
        if len(done) > 1
    )
    out = {
        "frames": run["frames"],
        "first_done": statistics.median(done[0]["done_at"] for done in by_worker.values()),
        "wall": run["wall"],
        "end_to_end_fps": run["frames"] / run["wall"],
        "steady_fps": steady_fps,
        "per_worker": "/".join(str(len(done)) for done in by_worker.values()),
    }
    for phase in PHASES:
        out[f"{phase}_ms"] = 1000.0 * run["steady_seconds"][phase] / run["steady_frames"]
    return out


def record_rollouts(out: pathlib.Path) -> pathlib.Path:
    """Closed-loop demo rollouts that all run to the step limit (`openpi-cam demo --perturb absent --record`): 8
    episodes of 30 frames, long enough for batches of 16 frames within an episode."""
    from openpi_cam import cli

    argv = ["demo", "--no-explain", "--num-episodes", "8", "--perturb", "absent", "--record", str(out)]
    cli.main(argv)
    return out


def batch_sizes(args: argparse.Namespace) -> None:
    """The local engine's steady frames per second at each batch size, each in a fresh process, side by side (the
    order rotated every round)."""
    from openpi_cam.lerobot.dataset import open_dataset

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        source = record_rollouts(pathlib.Path(tmp) / "rollouts") if args.dataset == "rollouts" else _source(args)
        ds = open_dataset(source)
        runs: dict[int, list[dict[str, float]]] = {b: [] for b in args.batch_sizes}
        for r in range(args.rounds):
            for i in range(len(args.batch_sizes)):
                batch = args.batch_sizes[(i + r) % len(args.batch_sizes)]
                out = pathlib.Path(tmp) / f"r{r}-b{batch}"
                out.mkdir()
                spec = {"source": str(source), "out": str(out), "engine": "local", "workers": 1, "batch_size": batch}
                run = spawn(spec, out / "stderr.log")
                runs[batch].append(figures(run))
                print(f"round {r}: batch {batch}: {run['frames']} frames", file=sys.stderr, flush=True)
        load_after = os.getloadavg()
    print(machine_line(load_before, load_after))
    lengths = [ds.episode_length(e) for e in ds.episodes]
    print(
        f"dataset {source.name}: {len(lengths)} episodes of {min(lengths)}-{max(lengths)} frames; demo pi0-FAST "
        f"float32, gradcam + gradnorm of the first action token, spot check on; local engine, steady (a second pass "
        f"with the compiled policy); {args.rounds} round(s), medians"
    )
    columns = ["batch size", "steady frames/s", "vs batch 1", *(f"{p} ms/frame" for p in PHASES)]
    print("| " + " | ".join(columns) + " |")
    print("|" + " --- |" * len(columns))
    med = {b: {k: statistics.median(f[k] for f in rs) for k in rs[0] if k != "per_worker"} for b, rs in runs.items()}
    base = med[args.batch_sizes[0]]
    for batch, m in med.items():
        fps = 1000.0 / sum(m[f"{p}_ms"] for p in PHASES)
        base_fps = 1000.0 / sum(base[f"{p}_ms"] for p in PHASES)
        cells = [str(batch), f"{fps:.2f}", f"{fps / base_fps:.2f}", *(f"{m[f'{p}_ms']:.1f}" for p in PHASES)]
        print("| " + " | ".join(cells) + " |")


def _source(args: argparse.Namespace) -> pathlib.Path:
    source = pathlib.Path(args.dataset)
    return source if source.is_dir() else SHARED_LEROBOT / args.dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--dataset",
        default="demo_reach_v30_video",
        help="a folder of ../shared/lerobot, a path, or `rollouts` (recorded demo rollouts, 30 frames an episode)",
    )
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--cold", action="store_true", help="no warm-up: every worker compiles from scratch")
    parser.add_argument(
        "--batch-sizes", type=int, nargs="+", help="compare the local engine's batch sizes instead of the engines"
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        spec = json.loads(args.child)
        print(json.dumps(run_local_job(spec) if spec["engine"] == "local" else run_ray_job(spec)))
        return
    if args.batch_sizes:
        batch_sizes(args)
        return

    from openpi_cam.lerobot.dataset import open_dataset

    source = _source(args)
    n_episodes = len(open_dataset(source).episodes)
    if n_episodes < 2 * max(w for _, w in ENGINES):
        raise SystemExit(f"{source} has {n_episodes} episodes: too few for two per worker")

    load_before = os.getloadavg()
    runs: dict[tuple[str, int], list[dict[str, float]]] = {e: [] for e in ENGINES}
    with tempfile.TemporaryDirectory() as tmp:
        if not args.cold:
            # Every worker of every engine then loads its compiled programs from this cache instead of compiling.
            os.environ["JAX_COMPILATION_CACHE_DIR"] = str(pathlib.Path(tmp) / "jax_cache")
            os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
            os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
            (pathlib.Path(tmp) / "warmup").mkdir()
            spec = {"source": str(source), "out": str(pathlib.Path(tmp) / "warmup"), "engine": "local", "workers": 1}
            spawn(spec, pathlib.Path(tmp) / "warmup" / "stderr.log")
        for r in range(args.rounds):
            for i in range(len(ENGINES)):
                engine, workers = ENGINES[(i + r) % len(ENGINES)]
                out = pathlib.Path(tmp) / f"r{r}-{engine}{workers}"
                out.mkdir()
                spec = {"source": str(source), "out": str(out), "engine": engine, "workers": workers}
                run = spawn(spec, out / "stderr.log")
                runs[(engine, workers)].append(figures(run))
                print(f"round {r}: {engine} x{workers}: {run}", file=sys.stderr, flush=True)
    load_after = os.getloadavg()

    med = {e: {k: statistics.median(f[k] for f in rs) for k in rs[0] if k != "per_worker"} for e, rs in runs.items()}
    local = med[("local", 1)]
    print(machine_line(load_before, load_after))
    print(
        f"dataset {source.name}: {n_episodes} episodes, {int(local['frames'])} frames; demo pi0-FAST float32, "
        f"gradcam + gradnorm of the first action token, spot check on; {args.rounds} round(s), medians; "
        + ("cold: every worker compiles" if args.cold else "warm: programs from a compilation cache filled first")
    )
    columns = ["engine", "workers", "first episode done s", "whole job s", "end to end frames/s", "steady frames/s"]
    columns += ["steady vs local", "episodes per worker", *(f"{p} ms/frame" for p in PHASES)]
    print("| " + " | ".join(columns) + " |")
    print("|" + " --- |" * len(columns))
    for (engine, workers), m in med.items():
        cells = [engine, str(workers), f"{m['first_done']:.1f}", f"{m['wall']:.1f}", f"{m['end_to_end_fps']:.3f}"]
        cells += [f"{m['steady_fps']:.2f}", f"{m['steady_fps'] / local['steady_fps']:.2f}"]
        cells += [" ; ".join(f["per_worker"] for f in runs[(engine, workers)])]
        cells += [f"{m[f'{p}_ms']:.1f}" for p in PHASES]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
