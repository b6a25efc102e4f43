"""Times upstream OpenPI's own pi0 / pi0.5 `sample_actions` on a checkpoint, for `bench_pi05.py` (side by side).

Runs in an environment that has upstream's dependencies (jax, flax, orbax as upstream pins them) and a local checkout
of upstream (`--upstream-src`: the repository root, holding `src/openpi` and `packages/openpi-client`); nothing is
downloaded. The modules that upstream imports but never runs on this path (torch, transformers, the PyTorch model,
the LeRobot data loader) are replaced by empty modules. A tiny or medium architecture is installed the way the
goldens in `../shared/golden/tiny_pi0*` were made: `gemma.get_config` and SigLIP's variant table are redirected to the
given sizes. Prints one JSON line: the actions (for the parity check) and the timings.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import types
from pathlib import Path


def install_stubs(upstream_src: str) -> None:
    sys.path[:0] = [f"{upstream_src}/src", f"{upstream_src}/packages/openpi-client/src"]
    for name in (
        "torch",
        "torch.nn",
        "torch.nn.functional",
        "transformers",
        "openpi.models_pytorch",
        "openpi.models_pytorch.pi0_pytorch",
        "openpi.training.data_loader",
    ):
        sys.modules[name] = types.ModuleType(name)
    sys.modules["torch"].Tensor = type("Tensor", (), {})
    sys.modules["transformers"].AutoProcessor = object


def upstream_args(bench: str) -> argparse.Namespace:
    """The arguments every upstream-side timing script takes (`bench`: the benchmark that writes its spec), with
    upstream's imports made possible (`install_stubs`)."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--upstream-src", required=True)
    ap.add_argument("--spec", required=True, help=f"JSON file: checkpoint, architecture, inputs (see {bench})")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    install_stubs(args.upstream_src)
    return args


def main() -> None:
    args = upstream_args("bench_pi05.py")

    import jax
    import numpy as np
    from openpi.models import gemma, model, pi0_config, siglip
    from openpi.shared import nnx_utils

    spec = json.loads(Path(args.spec).read_text())
    arch = spec["architecture"]
    configs = {name: gemma.Config(**arch[name]) for name in ("llm", "expert")}
    get_config = gemma.get_config
    gemma.get_config = lambda variant: configs.get(variant) or get_config(variant)
    gemma.PALIGEMMA_VOCAB_SIZE = arch["vocab_size"]
    decode = siglip.decode_variant
    siglip.decode_variant = lambda variant: (
        {**decode(variant), **arch["siglip"]} if variant == "So400m/14" else decode(variant)
    )

    config = pi0_config.Pi0Config(
        pi05=spec["pi05"],
        action_horizon=spec["action_horizon"],
        max_token_len=spec["max_token_len"],
        dtype="float32",
        paligemma_variant="llm",
        action_expert_variant="expert",
    )
    params = model.restore_params(spec["params_dir"], dtype=None)
    pi = config.load(params)
    inputs = dict(np.load(spec["inputs"]))
    cams = spec["cameras"]
    obs = model.Observation(
        images={c: inputs[f"image_{c}"] for c in cams},
        image_masks={c: inputs[f"image_mask_{c}"] for c in cams},
        state=inputs["state"],
        tokenized_prompt=inputs["tokenized_prompt"],
        tokenized_prompt_mask=inputs["tokenized_prompt_mask"],
    )
    sample = nnx_utils.module_jit(pi.sample_actions)  # as upstream's Policy compiles it
    key = jax.random.key(0)
    t0 = time.perf_counter()
    actions = np.asarray(jax.block_until_ready(sample(key, obs, noise=inputs["noise"])))
    first = time.perf_counter() - t0
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(sample(key, obs, noise=inputs["noise"]))
        times.append(time.perf_counter() - t0)
    print(
        json.dumps(
            {
                "jax": jax.__version__,
                "first_call_s": first,
                "infer_s": statistics.median(times),
                "actions": actions.tolist(),
            }
        )
    )


if __name__ == "__main__":
    main()
