"""Exhaustive occlusion's wall time per explained step and its program's memory against `MapOptions.mask_chunk` (how
many painted variants run vectorised at once), side by side: what the default chunk was kept or chosen by.

Per setting, the occlusion maps of one explained step (1 x 1 regions: every patch of every camera re-run once, plus
one unpainted reference per camera), through the model layer's maps function with the family's default target
(pi0-FAST `chunk`, pi0 / pi0.5 `chunk`), timed after one compiling call, the settings interleaved step by step so
that machine load hits every row alike; memory is XLA's analysis of the compiled program (`temp_size_in_bytes`: its
temporaries, what the chunk size bounds). The row "16, padded" runs the variants padded to whole chunks of 16, as
before `baseline_maps.balanced_chunk` evened the chunks out; "16, every camera" re-runs the variants of a camera the
model does not read (pi0.5's blank right wrist), as before `baseline_maps.camera_validity` left them out; "16, as
before" does both.

    python benchmarks/bench_occlusion.py --model pi0_fast           # bundled demo models: pi0_fast, pi05
    python benchmarks/bench_occlusion.py --model tiny_pi0_fast --steps 3   # golden tiny models (../shared/golden)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from openpi_cam import golden
from openpi_cam.checkpoints import model_spec
from openpi_cam.demo import bundled, task
from openpi_cam.model import baseline_maps, pi0, pi0_fast_maps, pi0_maps
from openpi_cam.model.pi0_fast import Pi0FAST
from openpi_cam.policies.pi0_fast_family import generated_steps
from openpi_cam.vocabulary import MapOptions

GOLDEN = Path(__file__).resolve().parents[1].parent / "shared" / "golden"
GOLDEN_CAMERAS = {
    "tiny_pi0_fast": ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"],
    "tiny_pi05": ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"],
}
PADDED = "16, padded"
EVERY_CAMERA = "16, every camera"
BEFORE = "16, as before"


@contextlib.contextmanager
def as_before(padded: bool, every_camera: bool) -> Iterator[None]:
    """Occlusion as it ran before: chunks of exactly `mask_chunk` variants (padded to a multiple of it, `padded`),
    every camera re-run whether or not the model reads it (`every_camera`)."""
    chunk, validity = baseline_maps.balanced_chunk, baseline_maps.camera_validity
    if padded:
        baseline_maps.balanced_chunk = lambda variants, chunk: chunk
    if every_camera:
        baseline_maps.camera_validity = lambda obs: np.ones(len(obs.images), bool)
    try:
        yield
    finally:
        baseline_maps.balanced_chunk, baseline_maps.camera_validity = chunk, validity


@contextlib.contextmanager
def recording(module, name: str, calls: list) -> Iterator[None]:
    """Records the arguments of every call of the jitted program `module.name` (to lower it again for its memory)."""
    program = getattr(module, name)

    def record(*args, **kwargs):
        calls.append((program, args, kwargs))
        return program(*args, **kwargs)

    setattr(module, name, record)
    try:
        yield
    finally:
        setattr(module, name, program)


def demo_steps(model: str, count: int, seed: int) -> tuple[Callable, list]:
    """(explain(options) per step, the steps) for a bundled demo model."""
    policy = model_spec.create_demo_policy(model=model)
    rng = np.random.default_rng(seed)
    steps = []
    for _ in range(count):
        scene = task.random_scene(rng)
        obs = bundled.policy_input(bundled.client_observation(task.observe(scene, task.random_start(rng, scene))))
        _, trace = policy.infer_traced(obs)
        noise = trace.sample_inputs.get("noise")
        noise = None if noise is None else np.asarray(noise)[None]
        steps.append((trace.observation, np.asarray(trace.output)[None], noise))
    return family_explain(policy.model), steps


def golden_steps(name: str, count: int) -> tuple[Callable, list]:
    folder, cameras = GOLDEN / name, GOLDEN_CAMERAS[name]
    cases = []
    for case in ("case_a", "case_b")[: max(1, min(count, 2))]:
        with np.load(folder / f"{case}.npz") as npz:
            data = {k: npz[k] for k in npz.files}
        cases.append(data)
    if name == "tiny_pi0_fast":
        model = Pi0FAST.from_checkpoint(
            folder / "checkpoint" / "params", dtype="float32", action_dim=8, action_horizon=10, max_token_len=48
        )
        steps = [(golden.load_observation(d, cameras), d["output_tokens"], None) for d in cases]
    else:
        model = pi0.Pi0.from_checkpoint(
            folder / "checkpoint" / "params", dtype="float32", action_horizon=10, max_token_len=48
        )
        steps = [(golden.load_observation(d, cameras), None, d["noise"]) for d in cases]
    return family_explain(model), [steps[i % len(steps)] for i in range(count)]


def family_explain(model) -> Callable:
    def explain(step, options: MapOptions) -> None:
        obs, generated, noise = step
        if isinstance(model, Pi0FAST):
            rows = [generated_steps(g) for g in generated]
            pi0_fast_maps.maps_for_chunk(model, obs, generated, rows, kinds=("occlusion",), options=options)
        else:
            pi0_maps.maps_for_actions(model, obs, noise, [pi0_maps.CHUNK], kinds=("occlusion",), options=options)

    return explain


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", choices=["pi0_fast", "pi05", *GOLDEN_CAMERAS], default="pi0_fast")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--chunks", type=int, nargs="+", default=[1, 4, 8, 16, 34])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    if args.model in GOLDEN_CAMERAS:
        explain, steps = golden_steps(args.model, args.steps)
    else:
        explain, steps = demo_steps(args.model, args.steps, args.seed)
    settings = {str(c): (MapOptions(mask_chunk=c), (False, False)) for c in args.chunks}
    settings[PADDED] = (MapOptions(mask_chunk=16), (True, False))
    settings[EVERY_CAMERA] = (MapOptions(mask_chunk=16), (False, True))
    settings[BEFORE] = (MapOptions(mask_chunk=16), (True, True))
    times: dict[str, list[float]] = {name: [] for name in settings}
    memory: dict[str, int | None] = {}
    for name, (options, before) in settings.items():  # compile every setting, and read its memory
        calls: list = []
        with (
            as_before(*before),
            recording(pi0_fast_maps, "_baseline_kinds", calls),
            recording(pi0_maps, "_flow_baseline_kinds", calls),
        ):
            explain(steps[0], options)
        program, a, kw = calls[0]
        with as_before(*before):
            analysis = program.lower(*a, **kw).compile().memory_analysis()
        memory[name] = getattr(analysis, "temp_size_in_bytes", None)
    for step in steps:
        for name, (options, before) in settings.items():
            with as_before(*before):
                t0 = time.perf_counter()
                explain(step, options)
                times[name].append(time.perf_counter() - t0)

    load = "load average {:.1f} {:.1f} {:.1f}".format(*os.getloadavg())
    print(f"{args.model}, exhaustive occlusion, {len(steps)} steps, {platform.machine()}, {os.cpu_count()} CPU cores")
    print(f"({load} at the end)")
    print(f"{'mask_chunk':>16} {'median ms':>10} {'vs 16':>6} {'temp MB':>8}")
    reference = statistics.median(times["16"]) if "16" in times else None
    for name, values in times.items():
        med = statistics.median(values)
        ratio = f"{med / reference:6.2f}" if reference else ""
        mb = "" if memory[name] is None else f"{memory[name] / 2**20:8.1f}"
        print(f"{name:>16} {med * 1e3:10.1f} {ratio} {mb}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
