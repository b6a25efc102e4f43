"""The full-size pi0-FAST (SigLIP So400m/14 + Gemma 2B, upstream's parameter tree) in bfloat16 on this machine: peak
host memory and time of loading, prefill + a few decode steps, and one explanation (gradcam + gradnorm of one token).

Weights are random (no download), drawn leaf by leaf directly in bfloat16 so that host memory never holds a float32
copy of the 2.9B parameters. Inputs: DROID's layout (3 cameras at 224 px, `max_token_len` 250 prompt slots).
Peak memory is the process's resident-set high-water mark (VmHWM) after each phase. Each timed phase runs twice
(the first compiles); both times are printed.

    python benchmarks/bench_fullsize.py --decode-steps 8
"""

from __future__ import annotations

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model import pi0_fast_maps
from openpi_cam.model.config import param_shapes, pi0_fast_config
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0_fast import Pi0FAST
from openpi_cam.nested import unflatten_dict

CAMERAS = ("base_0_rgb", "base_1_rgb", "wrist_0_rgb")


def rss_gb(field: str = "VmHWM") -> float:
    with open("/proc/self/status") as f:
        line = next(line for line in f if line.startswith(field + ":"))
    return int(line.split()[1]) / 2**20


def random_params(shapes: dict[str, tuple[int, ...]]) -> dict:
    """N(0, 0.02) in bfloat16, drawn with NumPy in chunks straight into each leaf's bfloat16 buffer and placed on the
    device one leaf at a time (norm scales included: this measures cost, not quality). Drawing a 0.5B-element
    embedding with `jax.random.normal` materialises its random bits and float32 values at once: 22.6 GB peak."""
    rng = np.random.default_rng(0)
    chunk = 1 << 24
    leaves = {}
    for path, shape in shapes.items():
        host = np.empty(int(np.prod(shape)), jnp.bfloat16)
        for start in range(0, host.size, chunk):
            stop = min(start + chunk, host.size)
            host[start:stop] = 0.02 * rng.standard_normal(stop - start, np.float32)
        leaves[path] = jax.device_put(host.reshape(shape))
        del host
    return unflatten_dict(leaves)


def observation(cfg, prompt_tokens: int) -> Observation:
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


def timed(label: str, fn, rounds: int = 2) -> None:
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    print(f"{label:>44}: {' / '.join(f'{t:7.1f} s' for t in times)}   peak RSS {rss_gb():5.1f} GB", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--decode-steps", type=int, default=8)
    parser.add_argument("--prompt-tokens", type=int, default=60)
    args = parser.parse_args()

    cfg = pi0_fast_config(action_dim=8, action_horizon=10, max_token_len=250)
    shapes = param_shapes(cfg.gemma, cfg.siglip)
    count = sum(int(np.prod(s)) for s in shapes.values())
    print(f"pi0-FAST full size: {count / 1e9:.2f}B parameters, bfloat16; {platform.machine()}, jax {jax.__version__}")
    print(f"{'baseline':>44}: peak RSS {rss_gb():5.1f} GB")
    start = time.perf_counter()
    model = Pi0FAST(cfg, random_params(shapes))
    print(f"{'random bfloat16 params':>44}: {time.perf_counter() - start:7.1f} s   peak RSS {rss_gb():5.1f} GB")
    obs = observation(cfg, args.prompt_tokens)
    tokens = {}

    def infer():
        tokens["ids"] = model.sample_actions(jax.random.key(0), obs, max_decoding_steps=args.decode_steps)
        return tokens["ids"]

    timed(f"prefill + {args.decode_steps} decode steps", infer)
    generated = np.asarray(tokens["ids"])
    timed(
        "explanation: gradcam + gradnorm of token 0",
        lambda: pi0_fast_maps.gradcam_for_action_token(model, obs, generated, 0).maps[CAMERAS[0]],
    )


if __name__ == "__main__":
    main()
