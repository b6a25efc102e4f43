"""Training-step timings of the bundled demo model, layer stacks scanned vs unrolled, side by side in one run.

    python benchmarks/bench_train.py [--batch-size 32 --repeats 20]

One step is what `openpi_cam.demo.train` runs: forward, backward and the AdamW update on a real batch of the reaching
task (tokenized with the shipped tokenizers). Prints the median step time of each layout, their ratio, the time to
build one batch in Python, and what a 10,000-step training run costs at the measured rate.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import jax

from openpi_cam.demo import bundled, make_tokenizers
from openpi_cam.demo.data import Batches, load_normalize
from openpi_cam.demo.train import adamw, example_losses, training_step
from openpi_cam.model.pi0_fast import init_params
from openpi_cam.policies import demo_reach


def step_seconds(batch, repeats: int, *, scan: bool) -> float:
    """Median time of one compiled training step (fresh params and optimizer state, compiled before timing)."""
    cfg = bundled.model_config(make_tokenizers.VOCAB_SIZE, scan=scan)
    params = init_params(cfg, jax.random.key(0))
    optimizer = adamw(1e-3)
    opt_state = optimizer.init(params)
    step = training_step(example_losses(cfg, decode_offset=1), optimizer)
    key = jax.random.key(0)

    params, opt_state, loss = step(params, opt_state, batch, key)
    jax.block_until_ready(loss)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        params, opt_state, loss = step(params, opt_state, batch, key)
        jax.block_until_ready(loss)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()

    batches = Batches(
        demo_reach.ASSETS, load_normalize(demo_reach.ASSETS), args.batch_size, seed=0, contrast_pairs=True
    )
    t0 = time.perf_counter()
    batch = [batches() for _ in range(args.repeats)][-1]
    batch_s = (time.perf_counter() - t0) / args.repeats
    timings = {}
    for unrolled in (False, True):
        timings[unrolled] = step_seconds(batch, args.repeats, scan=not unrolled)

    print(f"machine: {platform.machine()} {platform.processor() or ''}, {jax.device_count()} x {jax.devices()[0]}")
    print(f"demo model, batch {args.batch_size}, median of {args.repeats} steps")
    print("| | seconds per step | 10,000 steps |")
    print("| --- | --- | --- |")
    for unrolled, label in ((False, "layers scanned"), (True, "layers unrolled (served layout)")):
        print(f"| {label} | {timings[unrolled]:.3f} | {timings[unrolled] * 10_000 / 60:.0f} min |")
    print(f"| building one batch (Python) | {batch_s:.3f} | {batch_s * 10_000 / 60:.0f} min |")
    print(f"unrolled / scanned: {timings[True] / timings[False]:.2f}x the time")


if __name__ == "__main__":
    main()
