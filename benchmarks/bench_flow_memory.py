"""How much working memory explaining a pi0 / pi0.5 chunk takes as the Euler loop grows, from XLA's own accounting.

The explanation differentiates x_0 through `num_steps` action-expert passes. `pi0.denoise` rematerialises each Euler
step (`jax.checkpoint` inside the scan), so the backward pass keeps one step's activations plus the carried x_t per
step, instead of every step's activations. This compiles inference and one explanation (Grad-CAM + gradient norm of
the chunk) of the bundled pi0.5 demo model for several `num_steps` and prints XLA's temporary-buffer size of each
compiled program (`Compiled.memory_analysis()`), side by side: with remat the explanation's working set should stay
nearly flat in `num_steps`.

    python benchmarks/bench_flow_memory.py
"""

from __future__ import annotations

import dataclasses
import functools
import platform

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.checkpoints import model_spec
from openpi_cam.demo import bundled, task
from openpi_cam.model import pi0_maps
from openpi_cam.model.pi0 import preprocess, sample_actions


def temp_bytes(fn, *args) -> int:
    return int(jax.jit(fn).lower(*args).compile().memory_analysis().temp_size_in_bytes)


def main() -> None:
    policy = model_spec.create_demo_policy(model="pi05")
    model = policy.explainer.model
    rng = np.random.default_rng(0)
    scene = task.random_scene(rng)
    _, trace = policy.infer_traced(
        bundled.policy_input(bundled.client_observation(task.observe(scene, task.random_start(rng, scene))))
    )
    obs = trace.observation
    print(f"pi0.5 demo model, batch 1, {platform.machine()}, jax {jax.__version__} ({jax.default_backend()})")
    print(f"{'num_steps':>9} {'inference temp MB':>18} {'explanation temp MB':>20} {'ratio':>6}")
    for steps in (5, 10, 20, 40):
        cfg = dataclasses.replace(model.config, num_steps=steps)
        noise = jnp.zeros((1, cfg.action_horizon, cfg.action_dim), jnp.float32)
        infer = temp_bytes(functools.partial(sample_actions, cfg=cfg), model.params, obs, noise)
        explain = temp_bytes(
            functools.partial(pi0_maps._flow_gradient_maps, cfg=cfg, targets=(pi0_maps.CHUNK,)),
            model.params,
            preprocess(obs, cfg),
            noise,
        )
        print(f"{steps:9d} {infer / 2**20:18.2f} {explain / 2**20:20.2f} {explain / infer:6.1f}")


if __name__ == "__main__":
    main()
