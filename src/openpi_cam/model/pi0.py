"""pi0 and pi0.5: the PaliGemma prefix (images + prompt), then an action expert denoises an action chunk by flow
matching, as upstream's `Pi0` does.

The LLM is a mixture of two Gemma stacks over one attention: prefix tokens go through the PaliGemma weights
(`PaliGemma/llm/...`), suffix tokens (state, noisy actions) through the action expert's (`..._1`); queries and keys of
both share every attention layer. Sampling fills a KV cache with the prefix once, then runs `num_steps` Euler steps
from the noise (t = 1) to the actions (t = 0), each step attending to the cached prefix and to its own suffix.
pi0.5 reads the state as prompt text and conditions the expert's norms on the time (adaRMS: scale, shift, gate).

Shapes: B batch, P prefix length, S suffix length, H action horizon, A action dim, D LLM width, E expert width,
L layers, K kv heads, Hd head dim.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model import gemma, lrp
from openpi_cam.model.checkpoint import load_params
from openpi_cam.model.config import GemmaConfig, Pi0Config, pi0_architecture_from_params, pi0_param_shapes
from openpi_cam.model.init import init_from_shapes
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.paligemma import embed_images, embed_prefix, make_attn_mask, pool_prefix
from openpi_cam.model.safetensors_weights import LEROBOT_HEADS, HeadCounts, load_safetensors_params
from openpi_cam.nested import flatten_dict

KVCache = tuple[jax.Array, jax.Array]  # K (after RoPE) and V of every layer: [L, B, P, K, Hd] each


MIN_PERIOD, MAX_PERIOD = 4e-3, 4.0  # the time embedding's period range (upstream's and LeRobot's defaults)


def posemb_sincos(t: jax.Array, dim: int, min_period: float = MIN_PERIOD, max_period: float = MAX_PERIOD) -> jax.Array:
    """Sine-cosine embedding of scalar times t [B] -> [B, dim], the sine half first."""
    fraction = jnp.linspace(0.0, 1.0, dim // 2)
    period = min_period * (max_period / min_period) ** fraction
    angles = jnp.einsum("i,j->ij", t, 1.0 / period * 2 * math.pi, precision=jax.lax.Precision.HIGHEST)
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)


def lerobot_time_grid(num_steps: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """LeRobot's Euler times t_k = 1 + k dt (rounded to float32 once) [n] and their sine-cosine embeddings [n, dim],
    evaluated in float64 and rounded to float32, as its PyTorch port computes them."""
    dt = -1.0 / num_steps
    t = np.asarray([1.0 + k * dt for k in range(num_steps)], np.float32)
    period = MIN_PERIOD * (MAX_PERIOD / MIN_PERIOD) ** np.linspace(0.0, 1.0, dim // 2)
    angles = (1.0 / period * 2 * math.pi)[None, :] * t.astype(np.float64)[:, None]
    return t, np.concatenate([np.sin(angles), np.cos(angles)], axis=-1).astype(np.float32)


def _linear(p: dict, x: jax.Array) -> jax.Array:
    return jnp.dot(x, p["kernel"]) + p["bias"]


def _norm(x: jax.Array, p: dict, cond: jax.Array | None, rules: str = "gradient") -> tuple[jax.Array, jax.Array | None]:
    """RMSNorm; with a condition (pi0.5's expert) adaptive: (normed * (1 + scale) + shift, gate), where scale, shift
    and gate come from `cond @ Dense_0` [B, 3E]. Under "lrp" rules the normaliser and the modulation are constants
    (`model.lrp`: the modulation depends on the Euler step alone)."""
    if cond is None:
        return gemma.rms_norm(x, p["scale"], rules), None
    var = jnp.mean(jnp.square(x.astype(jnp.float32)), axis=-1, keepdims=True)
    normed = x * lrp.constant(jnp.reciprocal(jnp.sqrt(var + 1e-6)), rules)
    modulation = lrp.constant(_linear(p["Dense_0"], cond.astype(x.dtype)), rules)
    scale, shift, gate = jnp.split(modulation[:, None, :], 3, axis=-1)  # [B, 1, E] each
    return (normed * (1 + scale) + shift).astype(x.dtype), gate


def _gated(x: jax.Array, y: jax.Array, gate: jax.Array | None) -> jax.Array:
    return x + y if gate is None else x + y * gate


def _expert(llm: dict, i: int) -> dict:
    """Expert i's weights in the layout of one Gemma stack (the PaliGemma LLM has no suffix, the expert `_1`)."""
    sfx = "" if i == 0 else f"_{i}"
    layers, attn = llm["layers"], llm["layers"]["attn"]
    return {
        "layers": {
            "attn": {name: attn[name + sfx] for name in ("q_einsum", "kv_einsum", "attn_vec_einsum")},
            "mlp": layers["mlp" + sfx],
            "pre_attention_norm": layers["pre_attention_norm" + sfx],
            "pre_ffw_norm": layers["pre_ffw_norm" + sfx],
        },
        "final_norm": llm["final_norm" + sfx],
    }


def mixture_forward(
    llm: dict,
    xs: Sequence[jax.Array | None],
    positions: jax.Array,
    mask: jax.Array,
    cfgs: Sequence[GemmaConfig],
    conds: Sequence[jax.Array | None],
    cache: KVCache | None = None,
) -> tuple[list[jax.Array | None], KVCache]:
    """Runs each expert's tokens xs[i] [B, T_i, W_i] (None: expert i has none) through the shared-attention stack.

    `positions` [B, T] and `mask` [B, T, S] cover the present tokens in expert order (T = sum of T_i); with a
    `cache` the keys are [cached | present] (S = P + T). Returns each expert's final-normed outputs and the present
    tokens' K/V of every layer ([L, B, T, K, Hd]), K/V with the cache prepended when one was given."""
    active = [i for i, x in enumerate(xs) if x is not None]
    experts = [_expert(llm, i) for i in active]
    ref = cfgs[active[0]]
    dtype = xs[active[0]].dtype
    lengths = [xs[i].shape[1] for i in active]

    def layer(hs, scanned):
        lps, layer_cache = scanned
        normed, gates, qs, ks, vs = [], [], [], [], []
        for h, lp, i in zip(hs, lps, active, strict=True):
            n, gate = _norm(h, lp["pre_attention_norm"], conds[i], cfgs[i].rules)
            scale = cfgs[i].lora_alpha / cfgs[i].lora_rank if cfgs[i].lora_rank else 1.0
            q = gemma.einsum_lora("BTD,NDH->BTNH", n, lp["attn"], "q_einsum", scale)
            k, v = gemma.einsum_lora("BSD,CKDH->CBSKH", n, lp["attn"], "kv_einsum", scale)
            normed.append(n)
            gates.append(gate)
            qs, ks, vs = [*qs, q], [*ks, k], [*vs, v]
        q, k, v = (jnp.concatenate(t, axis=1) for t in (qs, ks, vs))
        # pi0's Gemma casts RoPE's float32 result back to the compute dtype (pi0-FAST's keeps float32).
        q = gemma.apply_rope(q, positions).astype(dtype) * ref.head_dim**-0.5
        k = gemma.apply_rope(k, positions).astype(dtype)
        if layer_cache is not None:
            k = jnp.concatenate([layer_cache[0], k], axis=1)
            v = jnp.concatenate([layer_cache[1], v], axis=1)
        b, t, n_heads, hd = q.shape
        q = q.reshape(b, t, ref.num_kv_heads, n_heads // ref.num_kv_heads, hd)
        encoded = gemma.attend(*lrp.attention_operands(q, k, v, ref.rules), mask, 0).reshape(b, t, n_heads, hd)
        out, start = [], 0
        for h, lp, i, gate, length in zip(hs, lps, active, gates, lengths, strict=True):
            scale = cfgs[i].lora_alpha / cfgs[i].lora_rank if cfgs[i].lora_rank else 1.0
            y = gemma.einsum_lora(
                "BTNH,NHD->BTD", encoded[:, start : start + length], lp["attn"], "attn_vec_einsum", scale
            )
            h = _gated(h, y, gate)
            n, gate = _norm(h, lp["pre_ffw_norm"], conds[i], cfgs[i].rules)
            out.append(_gated(h, gemma.feed_forward(n, lp["mlp"], cfgs[i].rules), gate))
            start += length
        return tuple(out), (k, v)

    hs = tuple(xs[i] for i in active)
    lps = tuple(e["layers"] for e in experts)
    hs, kv = jax.lax.scan(layer, hs, (lps, cache), unroll=not ref.scan)
    outs: list[jax.Array | None] = [None] * len(xs)
    for h, e, i in zip(hs, experts, active, strict=True):
        outs[i] = _norm(h, e["final_norm"], conds[i], cfgs[i].rules)[0]
    return outs, kv


def _configs(cfg: Pi0Config) -> tuple[GemmaConfig, GemmaConfig]:
    return cfg.gemma, cfg.expert


def preprocess(obs: Observation, cfg: Pi0Config) -> Observation:
    """Upstream's inference preprocessing for pi0 / pi0.5: the model's cameras (`cfg.image_keys`), in that order, and
    a prefix without AR structure (upstream's pi0 prefix is fully bidirectional whatever the tokenizer produced)."""
    return dataclasses.replace(preprocess_observation(obs, cfg.image_resolution, cfg.image_keys), token_ar_mask=None)


def embed_suffix(
    params: dict, cfg: Pi0Config, state: jax.Array, x_t: jax.Array, t: jax.Array, time_emb: jax.Array | None = None
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array | None]:
    """(tokens [B, S, E], input mask [B, S], AR mask [S], adaRMS condition [B, E] or None).

    pi0: a state token then H action tokens that mix x_t with the time embedding through an MLP; the state token
    sees the prefix and itself, the action tokens the prefix, the state and each other. pi0.5: H action tokens only,
    the time entering through the condition. `time_emb` [B, E] replaces the embedding of t (LeRobot's time grid)."""
    width = cfg.expert.width
    actions = _linear(params["action_in_proj"], x_t)  # [B, H, E]
    time_emb = posemb_sincos(t, width) if time_emb is None else time_emb
    b, h = x_t.shape[:2]
    if cfg.pi05:
        cond = jax.nn.swish(_linear(params["time_mlp_out"], jax.nn.swish(_linear(params["time_mlp_in"], time_emb))))
        tokens, ar = actions, [True] + [False] * (h - 1)
    else:
        mixed = jnp.concatenate([actions, jnp.broadcast_to(time_emb[:, None, :], (b, h, width))], axis=-1)
        hidden = lrp.swish(_linear(params["action_time_mlp_in"], mixed), cfg.expert.rules)
        mixed = _linear(params["action_time_mlp_out"], hidden)
        state_token = _linear(params["state_proj"], state)[:, None, :]
        cond, tokens, ar = None, jnp.concatenate([state_token, mixed], axis=1), [True, True] + [False] * (h - 1)
    return tokens, jnp.ones(tokens.shape[:2], bool), jnp.asarray(ar), cond


def fill_prefix_cache(params: dict, image_tokens: jax.Array, obs: Observation, cfg: Pi0Config):
    """One pass of the prefix through the PaliGemma weights -> (KV cache, prefix input mask [B, P])."""
    cache, input_mask, _ = _prefix_pass(params, image_tokens, obs, cfg)
    return cache, input_mask


def _prefix_pass(params: dict, image_tokens: jax.Array, obs: Observation, cfg: Pi0Config):
    """`fill_prefix_cache`, and the prefix's final-normed outputs [B, P, D] (unused, and so not computed, unless a
    caller reads them)."""
    x, input_mask, ar_mask = embed_prefix(params, image_tokens, obs, cfg)
    positions = jnp.cumsum(input_mask, axis=1) - 1
    mask = make_attn_mask(input_mask, ar_mask)
    llm = params["PaliGemma"]["llm"]
    (outputs, _), cache = mixture_forward(llm, [x, None], positions, mask, _configs(cfg), [None, None])
    return cache, input_mask, outputs


def velocity(
    params: dict,
    cfg: Pi0Config,
    cache: KVCache,
    prefix_mask: jax.Array,
    state: jax.Array,
    x_t: jax.Array,
    t: jax.Array,
    time_emb: jax.Array | None = None,
) -> jax.Array:
    """v_t [B, H, A] at x_t and time t [B], the suffix attending to the cached prefix (one Euler step's model call)."""
    return _velocity(params, cfg, cache, prefix_mask, state, x_t, t, time_emb)[0]


def _velocity(
    params: dict,
    cfg: Pi0Config,
    cache: KVCache,
    prefix_mask: jax.Array,
    state: jax.Array,
    x_t: jax.Array,
    t: jax.Array,
    time_emb: jax.Array | None,
) -> tuple[jax.Array, jax.Array]:
    """`velocity`, and the action expert's final-normed outputs at the action tokens [B, H, E] it was projected from."""
    tokens, suffix_mask, suffix_ar, cond = embed_suffix(params, cfg, state, x_t, t, time_emb)
    s = tokens.shape[1]
    mask = jnp.concatenate(
        [
            jnp.broadcast_to(prefix_mask[:, None, :], (tokens.shape[0], s, prefix_mask.shape[1])),
            make_attn_mask(suffix_mask, suffix_ar),
        ],
        axis=-1,
    )
    positions = jnp.sum(prefix_mask, axis=-1)[:, None] + jnp.cumsum(suffix_mask, axis=-1) - 1
    llm = params["PaliGemma"]["llm"]
    (_, out), _ = mixture_forward(llm, [None, tokens], positions, mask, _configs(cfg), [None, cond], cache)
    actions = out[:, -cfg.action_horizon :]
    return _linear(params["action_out_proj"], actions), actions


def denoise(
    params: dict, image_tokens: jax.Array, obs: Observation, noise: jax.Array, cfg: Pi0Config, *, record: bool = False
):
    """The Euler integration of upstream's `sample_actions` from the image tokens on, differentiable in them.

    t runs from 1 (noise) to 0 in `num_steps` steps of dt = -1 / num_steps accumulated in float32 exactly as upstream
    (its while-loop condition `t >= -dt / 2` always stops after `num_steps` steps), or on LeRobot's grid
    (`cfg.flow_time`, `lerobot_time_grid`). Each step is rematerialised, so a
    backward pass through all steps keeps one step's activations at a time. Returns x_0 [B, H, A], and with `record`
    (x before each step [B, n, H, A], v at each step [B, n, H, A], t at each step [n])."""
    x_0, trace, _ = _denoise(params, image_tokens, obs, noise, cfg, record, False)
    return (x_0, trace) if record else x_0


def _denoise(
    params: dict,
    image_tokens: jax.Array,
    obs: Observation,
    noise: jax.Array,
    cfg: Pi0Config,
    record: bool,
    signals: bool,
):
    """`denoise`'s integration -> (x_0, its record or None, and with `signals` what a failure monitor reads of it:
    `cameras` (camera -> [B, D]) and `prompt` [B, D], the prefix pass's outputs pooled per span
    (`paligemma.pool_prefix`), and `actions` [B, E], the action expert's outputs at the action tokens in the last
    Euler step, averaged over the H tokens in float32; else None). Each step's x and v are the same operations with
    signals or without: the pooled outputs are read beside them."""
    cache, prefix_mask, prefix_out = _prefix_pass(params, image_tokens, obs, cfg)
    dt = -1.0 / cfg.num_steps
    b = noise.shape[0]

    @jax.checkpoint
    def step(carry, grid):
        x_t, t = carry
        emb = None
        if grid is not None:
            t, emb = grid[0], jnp.broadcast_to(grid[1], (b, grid[1].shape[-1]))
        v_t, out = _velocity(params, cfg, cache, prefix_mask, obs.state, x_t, jnp.broadcast_to(t, (b,)), emb)
        pooled = jnp.mean(out.astype(jnp.float32), axis=1) if signals else None
        return (x_t + dt * v_t, t + dt), ((x_t, v_t, t) if record else None, pooled)

    grid = lerobot_time_grid(cfg.num_steps, cfg.expert.width) if cfg.flow_time == "lerobot" else None
    (x_0, _), (trace, pooled) = jax.lax.scan(step, (noise, jnp.asarray(1.0, jnp.float32)), grid, length=cfg.num_steps)
    if record:
        xs, vs, ts = trace
        trace = (jnp.moveaxis(xs, 0, 1), jnp.moveaxis(vs, 0, 1), ts)
    recorded = None
    if signals:
        cameras, prompt = pool_prefix(prefix_out, prefix_mask, list(obs.images), image_tokens.shape[2])
        recorded = {"cameras": cameras, "prompt": prompt, "actions": pooled[-1]}
    return x_0, trace, recorded


def sample_actions(params: dict, obs: Observation, noise: jax.Array, *, cfg: Pi0Config) -> jax.Array:
    """Upstream's `Pi0.sample_actions(rng, obs, noise=noise)`: x_0 [B, H, A]."""
    obs = preprocess(obs, cfg)
    return denoise(params, embed_images(params, obs, cfg), obs, noise, cfg)


def compute_loss(
    params: dict, obs: Observation, actions: jax.Array, noise: jax.Array, time: jax.Array, *, cfg: Pi0Config
) -> jax.Array:
    """Upstream's flow-matching loss for given noise and time [B]: mean over A of (v_t - (noise - actions))**2,
    from one pass over prefix + suffix together. -> [B, H]"""
    obs = preprocess(obs, cfg)
    t = time[:, None, None]
    x_t = t * noise + (1 - t) * actions
    prefix, prefix_mask, prefix_ar = embed_prefix(params, embed_images(params, obs, cfg), obs, cfg)
    suffix, suffix_mask, suffix_ar, cond = embed_suffix(params, cfg, obs.state, x_t, time)
    input_mask = jnp.concatenate([prefix_mask, suffix_mask], axis=1)
    ar = jnp.concatenate(
        [jnp.broadcast_to(prefix_ar, prefix_mask.shape), jnp.broadcast_to(suffix_ar, suffix_mask.shape)], 1
    )
    positions = jnp.cumsum(input_mask, axis=1) - 1
    llm = params["PaliGemma"]["llm"]
    mask = make_attn_mask(input_mask, ar)
    (_, out), _ = mixture_forward(llm, [prefix, suffix], positions, mask, _configs(cfg), [None, cond])
    v_t = _linear(params["action_out_proj"], out[:, -cfg.action_horizon :])
    return jnp.mean(jnp.square(v_t - (noise - actions)), axis=-1)


def sample_with_signals(
    params: dict, obs: Observation, noise: jax.Array, *, cfg: Pi0Config
) -> tuple[jax.Array, dict[str, Any]]:
    """`sample_actions` and what a failure monitor reads of the same call (`_denoise`'s signals): (x_0, signals)."""
    obs = preprocess(obs, cfg)
    x_0, _, signals = _denoise(params, embed_images(params, obs, cfg), obs, noise, cfg, False, True)
    return x_0, signals


sample_actions_jit = jax.jit(sample_actions, static_argnames="cfg")
sample_with_signals_jit = jax.jit(sample_with_signals, static_argnames="cfg")


def init_params(config: Pi0Config, rng: jax.Array) -> dict:
    """Fresh parameters with upstream's pi0 / pi0.5 tree, for training from scratch (`model.init.init_from_shapes`)."""
    return init_from_shapes(pi0_param_shapes(config), rng)


class Pi0:
    """A pi0 / pi0.5 config, its params, and the compiled sampler; maps are in `openpi_cam.model.pi0_maps`."""

    def __init__(self, config: Pi0Config, params: dict):
        self.config = config
        self.params = params
        self._embed_images = jax.jit(functools.partial(embed_images, cfg=config))
        self._loss = jax.jit(functools.partial(compute_loss, cfg=config))

    @property
    def family(self) -> str:
        return "pi05" if self.config.pi05 else "pi0"

    @classmethod
    def from_params(cls, params: dict, *, scan: bool | None = None, **data_config: Any) -> Pi0:
        """Architecture (and pi0 vs pi0.5) from the parameter shapes; `data_config` sets action_horizon,
        max_token_len, dtype, num_steps (action_dim comes from the projections)."""
        flat = flatten_dict(params)
        llm, expert, siglip, pi05 = pi0_architecture_from_params(flat, scan=scan)
        action_dim = flat["action_in_proj/kernel"].shape[0]
        return cls(Pi0Config(llm, expert, siglip, pi05, action_dim, **data_config), params)

    @classmethod
    def from_checkpoint(
        cls, params_dir: str | pathlib.Path, *, dtype: str = "bfloat16", scan: bool | None = None, **data_config: Any
    ) -> Pi0:
        """Loads an OpenPI `<checkpoint>/params` directory (bfloat16 weights in bfloat16, as upstream serves)."""
        params = load_params(params_dir, dtype=None if dtype == "float32" else dtype)
        return cls.from_params(params, scan=scan, dtype=dtype, **data_config)

    @classmethod
    def from_safetensors(
        cls,
        path: str | pathlib.Path,
        *,
        dtype: str = "bfloat16",
        heads: HeadCounts = LEROBOT_HEADS,
        scan: bool | None = None,
        **data_config: Any,
    ) -> Pi0:
        """Loads a PyTorch `model.safetensors` (LeRobot's keys or OpenPI's export), every weight cast to `dtype`."""
        params, _ = load_safetensors_params(path, dtype=dtype, heads=heads)
        return cls.from_params(params, scan=scan, dtype=dtype, **data_config)

    @property
    def camera_grid(self) -> tuple[int, int]:
        return self.config.siglip.grid

    def sample_actions(self, rng: jax.Array, observation: Observation, *, noise: jax.Array | None = None) -> jax.Array:
        """x_0 [B, H, A]; `noise` [B, H, A] (None: drawn from `rng`, as upstream)."""
        batch = observation.state.shape[0]
        if noise is None:
            noise = jax.random.normal(rng, (batch, self.config.action_horizon, self.config.action_dim))
        return sample_actions_jit(self.params, observation, jnp.asarray(noise, jnp.float32), cfg=self.config)

    def sample_with_signals(self, observation: Observation, noise: jax.Array) -> tuple[jax.Array, dict[str, Any]]:
        """`sample_actions` from `noise` [B, H, A] and what a failure monitor reads of the same call: (x_0 [B, H, A],
        signals: `cameras`, `prompt`, `actions`; `_denoise`)."""
        return sample_with_signals_jit(self.params, observation, jnp.asarray(noise, jnp.float32), cfg=self.config)

    def embed_images(self, observation: Observation) -> jax.Array:
        return self._embed_images(self.params, preprocess(observation, self.config))

    def compute_loss(
        self, observation: Observation, actions: jax.Array, noise: jax.Array, time: jax.Array
    ) -> jax.Array:
        return self._loss(self.params, observation, actions, noise, time)
