"""Model and Grad-CAM timings for a small pi0-FAST, measured side by side in one run.

    python benchmarks/bench_model.py [--width 256 --depth 4 --steps 64 --repeats 5]

Prints a table: prefill time, per-token decode time, compilations over repeated calls, and the Grad-CAM ratios
(one token vs inference, one token vs the prefill forward, all action tokens in one call vs a per-token loop).
Random weights: timings do not depend on the values, and greedy decoding runs all `--steps` (no EOS early stop
unless it happens to be sampled, which the table reports).
"""

from __future__ import annotations

import argparse
import functools
import platform
import statistics
import time

import jax
import numpy as np

from openpi_cam.model import pi0_fast_maps as maps
from openpi_cam.model.config import GemmaConfig, Pi0FASTConfig, SiglipConfig
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, embed_prefix, init_params, prefill, sample_tokens_jit


def timed(fn, repeats: int) -> float:
    """Median wall time of `fn()` (blocking on its result), after one warm-up call."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def make_observation(cfg: Pi0FASTConfig, cameras: int, prompt_len: int, seed: int = 0) -> Observation:
    rng = np.random.default_rng(seed)
    size = cfg.siglip.image_size
    images = {f"cam{i}": rng.uniform(-1, 1, (1, size, size, 3)).astype(np.float32) for i in range(cameras)}
    tokens = np.zeros((1, cfg.max_token_len), np.int32)
    tokens[0, :prompt_len] = rng.integers(2, cfg.gemma.vocab_size, prompt_len)
    mask = np.arange(cfg.max_token_len)[None] < prompt_len
    return Observation(
        images=images,
        image_masks={k: np.ones(1, bool) for k in images},
        state=np.zeros((1, cfg.action_dim), np.float32),
        tokenized_prompt=tokens,
        tokenized_prompt_mask=mask,
        token_ar_mask=np.zeros_like(tokens),
        token_loss_mask=np.zeros_like(mask),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--vision-width", type=int, default=64)
    ap.add_argument("--vocab", type=int, default=4096)
    ap.add_argument("--cameras", type=int, default=3)
    ap.add_argument("--steps", type=int, default=64, help="max_decoding_steps")
    ap.add_argument("--tokens", type=int, default=8, help="action tokens explained in the all-tokens comparison")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dtype", default="float32")
    args = ap.parse_args()

    gemma = GemmaConfig(args.width, args.depth, 4 * args.width, 4, 1, args.width // 4, args.vocab)
    siglip = SiglipConfig(args.vision_width, 2, 4 * args.vision_width, 2, 14, 224, args.width)
    cfg = Pi0FASTConfig(gemma=gemma, siglip=siglip, action_dim=8, action_horizon=10, max_token_len=48, dtype=args.dtype)
    model = Pi0FAST(cfg, init_params(cfg, jax.random.key(0)))
    obs = make_observation(cfg, args.cameras, prompt_len=30)
    key = jax.random.key(0)

    @functools.partial(jax.jit, static_argnames=("steps",))
    def prefill_only(params, obs, steps):
        x, m, ar = embed_prefix(params, embed_images(params, obs, cfg), obs, cfg)
        return prefill(params, x, m, ar, cfg, steps)[0]

    t_prefill = timed(lambda: prefill_only(model.params, obs, args.steps), args.repeats)
    t_infer = timed(lambda: model.sample_actions(key, obs, max_decoding_steps=args.steps), args.repeats)
    tokens, n_run, _ = sample_tokens_jit(
        model.params, obs, key, cfg=cfg, max_decoding_steps=args.steps, temperature=0.0
    )
    n_run = int(n_run)
    compiles_before = sample_tokens_jit._cache_size()
    for seed in range(3):  # new inputs of the same shape must reuse the compiled decode loop
        jax.block_until_ready(
            model.sample_actions(key, make_observation(cfg, args.cameras, 30, seed + 1), max_decoding_steps=args.steps)
        )
    decode_compiles = sample_tokens_jit._cache_size() - compiles_before
    per_token = (t_infer - t_prefill) / max(n_run, 1)

    steps = list(range(min(args.tokens, n_run)))
    t_one = timed(lambda: maps.gradcam_for_action_token(model, obs, tokens, steps[-1]).score, args.repeats)
    t_all = timed(lambda: maps.gradcam_for_steps(model, obs, tokens, steps).score, args.repeats)
    t_loop = timed(
        lambda: [maps.gradcam_for_action_token(model, obs, tokens, k).score for k in steps], max(1, args.repeats // 2)
    )
    t_chunk = timed(lambda: maps.gradcam_for_chunk(model, obs, tokens, steps).score, args.repeats)
    cam_before = maps._token_cams._cache_size()
    for k in range(n_run):  # every step of the request: no new compilation
        maps.gradcam_for_action_token(model, obs, tokens, k)
    cam_compiles = maps._token_cams._cache_size() - cam_before

    prefix = args.cameras * siglip.num_tokens + 48
    print(
        f"machine: {platform.machine()} {platform.processor() or ''}, {jax.devices()[0].device_kind}, "
        f"jax {jax.__version__}, {args.dtype}"
    )
    print(
        f"model: LLM width {args.width} depth {args.depth} vocab {args.vocab}; SigLIP width {args.vision_width}; "
        f"{args.cameras} cameras -> prefix {prefix} tokens; max_decoding_steps {args.steps} ({n_run} run)"
    )
    rows = [
        ("prefill forward (ms)", t_prefill * 1e3),
        ("inference = prefill + decode (ms)", t_infer * 1e3),
        ("decode per token (ms)", per_token * 1e3),
        ("decode compilations for 3 new same-shape inputs", decode_compiles),
        ("Grad-CAM one token (ms)", t_one * 1e3),
        ("  / inference", t_one / t_infer),
        ("  / prefill forward", t_one / t_prefill),
        (f"Grad-CAM {len(steps)} tokens, one call (ms)", t_all * 1e3),
        (f"Grad-CAM {len(steps)} tokens, per-token loop (ms)", t_loop * 1e3),
        ("  one call / loop", t_all / t_loop),
        ("Grad-CAM chunk (ms)", t_chunk * 1e3),
        (f"Grad-CAM compilations over all {n_run} steps after warm-up", cam_compiles),
    ]
    for name, value in rows:
        print(f"| {name:<52} | {value:>10.3f} |" if isinstance(value, float) else f"| {name:<52} | {value:>10d} |")


if __name__ == "__main__":
    main()
