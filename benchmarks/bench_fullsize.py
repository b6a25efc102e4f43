"""The full-size pi0-FAST (SigLIP So400m/14 + Gemma 2B, upstream's parameter tree) in bfloat16 on whatever JAX runs
on: time and peak memory of loading, prefill + greedy decode (a chunk), and explanations of generated tokens.

Weights are random (no download): N(0, 0.02) in bfloat16, drawn leaf by leaf so that nothing holds a float32 copy of
the 2.9B parameters (on the CPU with NumPy straight into each leaf's buffer; on an accelerator on the device).
Inputs: DROID's layout (3 cameras at 224 px, `max_token_len` 250 prompt slots, `--prompt-tokens` of them used).
Random weights never emit EOS, so a decode of N steps runs all N: a chunk of a real checkpoint stops at its EOS.

Rows (each timed `--rounds` times after a first, compiling call; medians):
  prefill + N decode steps     our `Pi0FAST.sample_actions`, for each N of `--decode-steps`
  upstream                     with `--upstream-src`: upstream's own `sample_actions` on the same weights, inputs
                               and device (`upstream_fast_timing.py`, in a subprocess), and whether its tokens are ours
  one token                    gradcam + gradnorm of token 0, as the side channel asks for it (no full logit vector),
                               in the layout it is served with (`model.remat`: the stack's remat dropped where XLA's
                               memory analysis says the program fits the device) and, with `--compare-remat` (the
                               default on an accelerator), with remat forced on
  K tokens in one call         the same for tokens 0..K-1 (`--explain-tokens`), as `all-action-tokens` asks
  ig, occlusion                with `--map-kinds`: the baseline kinds of the same token, default `MapOptions` (IG: 16
                               Gauss-Legendre points, doubled while completeness misses 2%; occlusion: every patch of
                               every camera alone, C x (N + 1) re-runs of the whole model); with `--compare-remat`
                               also IG with the stack's remat off
Peak memory: the process's resident-set high-water mark (VmHWM) and, on an accelerator, the device's
`peak_bytes_in_use` (device memory is not preallocated, so that figure is what the programs used).

    python benchmarks/bench_fullsize.py --decode-steps 8                                     # this 2-core CPU machine
    python benchmarks/bench_fullsize.py --decode-steps 32 256 --rounds 3 --explain-tokens 16 \
        --map-kinds ig occlusion --upstream-src ../openpi                                      # a GPU
"""

from __future__ import annotations

import os

# Before JAX starts: an accelerator's memory is taken as needed, so its peak is the programs' own (and the upstream
# subprocess finds room on the same device).
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse
import contextlib
import dataclasses
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model import pi0_fast_maps, remat
from openpi_cam.model.config import GemmaConfig, Pi0FASTConfig, param_shapes
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0_fast import Pi0FAST
from openpi_cam.nested import unflatten_dict

CAMERAS = ("base_0_rgb", "base_1_rgb", "wrist_0_rgb")
# openpi #271: pi0_fast_droid served by upstream on an RTX 4090, one chunk (a real checkpoint, stopping at its EOS).
UPSTREAM_PUBLISHED_4090_S = 0.388


def fullsize_config(llm_depth: int | None = None, siglip_depth: int | None = None) -> Pi0FASTConfig:
    """pi0_fast_droid's model: Gemma 2B + So400m/14, action_dim 8, horizon 10, 250 prompt slots; depths replaceable
    for smoke runs."""
    cfg = Pi0FASTConfig(gemma=GemmaConfig(remat=True), action_dim=8, action_horizon=10, max_token_len=250)
    gemma = dataclasses.replace(cfg.gemma, depth=llm_depth or cfg.gemma.depth)
    siglip = dataclasses.replace(cfg.siglip, depth=siglip_depth or cfg.siglip.depth)
    return dataclasses.replace(cfg, gemma=gemma, siglip=siglip)


def rss_gb(field: str = "VmHWM") -> float:
    with open("/proc/self/status") as f:
        line = next(line for line in f if line.startswith(field + ":"))
    return int(line.split()[1]) / 2**20


def device_peak_gb() -> float | None:
    stats = jax.devices()[0].memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return None if peak is None else peak / 2**30


def random_params(shapes: dict[str, tuple[int, ...]]) -> dict:
    """N(0, 0.02) in bfloat16, the same for every process on the same kind of backend (norm scales included: this
    measures cost, not quality). On the CPU, NumPy draws in chunks straight into each leaf's bfloat16 buffer:
    `jax.random.normal` would materialise a 0.5B-element embedding's random bits and float32 values at once (22.6 GB
    peak). On an accelerator each leaf is drawn on the device (seconds instead of minutes of host time)."""
    if jax.default_backend() != "cpu":
        key = jax.random.key(0)
        return unflatten_dict(
            {
                path: 0.02 * jax.random.normal(jax.random.fold_in(key, i), shape, jnp.bfloat16)
                for i, (path, shape) in enumerate(sorted(shapes.items()))
            }
        )
    rng = np.random.default_rng(0)
    chunk = 1 << 24
    leaves = {}
    for path, shape in sorted(shapes.items()):
        host = np.empty(int(np.prod(shape)), jnp.bfloat16)
        for start in range(0, host.size, chunk):
            stop = min(start + chunk, host.size)
            host[start:stop] = 0.02 * rng.standard_normal(stop - start, np.float32)
        leaves[path] = jax.device_put(host.reshape(shape))
        del host
    return unflatten_dict(leaves)


def observation(cfg: Pi0FASTConfig, prompt_tokens: int) -> Observation:
    rng = np.random.default_rng(0)
    size = cfg.siglip.image_size
    mask = np.zeros((1, cfg.max_token_len), bool)
    mask[:, :prompt_tokens] = True
    return Observation(
        images={c: rng.uniform(-1, 1, (1, size, size, 3)).astype(np.float32) for c in CAMERAS},
        image_masks={c: np.ones((1,), bool) for c in CAMERAS},
        state=np.zeros((1, cfg.action_dim), np.float32),
        tokenized_prompt=rng.integers(2, 1000, (1, cfg.max_token_len)).astype(np.int32) * mask,
        tokenized_prompt_mask=mask,
        token_ar_mask=np.zeros((1, cfg.max_token_len), np.int32),
    )


@contextlib.contextmanager
def remat_forced():
    """Explanations keep the stack's remat whatever the device's memory (`model.remat` sees no device report)."""
    report = remat.free_device_bytes
    remat.free_device_bytes = lambda params: None
    try:
        yield
    finally:
        remat.free_device_bytes = report


def timed(fn, rounds: int) -> tuple[float, float, object]:
    """(first call's seconds, median of `rounds` later calls, the last call's result)."""
    times = []
    for _ in range(rounds + 1):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return times[0], statistics.median(times[1:]), out


def run_upstream(args: argparse.Namespace) -> dict:
    spec = {
        "decode_steps": args.decode_steps,
        "prompt_tokens": args.prompt_tokens,
        "llm_depth": args.llm_depth,
        "siglip_depth": args.siglip_depth,
    }
    path = Path(tempfile.mkdtemp(prefix="bench_fullsize_")) / "spec.json"
    path.write_text(json.dumps(spec))
    script = Path(__file__).with_name("upstream_fast_timing.py")
    cmd = [args.upstream_python, str(script), "--upstream-src", str(args.upstream_src), "--spec", str(path)]
    out = subprocess.run([*cmd, "--repeats", str(args.rounds)], capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"upstream timing failed:\n{out.stderr[-4000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--decode-steps", type=int, nargs="+", default=[8])
    parser.add_argument("--prompt-tokens", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=1, help="timed calls after the first (compiling) one")
    parser.add_argument("--explain-tokens", type=int, default=0, help="also explain tokens 0..K-1 in one call")
    parser.add_argument("--map-kinds", nargs="*", default=[], choices=["ig", "occlusion"])
    parser.add_argument(
        "--compare-remat",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also explain with remat forced on (default: on an accelerator, where the served layout may drop it)",
    )
    parser.add_argument("--llm-depth", type=int, default=None, help="smoke runs: fewer Gemma layers")
    parser.add_argument("--siglip-depth", type=int, default=None, help="smoke runs: fewer SigLIP layers")
    parser.add_argument("--upstream-src", type=Path, default=None, help="a checkout of upstream OpenPI")
    parser.add_argument("--upstream-python", default=sys.executable, help="an interpreter with upstream's deps")
    args = parser.parse_args()
    accelerator = jax.default_backend() != "cpu"
    compare_remat = accelerator if args.compare_remat is None else args.compare_remat

    cfg = fullsize_config(args.llm_depth, args.siglip_depth)
    shapes = param_shapes(cfg.gemma, cfg.siglip)
    count = sum(int(np.prod(s)) for s in shapes.values())
    print(
        f"pi0-FAST {count / 1e9:.2f}B parameters (Gemma depth {cfg.gemma.depth}, SigLIP depth {cfg.siglip.depth}), "
        f"bfloat16; {platform.machine()}, {jax.devices()[0].device_kind}, jax {jax.__version__}",
        flush=True,
    )
    rows: list[tuple[str, str, str, str]] = []

    def row(label: str, first: float, median: float | None = None, *_) -> float | None:
        dev = device_peak_gb()
        peak = f"{rss_gb():.1f} GB host" + (f", {dev:.1f} GB device" if dev is not None else "")
        rows.append((label, f"{1e3 * first:,.0f}", "" if median is None else f"{1e3 * median:,.0f}", peak))
        print(" | ".join(rows[-1]), flush=True)
        return median

    start = time.perf_counter()
    model = Pi0FAST(cfg, jax.block_until_ready(random_params(shapes)))
    row("random bfloat16 params", time.perf_counter() - start, None)
    obs = observation(cfg, args.prompt_tokens)
    ours: dict[int, tuple[float, np.ndarray]] = {}  # decode steps -> (median seconds, tokens)
    for steps in args.decode_steps:
        first, median, tokens = timed(
            lambda s=steps: model.sample_actions(jax.random.key(0), obs, max_decoding_steps=s), args.rounds
        )
        ours[steps] = (row(f"prefill + {steps} decode steps", first, median), np.asarray(tokens))
    generated = ours[max(args.decode_steps)][1]

    def explain(m: Pi0FAST, steps: list[int], kinds: tuple[str, ...] = ("gradcam", "gradnorm")):
        res = pi0_fast_maps.maps_for_steps(m, obs, generated, steps, kinds=kinds, logits=False)
        if res.ig_completeness is not None:
            ig_steps.append(res.ig_completeness.steps)
        return res.score

    ig_steps: list[int] = []  # IG's quadrature points per call (doubled while completeness misses 2%)

    def explain_row(label: str, m: Pi0FAST, steps: list[int], kinds: tuple[str, ...] = ("gradcam", "gradnorm")):
        ig_steps.clear()
        decided = len(remat._fits)
        times = timed(lambda: explain(m, steps, kinds), args.rounds)
        notes = [f"{'/'.join(map(str, ig_steps))} IG points"] if ig_steps else []
        notes += [f"remat {'off' if fits else 'kept'}" for fits in list(remat._fits.values())[decided:]]
        row(f"{label} ({', '.join(notes)})" if notes else label, *times)

    explanations = [("one token", [0])]
    if args.explain_tokens:
        explanations.append((f"{args.explain_tokens} tokens in one call", list(range(args.explain_tokens))))
    for label, steps in explanations:
        if compare_remat:
            with remat_forced():
                explain_row(f"explanation: {label}, remat forced", model, steps)
        explain_row(f"explanation: {label}, layout as served", model, steps)
    for kind in args.map_kinds:
        explain_row(f"explanation: one token, {kind}", model, [0], (kind,))
    if compare_remat and "ig" in args.map_kinds:
        kept = Pi0FAST(remat.without_remat(cfg), model.params)
        explain_row("explanation: one token, ig, remat off", kept, [0], ("ig",))

    upstream = None
    if args.upstream_src:
        try:
            upstream = run_upstream(args)
        except RuntimeError as err:  # our rows are measured already: print them anyway
            print(err, flush=True)
    print()
    print(f"| quantity ({jax.devices()[0].device_kind}) | first call ms | median ms ({args.rounds} calls) | peak |")
    print("| --- | --- | --- | --- |")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    if upstream:
        for steps in args.decode_steps:
            up = upstream["decode"][str(steps)]
            ours_s, tokens = ours[steps]
            same = np.array_equal(np.asarray(up["tokens"]), tokens)
            print(
                f"| upstream prefill + {steps} decode steps (jax {upstream['jax']}; tokens "
                f"{'identical' if same else 'differ'}) | {1e3 * up['first_call_s']:,.0f} | "
                f"{1e3 * up['median_s']:,.0f} | ours / upstream {ours_s / up['median_s']:.2f} |"
            )
    if accelerator:
        published = f"{1e3 * UPSTREAM_PUBLISHED_4090_S:.0f}"
        print(f"| upstream, published (openpi #271: RTX 4090, one chunk of a real checkpoint) | | {published} | |")


if __name__ == "__main__":
    main()
