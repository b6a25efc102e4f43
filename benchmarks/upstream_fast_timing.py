"""Times upstream OpenPI's own pi0-FAST `sample_actions` (prefill + greedy decode) for `bench_fullsize.py
--upstream-src`: the same random weights, the same inputs, the same device as our side of that benchmark.

Runs in an environment with upstream's dependencies and a local checkout of upstream (`--upstream-src`), with the
stubs of `upstream_pi0_timing.py`. Weights and inputs come from `bench_fullsize`'s own recipe (same seed, same leaf
order), so both sides decode the same tokens; upstream's model is built by upstream's `Pi0FASTConfig.load`, and its
`sample_actions` is compiled the way upstream's `Policy` compiles it (`nnx_utils.module_jit`), with the decode budget
static so that each budget is its own program (upstream's policy passes its default, 256, as a Python int).
Layer depths given in the spec replace upstream's Gemma and SigLIP depths (smoke runs). Prints one JSON line.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

from upstream_pi0_timing import upstream_args


def main() -> None:
    args = upstream_args("bench_fullsize.py")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

    import bench_fullsize as ours
    import jax
    import numpy as np
    from openpi.models import gemma_fast, model, pi0_fast, siglip
    from openpi.shared import nnx_utils

    from openpi_cam.model.config import param_shapes

    spec = json.loads(Path(args.spec).read_text())
    cfg = ours.fullsize_config(spec["llm_depth"], spec["siglip_depth"])
    get_config, decode = gemma_fast.get_config, siglip.decode_variant

    def llm_config(variant):
        c = get_config(variant)
        c.depth = cfg.gemma.depth
        return c

    gemma_fast.get_config = llm_config
    siglip.decode_variant = lambda variant: {**decode(variant), "depth": cfg.siglip.depth}

    config = pi0_fast.Pi0FASTConfig(
        action_dim=cfg.action_dim, action_horizon=cfg.action_horizon, max_token_len=cfg.max_token_len
    )
    start = time.perf_counter()
    pi = config.load(ours.random_params(param_shapes(cfg.gemma, cfg.siglip)))
    load_s = time.perf_counter() - start
    obs = ours.observation(cfg, spec["prompt_tokens"])
    up_obs = model.Observation(
        images=obs.images,
        image_masks=obs.image_masks,
        state=obs.state,
        tokenized_prompt=obs.tokenized_prompt,
        tokenized_prompt_mask=obs.tokenized_prompt_mask,
        token_ar_mask=obs.token_ar_mask,
        token_loss_mask=np.zeros_like(obs.tokenized_prompt_mask),
    )
    sample = nnx_utils.module_jit(pi.sample_actions, static_argnames=("max_decoding_steps",))
    key = jax.random.key(0)
    out = {"jax": jax.__version__, "device": str(jax.devices()[0]), "load_s": load_s, "decode": {}}
    for steps in spec["decode_steps"]:
        start = time.perf_counter()
        tokens = np.asarray(jax.block_until_ready(sample(key, up_obs, max_decoding_steps=steps)))
        first = time.perf_counter() - start
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(sample(key, up_obs, max_decoding_steps=steps))
            times.append(time.perf_counter() - start)
        out["decode"][str(steps)] = {
            "first_call_s": first,
            "median_s": statistics.median(times),
            "tokens": tokens.astype(int).tolist(),
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
