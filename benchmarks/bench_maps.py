"""What each map kind costs next to the inference it explains, on a bundled demo model, measured side by side.

For `--scenes` fresh demo scenes (after one compile scene), times `policy.infer` and one explanation per kind set
(gradcam + gradnorm share a backward pass, gradxinput rides on it; taylor continues it through SigLIP; smoothgrad;
ig; occlusion; rise; all four compared kinds; lrp, its own modified backward pass through SigLIP too) through the
family's explainer, exactly what the side channel runs per explained request, and the spot check the side channel
adds to the gradcam + gradnorm explanation (each map's top patch and `--check-patches` random patches re-scored,
`cam.spot_check`), interleaved scene by scene so that machine load hits every row alike. Prints medians, the ratio
explanation / inference and the cost in backward-pass equivalents: each row's time over the gradcam + gradnorm
pass's on the same scene, the median over scenes (steadier under load than a ratio of medians).

    python benchmarks/bench_maps.py                       # pi0-FAST demo model, target chunk
    python benchmarks/bench_maps.py --model pi05 --target action
    python benchmarks/bench_maps.py --dtype bfloat16 --target action-token --compare-ig-stall
    python benchmarks/bench_maps.py --sets gradcam+gradnorm lrp --scenes 40   # the two one-pass rows alone

`--compare-ig-stall` adds a row "ig, no stall": IG with its quadrature points doubled to the cap whenever completeness
misses its target, as before `attribution.IG_STALL` (which stops doubling when a doubling did not shrink the error).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from openpi_cam.cam.spot_check import check_trace
from openpi_cam.checkpoints import model_spec
from openpi_cam.demo import bundled, task
from openpi_cam.model import attribution, baseline_maps
from openpi_cam.vocabulary import DEFAULT_PATCHES, ExplainOptions

GRADIENT_PASS = "gradcam+gradnorm"
KIND_SETS = {
    GRADIENT_PASS: ("gradcam", "gradnorm"),
    "+gradxinput": ("gradcam", "gradnorm", "gradxinput"),
    "taylor": ("taylor",),
    "smoothgrad": ("smoothgrad",),
    "ig": ("ig",),
    "occlusion": ("occlusion",),
    "rise": ("rise",),
    "all four": ("gradcam", "gradnorm", "ig", "occlusion"),
    "lrp": ("lrp",),
}


@contextlib.contextmanager
def ig_stall(value: float):
    """IG's refinement with `value` in place of `attribution.IG_STALL` (inf: doubling to the cap, as before it)."""
    kept = baseline_maps.IG_STALL
    baseline_maps.IG_STALL = value
    try:
        yield
    finally:
        baseline_maps.IG_STALL = kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", choices=["pi0_fast", "pi05"], default="pi0_fast")
    parser.add_argument("--target", default="chunk")
    parser.add_argument("--scenes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--check-patches", type=int, default=DEFAULT_PATCHES)
    parser.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32")
    parser.add_argument("--compare-ig-stall", action="store_true")
    # the kind sets to time (the gradient kinds' pass always: every ratio is to it)
    parser.add_argument("--sets", nargs="+", choices=list(KIND_SETS), default=list(KIND_SETS))
    args = parser.parse_args()

    policy = model_spec.create_demo_policy(model=args.model, dtype=args.dtype)
    chosen = {name: KIND_SETS[name] for name in KIND_SETS if name in args.sets or name == GRADIENT_PASS}
    kind_sets = {**chosen, **({"ig, no stall": ("ig",)} if args.compare_ig_stall else {})}
    explainer = policy.explainer
    rng = np.random.default_rng(args.seed)
    check_row = f"spot check ({args.check_patches})"
    times: dict[str, list[float]] = {"infer": [], **{name: [] for name in kind_sets}, check_row: []}
    ig_steps: dict[str, list[int]] = {"ig": [], "ig, no stall": []}
    for scene_index in range(args.scenes + 1):
        scene = task.random_scene(rng)
        obs = bundled.policy_input(bundled.client_observation(task.observe(scene, task.random_start(rng, scene))))
        t0 = time.perf_counter()
        _, trace = policy.infer_traced(obs)
        infer_s = time.perf_counter() - t0
        outputs = np.asarray(trace.output)[None]
        sample_inputs = {k: np.asarray(v)[None] for k, v in trace.sample_inputs.items()}
        row = {"infer": infer_s}
        for name, kinds in kind_sets.items():
            request = ExplainOptions(args.target, maps=kinds)
            with ig_stall(np.inf if name == "ig, no stall" else attribution.IG_STALL):
                t0 = time.perf_counter()
                [explanation] = explainer.explain(trace.observation, outputs, request, sample_inputs)
                row[name] = time.perf_counter() - t0
            if name in ig_steps and scene_index > 0:
                ig_steps[name].append(explanation.details["ig_completeness"]["steps"])
            if name == GRADIENT_PASS:
                t0 = time.perf_counter()
                options, patches = request.map_options, args.check_patches
                check = check_trace(explainer, trace, explanation, options, patches=patches, seed=0)
                row[check_row] = time.perf_counter() - t0
                assert check.skipped is None, check
        if scene_index == 0:
            continue  # compilation
        for name, seconds in row.items():
            times[name].append(seconds)

    cpu = f"{os.cpu_count()} CPU cores" if sys.platform != "darwin" else platform.processor()
    model = f"{args.model} demo model ({args.dtype}), target {args.target}"
    load = ""
    if hasattr(os, "getloadavg"):
        load = ", load average {:.1f} {:.1f} {:.1f} at the end".format(*os.getloadavg())
    print(f"{model}, {args.scenes} scenes, {platform.machine()}, {cpu}{load}")
    infer = statistics.median(times["infer"])
    print(f"{'':>18} {'median ms':>10} {'x inference':>12} {'x gradient pass':>16}")
    for name, values in times.items():
        med = statistics.median(values)
        passes = statistics.median(v / g for v, g in zip(values, times[GRADIENT_PASS], strict=True))
        print(f"{name:>18} {med * 1e3:10.1f} {med / infer:12.1f} {passes:16.2f}")
    for name, used in ig_steps.items():
        if used:
            counts = dict(zip(*np.unique(used, return_counts=True), strict=True))
            print(f"{name}: IG quadrature points used (points: scenes):", {int(k): int(v) for k, v in counts.items()})


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
