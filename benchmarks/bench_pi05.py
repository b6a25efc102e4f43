"""pi0.5 inference and one explanation, ours vs upstream OpenPI's own code on the same checkpoint and machine.

Builds a pi0.5 checkpoint of the given size with random weights (orbax, upstream's tree), runs our `Pi0` on fixed
inputs and noise, and, with `--upstream-python` (an interpreter with upstream's pinned dependencies) and
`--upstream-src` (a local checkout of upstream), runs `upstream_pi0_timing.py` on the same checkpoint and inputs in
between our rounds. Prints the medians side by side, their ratio, upstream's and our actions' largest difference,
and what one explanation costs relative to one inference.

    python benchmarks/bench_pi05.py                       # ours only
    python benchmarks/bench_pi05.py --upstream-python /path/upstream_env/bin/python --upstream-src /path/openpi
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model.checkpoint import save_params
from openpi_cam.model.config import GemmaConfig, Pi0Config, SiglipConfig
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0 import IMAGE_KEYS, Pi0, init_params
from openpi_cam.model.pi0_maps import CHUNK, maps_for_actions


def architecture(args: argparse.Namespace) -> Pi0Config:
    llm = GemmaConfig(args.width, args.depth, 2 * args.width, args.heads, 1, args.head_dim, args.vocab)
    expert = dataclasses.replace(llm, width=args.width // 2, mlp_dim=args.width, vocab_size=0)
    siglip = SiglipConfig(args.vision_width, args.depth, 4 * args.vision_width, 4, 14, 224, args.width)
    return Pi0Config(llm, expert, siglip, True, 32, args.horizon, args.max_token_len, "float32")


def random_params(cfg: Pi0Config) -> dict:
    """Our initialiser, with every leaf it sets to zero or one (biases, norm scales, adaRMS modulations) perturbed,
    so that every weight matters to the comparison."""
    params = init_params(cfg, jax.random.key(0))
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.key(1), len(leaves))
    leaves = [x + 0.05 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys, strict=True)]
    return jax.tree.unflatten(tree, leaves)


def inputs(cfg: Pi0Config, prompt_len: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    out = {}
    for c in IMAGE_KEYS:
        out[f"image_{c}"] = (rng.integers(0, 256, (1, 224, 224, 3)) / 255 * 2 - 1).astype(np.float32)
        out[f"image_mask_{c}"] = np.ones(1, bool)
    tokens = np.zeros((1, cfg.max_token_len), np.int32)
    tokens[0, :prompt_len] = rng.integers(2, cfg.gemma.vocab_size, prompt_len)
    out["tokenized_prompt"] = tokens
    out["tokenized_prompt_mask"] = tokens > 0
    out["state"] = rng.uniform(-1, 1, (1, 32)).astype(np.float32)
    out["noise"] = rng.standard_normal((1, cfg.action_horizon, 32)).astype(np.float32)
    return out


def median_time(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--head-dim", type=int, default=64)
    ap.add_argument("--vision-width", type=int, default=256)
    ap.add_argument("--vocab", type=int, default=1024)
    ap.add_argument("--horizon", type=int, default=15)
    ap.add_argument("--max-token-len", type=int, default=64)
    ap.add_argument("--prompt-len", type=int, default=48)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds of ours and upstream's")
    ap.add_argument("--upstream-python", type=Path)
    ap.add_argument("--upstream-src", type=Path)
    args = ap.parse_args()

    cfg = architecture(args)
    work = Path(tempfile.mkdtemp(prefix="bench_pi05_"))
    save_params(work / "params", random_params(cfg))
    data = inputs(cfg, args.prompt_len)
    np.savez(work / "inputs.npz", **data)
    model = Pi0.from_checkpoint(
        work / "params", dtype="float32", action_horizon=cfg.action_horizon, max_token_len=cfg.max_token_len
    )
    obs = Observation(
        images={c: data[f"image_{c}"] for c in IMAGE_KEYS},
        image_masks={c: data[f"image_mask_{c}"] for c in IMAGE_KEYS},
        state=data["state"],
        tokenized_prompt=data["tokenized_prompt"],
        tokenized_prompt_mask=data["tokenized_prompt_mask"],
    )
    noise = jnp.asarray(data["noise"])
    spec = {
        "params_dir": str(work / "params"),
        "inputs": str(work / "inputs.npz"),
        "cameras": list(IMAGE_KEYS),
        "pi05": True,
        "action_horizon": cfg.action_horizon,
        "max_token_len": cfg.max_token_len,
        "architecture": {
            "vocab_size": cfg.gemma.vocab_size,
            "llm": {
                k: getattr(cfg.gemma, k) for k in ("width", "depth", "mlp_dim", "num_heads", "num_kv_heads", "head_dim")
            },
            "expert": {
                k: getattr(cfg.expert, k)
                for k in ("width", "depth", "mlp_dim", "num_heads", "num_kv_heads", "head_dim")
            },
            "siglip": {
                "width": cfg.siglip.width,
                "depth": cfg.siglip.depth,
                "mlp_dim": cfg.siglip.mlp_dim,
                "num_heads": cfg.siglip.num_heads,
            },
        },
    }
    (work / "spec.json").write_text(json.dumps(spec))

    ours, theirs, first_upstream = [], [], []
    actions = np.asarray(model.sample_actions(None, obs, noise=noise))
    upstream_actions = None
    for _ in range(args.rounds):
        ours.append(median_time(lambda: model.sample_actions(None, obs, noise=noise), args.repeats))
        if args.upstream_python and args.upstream_src:
            script = Path(__file__).with_name("upstream_pi0_timing.py")
            cmd = [
                str(args.upstream_python),
                str(script),
                "--upstream-src",
                str(args.upstream_src),
                "--spec",
                str(work / "spec.json"),
                "--repeats",
                str(args.repeats),
            ]
            result = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.splitlines()[-1])
            theirs.append(result["infer_s"])
            first_upstream.append(result["first_call_s"])
            upstream_actions = np.asarray(result["actions"])
    one = median_time(lambda: maps_for_actions(model, obs, noise, [(0, 0)]).score, args.repeats)
    chunk = median_time(lambda: maps_for_actions(model, obs, noise, [CHUNK]).score, args.repeats)

    infer = statistics.median(ours)
    device = jax.devices()[0].device_kind
    print(f"machine: {platform.machine()} {platform.processor() or ''}, {device}, jax {jax.__version__}")
    print(
        f"pi0.5, float32: LLM {cfg.gemma.width} x {cfg.gemma.depth}, expert {cfg.expert.width}, SigLIP "
        f"{cfg.siglip.width} x {cfg.siglip.depth}, 3 cameras, horizon {cfg.action_horizon}, {cfg.num_steps} steps"
    )
    print("| quantity | value |")
    print("| --- | --- |")
    print(f"| inference (ours), median of {args.rounds} x {args.repeats} | {1000 * infer:.0f} ms |")
    if theirs:
        upstream = statistics.median(theirs)
        print(f"| inference (upstream, {len(theirs)} runs interleaved with ours) | {1000 * upstream:.0f} ms |")
        print(f"| ours / upstream | {infer / upstream:.2f} |")
        print(f"| upstream first call (compile) | {statistics.median(first_upstream):.1f} s |")
        print(
            f"| max abs difference of the actions, ours vs upstream | {np.abs(actions - upstream_actions).max():.2g} "
            f"(max abs action {np.abs(upstream_actions).max():.2g}) |"
        )
    print(f"| one explanation, target action (0, 0) / inference | {one / infer:.2f} |")
    print(f"| one explanation, target chunk / inference | {chunk / infer:.2f} |")


if __name__ == "__main__":
    main()
