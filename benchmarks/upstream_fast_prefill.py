"""Times upstream OpenPI's own pi0-FAST prefill on a checkpoint, for `bench_model.py --upstream-python` (side by side).

Runs in an environment with upstream's pinned dependencies and a local checkout of upstream (`--upstream-src`), the
way `upstream_pi0_timing.py` does (same stubs for modules upstream imports but never runs here). The architecture is
installed as the goldens in `../shared/golden/tiny_pi0_fast` were made: `gemma_fast.get_config` returns the given
Gemma and SigLIP's variant table the given sizes. The timed program is the first half of upstream's
`Pi0FAST.sample_actions`, made of upstream's own functions and modules: embed the prefix, right-align it, fill a KV
cache of prefix + `max_decoding_steps` slots with its decoder (which projects every prefix slot onto the
vocabulary), and keep the last slot's logits and the cache. Prints one JSON line: timings and those logits.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from upstream_pi0_timing import upstream_args


def main() -> None:
    args = upstream_args("bench_model.py")

    import flax.nnx as nnx
    import jax
    import jax.numpy as jnp
    import ml_collections
    import numpy as np
    from openpi.models import gemma_fast, model, pi0_fast, siglip

    spec = json.loads(Path(args.spec).read_text())
    arch = spec["architecture"]
    llm = ml_collections.ConfigDict(
        {"variant": "gemma_2b", **arch["llm"], "norm_eps": 1e-6, "scan": True, "remat_policy": "none"}
    )
    gemma_fast.get_config = lambda variant: llm
    decode = siglip.decode_variant
    siglip.decode_variant = lambda variant: {**decode(variant), **arch["siglip"]}

    config = pi0_fast.Pi0FASTConfig(
        dtype="float32",
        action_dim=spec["action_dim"],
        action_horizon=spec["action_horizon"],
        max_token_len=spec["max_token_len"],
    )
    pi = config.load(model.restore_params(spec["params_dir"], dtype=None))
    inputs = dict(np.load(spec["inputs"]))
    cams = spec["cameras"]
    obs = model.Observation(
        images={c: inputs[f"image_{c}"] for c in cams},
        image_masks={c: inputs[f"image_mask_{c}"] for c in cams},
        state=inputs["state"],
        tokenized_prompt=inputs["tokenized_prompt"],
        tokenized_prompt_mask=inputs["tokenized_prompt_mask"],
        token_ar_mask=inputs["token_ar_mask"],
        token_loss_mask=inputs["token_loss_mask"],
    )
    steps = spec["max_decoding_steps"]
    graphdef, state = nnx.split(pi)

    @jax.jit
    def prefill(state, obs):
        m = nnx.merge(graphdef, state)
        x, input_mask, ar_mask = m.embed_inputs(obs)
        x, input_mask, attn = pi0_fast.left_to_right_align(x, input_mask, pi0_fast.make_attn_mask(input_mask, ar_mask))
        attn = jnp.pad(attn, ((0, 0), (0, 0), (0, steps)))
        positions = jnp.cumsum(input_mask, axis=-1) - 1
        logits, cache, _ = m.PaliGemma.llm(embedded_prefix=x, mask=attn, positions=positions, decode=True)
        return logits[:, -1], cache

    t0 = time.perf_counter()
    last = np.asarray(jax.block_until_ready(prefill(state, obs))[0])
    first = time.perf_counter() - t0
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(prefill(state, obs))
        times.append(time.perf_counter() - t0)
    print(json.dumps({"jax": jax.__version__, "first_call_s": first, "prefill_s": statistics.median(times),
                      "last_logits": last.tolist()}))  # fmt: skip


if __name__ == "__main__":
    main()
