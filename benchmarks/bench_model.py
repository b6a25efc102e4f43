"""What an explanation costs next to the forward pass it explains, for a pi0-FAST of medium size, side by side in one
run; with `--upstream-python` / `--upstream-src` also upstream's own prefill on the same weights and inputs.

    python benchmarks/bench_model.py                       # issue 19's medium model: ours only
    python benchmarks/bench_model.py --upstream-python /path/upstream_env/bin/python --upstream-src /path/openpi

Model (defaults): Gemma width 512 x depth 4 (4 heads of 128, one KV head, MLP 2048) with PaliGemma's vocabulary
(257152), SigLIP width 256 x depth 4, 3 cameras x 256 tokens + 48 prompt tokens = 816 prefix tokens, float32, random
weights (timings do not depend on the values). The decode has upstream's 256 slots and generated `--generated` tokens
(random ids fed back: teacher forcing does not depend on where they came from); "action tokens" are the last
`--tokens` of them. Rows:
  prefill                ours vs upstream's (same tokens: the last slot's logits are compared), both keeping the
                         last slot's logits and the KV cache of prefix + 256 slots
  teacher-forced forward SigLIP + prefix + the generated tokens up to the last one, the explained logit: what an
                         explanation of the last generated token differentiates (its replay, cut as it cuts it)
  one token              gradcam + gradnorm of the last generated token; also with the replay at all 256 slots (the
                         cut at the last explained step disabled, the other savings kept)
  action tokens          all of them in one call (one forward, one backward each) vs a loop of one-token calls
  scanned backward       the one-token explanation with the Gemma stack scanned in its backward pass, as before
                         `pi0_fast_maps.backward_config` unrolled it (same stacked parameters)
  full logit vector      the one-token explanation also projecting the explained output onto the vocabulary
                         (`logits=True`, the API's default; the side channel and `explain` leave it out)
  differentiated attention  the one-token explanation with JAX differentiating the masked softmax attention, as
                         before `gemma.attend` wrote its backward pass out
Explanations are gradcam + gradnorm as the side channel asks for them (`logits=False`).
Every row runs in each of `--rounds` rounds (rows interleaved); ratios are of medians.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model import gemma as gemma_lib
from openpi_cam.model import pi0_fast_maps as maps
from openpi_cam.model.checkpoint import save_params
from openpi_cam.model.config import MAX_DECODING_STEPS, GemmaConfig, Pi0FASTConfig, SiglipConfig
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, embed_prefix, init_params, prefill, replay_prelogits

CAMERAS = ("base_0_rgb", "base_1_rgb", "wrist_0_rgb")


def timed(fn, repeats: int) -> list[float]:
    """Wall times of `fn()` (blocking on its result), after one warm-up call."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return times


def inputs(cfg: Pi0FASTConfig, prompt_len: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    size = cfg.siglip.image_size
    out = {}
    for c in CAMERAS:
        out[f"image_{c}"] = (rng.integers(0, 256, (1, size, size, 3)) / 255 * 2 - 1).astype(np.float32)
        out[f"image_mask_{c}"] = np.ones(1, bool)
    tokens = np.zeros((1, cfg.max_token_len), np.int32)
    tokens[0, :prompt_len] = rng.integers(2, cfg.gemma.vocab_size, prompt_len)
    out["tokenized_prompt"] = tokens
    out["tokenized_prompt_mask"] = np.arange(cfg.max_token_len)[None] < prompt_len
    out["token_ar_mask"] = np.zeros_like(tokens)
    out["token_loss_mask"] = np.zeros((1, cfg.max_token_len), bool)
    out["state"] = np.zeros((1, cfg.action_dim), np.float32)
    return out


def observation(data: dict[str, np.ndarray]) -> Observation:
    return Observation(
        images={c: data[f"image_{c}"] for c in CAMERAS},
        image_masks={c: data[f"image_mask_{c}"] for c in CAMERAS},
        state=data["state"],
        tokenized_prompt=data["tokenized_prompt"],
        tokenized_prompt_mask=data["tokenized_prompt_mask"],
        token_ar_mask=data["token_ar_mask"],
        token_loss_mask=data["token_loss_mask"],
    )


def upstream_spec(cfg: Pi0FASTConfig, work: Path, steps: int) -> Path:
    g, s = cfg.gemma, cfg.siglip
    spec = {
        "params_dir": str(work / "params"),
        "inputs": str(work / "inputs.npz"),
        "cameras": list(CAMERAS),
        "action_dim": cfg.action_dim,
        "action_horizon": cfg.action_horizon,
        "max_token_len": cfg.max_token_len,
        "max_decoding_steps": steps,
        "architecture": {
            "llm": {k: getattr(g, k) for k in ("width", "depth", "mlp_dim", "num_heads", "num_kv_heads", "head_dim")}
            | {"vocab_size": g.vocab_size},
            "siglip": {"width": s.width, "depth": s.depth, "mlp_dim": s.mlp_dim, "num_heads": s.num_heads},
        },
    }
    path = work / "spec.json"
    path.write_text(json.dumps(spec))
    return path


def run_upstream(args: argparse.Namespace, spec: Path) -> dict:
    script = Path(__file__).with_name("upstream_fast_prefill.py")
    cmd = [str(args.upstream_python), str(script), "--upstream-src", str(args.upstream_src), "--spec", str(spec)]
    cmd += ["--repeats", str(args.repeats)]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # upstream's environment, not ours
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(out.stdout.splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--vision-width", type=int, default=256)
    ap.add_argument("--vision-depth", type=int, default=4)
    ap.add_argument("--vocab", type=int, default=257_152)
    ap.add_argument("--prompt-len", type=int, default=48)
    ap.add_argument("--steps", type=int, default=MAX_DECODING_STEPS, help="max_decoding_steps (KV cache slots)")
    ap.add_argument("--generated", type=int, default=32, help="tokens the decode generated (of --steps)")
    ap.add_argument("--tokens", type=int, default=16, help="action tokens: the last ones generated")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds of every row")
    ap.add_argument("--upstream-python", type=Path)
    ap.add_argument("--upstream-src", type=Path)
    args = ap.parse_args()
    load_before = f"{os.getloadavg()[0]:.2f}"

    w = args.width
    gemma = GemmaConfig(w, args.depth, 4 * w, 4, 1, w // 4, args.vocab)
    siglip = SiglipConfig(args.vision_width, args.vision_depth, 4 * args.vision_width, 4, 14, 224, w)
    cfg = Pi0FASTConfig(gemma, siglip, action_dim=8, action_horizon=10, max_token_len=args.prompt_len, dtype="float32")
    model = Pi0FAST(cfg, init_params(cfg, jax.random.key(0)))
    data = inputs(cfg, args.prompt_len)
    obs = observation(data)
    pobs = preprocess_observation(obs, cfg.image_resolution)
    generated = np.zeros((1, args.steps), np.int32)
    generated[0, : args.generated] = np.random.default_rng(1).integers(2, args.vocab, args.generated)
    last = args.generated - 1
    action_steps = list(range(args.generated - args.tokens, args.generated))
    llm = model.params["PaliGemma"]["llm"]

    @functools.partial(jax.jit, static_argnames=("steps",))
    def our_prefill(params, obs, steps):
        x, m, ar = embed_prefix(params, embed_images(params, obs, cfg), obs, cfg)
        last_pre, cache, _, _ = prefill(params, x, m, ar, cfg, steps)
        return gemma_lib.logits_from_prelogits(params["PaliGemma"]["llm"], last_pre), cache

    @functools.partial(jax.jit, static_argnames=("decode_len",))
    def forward(params, obs, fed, step, decode_len):
        pre = replay_prelogits(params, embed_images(params, obs, cfg), obs, fed, cfg, decode_len)[:, step]
        return jnp.einsum("bd,bd->b", pre, llm["embedder"]["input_embedding"][fed[:, step]])

    fed = jnp.asarray(generated[:, : maps.replay_length(last, args.steps)])

    def explain(steps: list[int], logits: bool = False) -> np.ndarray:
        """gradcam + gradnorm of `steps` as the side channel asks for them (no full logit vector by default)."""
        return maps.maps_for_steps(model, obs, generated, steps, logits=logits).score

    rows = {
        "prefill": lambda: our_prefill(model.params, pobs, args.steps),
        "forward": lambda: forward(model.params, pobs, fed, last, args.steps),
        "one": lambda: explain([last]),
        "one_full": lambda: full_length(lambda: explain([last])),
        "one_logits": lambda: explain([last], logits=True),
        "all": lambda: explain(action_steps),
        "loop": lambda: [explain([k]) for k in action_steps],
        "one_scanned": lambda: scanned_backward(lambda: explain([last])),
        "one_autodiff": lambda: autodiff_attention(lambda: explain([last])),
    }
    before = maps._token_gradient_maps._cache_size()
    for k in range(args.generated):  # every step of the request, one token at a time
        explain([k])
    compiles = maps._token_gradient_maps._cache_size() - before

    work = Path(tempfile.mkdtemp(prefix="bench_model_"))
    spec = None
    if args.upstream_python and args.upstream_src:
        save_params(work / "params", model.params)
        np.savez(work / "inputs.npz", **data)
        spec = upstream_spec(cfg, work, args.steps)
    times: dict[str, list[float]] = {k: [] for k in rows}
    upstream = []
    for _ in range(args.rounds):
        for name, fn in rows.items():
            times[name] += timed(fn, 1 if name in ("all", "loop") else args.repeats)
        if spec is not None:
            upstream.append(run_upstream(args, spec))
    t = {k: statistics.median(v) for k, v in times.items()}
    ours_last = np.asarray(our_prefill(model.params, pobs, args.steps)[0])

    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, {jax.devices()[0].device_kind}, jax {jax.__version__}"
    )
    print(f"load average before / after: {load_before} / {os.getloadavg()[0]:.2f}")
    prefix = len(CAMERAS) * siglip.num_tokens + args.prompt_len
    print(
        f"model: Gemma {w} x {args.depth}, vocab {args.vocab}; SigLIP {args.vision_width} x {args.vision_depth}; "
        f"{len(CAMERAS)} cameras -> prefix {prefix} tokens; float32; {args.steps} decode slots, {args.generated} "
        f"generated; medians of {args.rounds} rounds x {args.repeats} (action tokens: x 1)"
    )
    table = [("prefill, ours (ms)", f"{1e3 * t['prefill']:.0f}")]
    if upstream:
        up = statistics.median(u["prefill_s"] for u in upstream)
        diff = np.abs(ours_last - np.asarray(upstream[-1]["last_logits"])).max()
        table += [
            (
                f"prefill, upstream (ms, {len(upstream)} runs x {args.repeats}, jax {upstream[0]['jax']})",
                f"{1e3 * up:.0f}",
            ),
            ("  ours / upstream (target <= 0.8)", f"{t['prefill'] / up:.2f}"),
            ("  max abs difference of the last slot's logits", f"{diff:.2g} (of {np.abs(ours_last).max():.2g})"),
        ]
    else:
        table += [("prefill, upstream", "not run (--upstream-python / --upstream-src)")]
    table += [
        (f"teacher-forced forward, step {last} (ms)", f"{1e3 * t['forward']:.0f}"),
        (f"one token, step {last} (ms)", f"{1e3 * t['one']:.0f}"),
        ("  / teacher-forced forward (target <= 2.2)", f"{t['one'] / t['forward']:.2f}"),
        (f"one token, step {last}, replay at all {args.steps} slots (ms)", f"{1e3 * t['one_full']:.0f}"),
        ("  / teacher-forced forward", f"{t['one_full'] / t['forward']:.2f}"),
        (f"{args.tokens} action tokens, one call (ms)", f"{1e3 * t['all']:.0f}"),
        (f"{args.tokens} action tokens, per-token loop (ms)", f"{1e3 * t['loop']:.0f}"),
        ("  one call / loop (target <= 0.4)", f"{t['all'] / t['loop']:.2f}"),
        (f"compilations over all {args.generated} steps, one token each", f"{compiles}"),
        (f"one token, step {last}, stack scanned in the backward pass (ms)", f"{1e3 * t['one_scanned']:.0f}"),
        ("  / teacher-forced forward", f"{t['one_scanned'] / t['forward']:.2f}"),
        ("  one token: unrolled (the default) / scanned backward pass", f"{t['one'] / t['one_scanned']:.2f}"),
        (f"one token, step {last}, with the full logit vector (ms)", f"{1e3 * t['one_logits']:.0f}"),
        ("  one token: without (the side channel) / with the full logit vector", f"{t['one'] / t['one_logits']:.2f}"),
        (f"one token, step {last}, attention differentiated by JAX (ms)", f"{1e3 * t['one_autodiff']:.0f}"),
        ("  / teacher-forced forward", f"{t['one_autodiff'] / t['forward']:.2f}"),
        ("  one token: written-out (the default) / differentiated attention", f"{t['one'] / t['one_autodiff']:.2f}"),
    ]
    print("| quantity | value |")
    print("| --- | --- |")
    for name, value in table:
        print(f"| {name} | {value} |")


def full_length(fn):
    """Runs `fn` with every replay at the decode's full length (what each explanation ran before the cut)."""
    cut = maps.replay_length
    maps.replay_length = lambda last_step, decode_len: decode_len
    try:
        return fn()
    finally:
        maps.replay_length = cut


def autodiff_attention(fn):
    """Runs `fn` with Gemma's attention differentiated by JAX, as before `gemma.attend` wrote its backward pass out;
    the programs it compiles are its own (a fresh jit of the same function)."""
    attend = gemma_lib.attend
    gemma_lib.attend = lambda q, k, v, mask, hidden: gemma_lib._masked_softmax_attention(q, k, v, mask, hidden)[0]
    token_gradient_maps = maps._token_gradient_maps
    maps._token_gradient_maps = _AUTODIFF_TOKEN_GRADIENT_MAPS
    try:
        return fn()
    finally:
        gemma_lib.attend, maps._token_gradient_maps = attend, token_gradient_maps


# A function of its own: JAX caches traces per traced function, so jitting `_token_gradient_maps`'s own function
# again would reuse the program traced with the written-out backward pass. The function is taken now:
# `autodiff_attention` replaces `maps._token_gradient_maps` with this program while it runs.
_TOKEN_GRADIENT_MAPS_FN = maps._token_gradient_maps.__wrapped__
_AUTODIFF_TOKEN_GRADIENT_MAPS = jax.jit(
    lambda *args, **kwargs: _TOKEN_GRADIENT_MAPS_FN(*args, **kwargs),
    static_argnames=("cfg", "decode_len", "logits", "program", "options"),
)


def scanned_backward(fn):
    """Runs `fn` with the explanation's stack scanned, as the served model runs it (before the backward unroll)."""
    unrolled = maps.backward_config
    maps.backward_config = lambda cfg, tokens: cfg
    try:
        return fn()
    finally:
        maps.backward_config = unrolled


if __name__ == "__main__":
    main()
