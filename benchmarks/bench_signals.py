"""What the failure monitor's signals cost the served call (issue 43): the same call with and without them, side by
side in one run, rows interleaved round by round; and what scoring one call costs the side channel's worker.

Rows (medians of `--rounds` calls after each program's first, compiling call):
  pi0-FAST model       `Pi0FAST.sample_actions` vs `sample_with_signals` (prefill + `--decode-steps` greedy steps):
                       the signals add the top layer over every prefix token beside the last-slot pass, and per
                       decode step the chosen token's entropy over the vocabulary and its pre-logits kept
  pi0-FAST policy      `Policy.infer_traced` vs `infer_traced(signals=True)` of the bundled demo model (the host work
                       too: the action tokens' features averaged, the arrays brought back), demo size only
  pi0 / pi0.5 model    `Pi0.sample_actions` vs `sample_with_signals` (the prefix pass's outputs pooled, the expert's
                       outputs at the last Euler step)
  pi0.5 policy         as the pi0-FAST policy row, the bundled pi0.5, demo size only
  scoring              `LiveMonitor.score` of one call: a probe over every pooled feature and STAC (the work the side
                       channel's worker does per served call)
Sizes: `--size demo` (the bundled models' architectures, float32, their weights) or `--size full` (pi0_fast_droid's
and pi0's architectures: Gemma 2B + So400m/14, pi0's 300M expert; random bfloat16 weights, 3 cameras at 224 px; an
accelerator: random weights never emit EOS, so every decode runs all its steps). The tokens and actions of both
programs are compared too (they must be the same, bit for bit).

    python benchmarks/bench_signals.py --rounds 20                              # the demo models, this machine
    python benchmarks/bench_signals.py --size full --rounds 10 --decode-steps 32 256   # an accelerator
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse
import dataclasses
import json
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
from bench_fullsize import fullsize_config, random_params
from bench_fullsize import observation as fast_observation

from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.model.config import Pi0Config, param_shapes, pi0_param_shapes
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0 import Pi0
from openpi_cam.model.pi0_fast import Pi0FAST
from openpi_cam.monitor.fit import Episode, FitOptions, fit_monitor
from openpi_cam.monitor.signals import STAC
from openpi_cam.monitor.stream import step_inputs
from openpi_cam.vocabulary import FEATURES_PREFIX


def interleaved(rows: dict[str, callable], rounds: int) -> dict[str, dict[str, float]]:
    """Each row's first call (compiling) and the median of `rounds` later ones, the rows taking turns each round so
    that a load change on the machine falls on all of them alike. Seconds."""
    first, times = {}, {name: [] for name in rows}
    for name, fn in rows.items():
        start = time.perf_counter()
        jax.block_until_ready(fn())
        first[name] = time.perf_counter() - start
    for _ in range(rounds):
        for name, fn in rows.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    return {name: {"first_s": first[name], "median_ms": 1000 * statistics.median(times[name])} for name in rows}


def pair(plain: str, signals: str, timings: dict[str, dict[str, float]]) -> dict[str, float]:
    a, b = timings[plain]["median_ms"], timings[signals]["median_ms"]
    return {"without_ms": round(a, 3), "with_ms": round(b, 3), "added_ms": round(b - a, 3), "ratio": round(b / a, 4)}


def create_demo_policy(model: str = "pi0_fast"):
    # imported here: the full-size rows need none of the command line's loaders on an accelerator's bare image
    from openpi_cam.checkpoints.model_spec import create_demo_policy as create

    return create(model)


def fast_model_rows(args: argparse.Namespace) -> tuple[dict, dict]:
    if args.size == "full":
        cfg = fullsize_config(args.llm_depth, args.siglip_depth)
        model = Pi0FAST(cfg, random_params(param_shapes(cfg.gemma, cfg.siglip)))
        obs = fast_observation(cfg, args.prompt_tokens)
    else:
        policy = create_demo_policy()
        model, obs = policy.model, policy.warm_up().observation
    rows, same = {}, {}
    for steps in args.decode_steps:
        plain = lambda s=steps: model.sample_actions(jax.random.key(0), obs, max_decoding_steps=s)  # noqa: E731
        signalled = lambda s=steps: model.sample_with_signals(jax.random.key(0), obs, max_decoding_steps=s)  # noqa: E731
        rows[f"pi0-FAST model, {steps} steps"] = plain
        rows[f"pi0-FAST model, {steps} steps, signals"] = signalled
        same[steps] = bool(np.array_equal(np.asarray(plain()), np.asarray(signalled()[0])))
    return rows, same


def flow_model_rows(args: argparse.Namespace) -> tuple[dict, dict]:
    if args.size == "full":
        small = fullsize_config(args.llm_depth, args.siglip_depth)
        cfg = Pi0Config(gemma=small.gemma, siglip=small.siglip)
        cfg = dataclasses.replace(cfg, expert=dataclasses.replace(cfg.expert, depth=small.gemma.depth))
        model = Pi0(cfg, random_params(pi0_param_shapes(cfg)))
        base = fast_observation(small, args.prompt_tokens)
        images = {k: base.images[c] for k, c in zip(cfg.image_keys, base.images, strict=True)}
        mask = base.tokenized_prompt_mask[:, : cfg.max_token_len]
        obs = Observation(
            images=images,
            image_masks={k: np.ones((1,), bool) for k in images},
            state=np.zeros((1, cfg.action_dim), np.float32),
            tokenized_prompt=base.tokenized_prompt[:, : cfg.max_token_len],
            tokenized_prompt_mask=mask,
        )
    else:
        policy = create_demo_policy("pi05")
        model, obs, cfg = policy.model, policy.warm_up().observation, policy.model.config
    noise = jnp.asarray(np.random.default_rng(0).standard_normal((1, cfg.action_horizon, cfg.action_dim)), jnp.float32)
    plain = lambda: model.sample_actions(jax.random.key(0), obs, noise=noise)  # noqa: E731
    signalled = lambda: model.sample_with_signals(obs, noise)  # noqa: E731
    name = "pi0.5" if cfg.pi05 else "pi0"
    rows = {f"{name} model": plain, f"{name} model, signals": signalled}
    return rows, {"actions_identical": bool(np.array_equal(np.asarray(plain()), np.asarray(signalled()[0])))}


def policy_rows() -> dict:
    rows = {}
    for name, model in (("pi0-FAST", "pi0_fast"), ("pi0.5", "pi05")):
        policy = create_demo_policy(model)
        trace = policy.warm_up()
        obs = dict(trace.request)
        noise = None if model == "pi0_fast" else np.zeros(trace.sample_inputs["noise"].shape, np.float32)
        rows[f"{name} policy"] = lambda p=policy, o=obs, n=noise: p.infer_traced(o, noise=n)[0]["actions"]
        rows[f"{name} policy, signals"] = lambda p=policy, o=obs, n=noise: p.infer_traced(o, noise=n, signals=True)[0][
            "actions"
        ]
    return rows


def scoring_cost(size: str, rounds: int) -> dict[str, float]:
    """A probe over every pooled feature a pi0-FAST call gives (widths as the model's) and STAC, fitted on random
    episodes; the median time of scoring one call in a live stream."""
    width = 2048 if size == "full" else 128
    names = [FEATURES_PREFIX + n for n in ("base_0_rgb", "base_1_rgb", "wrist_0_rgb", "prompt", "actions")]
    rng = np.random.default_rng(0)
    episodes = [
        Episode({**{n: rng.normal(size=(20, width)) for n in names}, STAC: rng.random(20)}, i % 3 != 0)
        for i in range(30)
    ]
    monitor = fit_monitor(episodes, FitOptions(kind="probe", inputs=(*names, STAC)))
    live = LiveMonitor(monitor, "bench.json")
    call = {n: rng.normal(size=width).astype(np.float32) for n in names} | {"chunk": rng.normal(size=(10, 8))}
    assert set(step_inputs(call)) == set(names)
    times = []
    for _ in range(rounds + 1):
        start = time.perf_counter()
        live.score("conn", call)
        times.append(time.perf_counter() - start)
    return {"inputs": monitor.input_dim, "median_us": round(1e6 * statistics.median(times[1:]), 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=["demo", "full"], default="demo")
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--decode-steps", type=int, nargs="+", default=[32])
    parser.add_argument("--prompt-tokens", type=int, default=60)
    parser.add_argument("--llm-depth", type=int, default=None, help="smoke runs: fewer Gemma layers")
    parser.add_argument("--siglip-depth", type=int, default=None, help="smoke runs: fewer SigLIP layers")
    args = parser.parse_args()
    fast, fast_same = fast_model_rows(args)
    flow, flow_same = flow_model_rows(args)
    rows = {**fast, **flow, **(policy_rows() if args.size == "demo" else {})}
    timings = interleaved(rows, args.rounds)
    plain = [name for name in rows if not name.endswith(", signals")]
    report = {
        "machine": {
            "platform": platform.platform(),
            "devices": [str(d) for d in jax.devices()],
            "cpus": os.cpu_count(),
        },
        "load_average": os.getloadavg(),
        "size": args.size,
        "rounds": args.rounds,
        "rows": {name: pair(name, name + ", signals", timings) for name in plain},
        "first_call_s": {name: round(t["first_s"], 2) for name, t in timings.items()},
        "tokens_identical_by_steps": fast_same,
        "flow": flow_same,
        "scoring_one_call": scoring_cost(args.size, max(args.rounds, 200)),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
