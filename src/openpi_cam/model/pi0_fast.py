"""pi0-FAST: SigLIP image tokens + prompt tokens as a bidirectional prefix, then Gemma decodes FAST action tokens.

Everything here is a pure function of an explicit params pytree (upstream's names); `Pi0FAST` only bundles a
config with its params and the compiled entry points. Shapes: B batch, C cameras, N tokens per camera, L prompt
length, P = C*N + L prefix length, S = max_decoding_steps, D LLM width, V vocabulary.
"""

from __future__ import annotations

import functools
import pathlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from openpi_cam.model import gemma
from openpi_cam.model.checkpoint import load_params
from openpi_cam.model.config import (
    EOS_TOKEN,
    MAX_DECODING_STEPS,
    Pi0FASTConfig,
    architecture_from_params,
    param_shapes,
)
from openpi_cam.model.init import init_from_shapes
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.paligemma import embed_images, embed_prefix, make_attn_mask, pool_prefix
from openpi_cam.nested import flatten_dict


@jax.vmap
def left_to_right_align(x: jax.Array, input_mask: jax.Array, attn_mask: jax.Array):
    """Rolls each row left by (last valid index + 1) so its valid span ends at the last slot, as upstream does.

    Masked tokens *inside* the valid span (e.g. a masked camera between two valid ones) stay inside it."""
    seqlen = jnp.max(input_mask * jnp.arange(input_mask.shape[0])) + 1
    return (
        jnp.roll(x, -seqlen, axis=0),
        jnp.roll(input_mask, -seqlen, axis=0),
        jnp.roll(attn_mask, -seqlen, axis=(0, 1)),
    )


def prefill(
    params: dict,
    x: jax.Array,
    input_mask: jax.Array,
    ar_mask: jax.Array,
    cfg: Pi0FASTConfig,
    steps: int,
    *,
    hidden_steps: int = 0,
):
    """Right-aligns the prefix and fills a KV cache of P + `steps` slots (the unused ones zero), as upstream.

    Only the last prefix slot's output is ever used (it predicts the first token), so the top layer runs the rest of
    the prefix only as far as its K/V and the vocabulary projection is left to the caller, for that one slot
    (upstream projects every prefix slot). `hidden_steps`: decode slots past the cache's end, for a replay shorter
    than the decode (`replay_prelogits`). Returns (pre_logits of the last prefix slot [B, D], cache, prefill_len [B],
    prefix_start [B])."""
    return _prefill(params, x, input_mask, ar_mask, cfg, steps, hidden_steps, False)[:4]


def _prefill(
    params: dict,
    x: jax.Array,
    input_mask: jax.Array,
    ar_mask: jax.Array,
    cfg: Pi0FASTConfig,
    steps: int,
    hidden_steps: int,
    every_output: bool,
):
    """`prefill`, and with `every_output` every prefix token's final-normed output [B, P, D] in prefix order (the
    alignment undone), as `gemma.forward_with_outputs` computes it beside the unchanged last-slot pass."""
    seqlen = jnp.max(input_mask * jnp.arange(input_mask.shape[1]), axis=-1) + 1  # what the alignment rolls by
    attn = make_attn_mask(input_mask, ar_mask)
    x, input_mask, attn = left_to_right_align(x, input_mask, attn)
    prefill_size = x.shape[1]
    prefill_len = jnp.sum(input_mask, axis=-1)
    # Fully masked rows (a masked camera, padding) softmax uniformly over *all* P + steps slots, the zero-filled
    # decode slots included; padding the mask here, not trimming it, keeps their K/V exactly upstream's.
    attn = jnp.pad(attn, ((0, 0), (0, 0), (0, steps)))
    positions = jnp.cumsum(input_mask, axis=-1) - 1
    llm = params["PaliGemma"]["llm"]
    outputs = None
    if every_output:
        pre, cache, aligned = gemma.forward_with_outputs(llm, x, positions, attn, cfg.gemma, hidden_slots=hidden_steps)
        outputs = jax.vmap(lambda o, s: jnp.roll(o, s, axis=0))(aligned, seqlen)
    else:
        pre, cache = gemma.forward(llm, x, positions, attn, cfg.gemma, last_only=True, hidden_slots=hidden_steps)
    return pre[:, -1], cache, prefill_len, prefill_size - prefill_len, outputs


def decode_window(prefix_start: jax.Array, prefill_size: int, steps: int, step: jax.Array) -> jax.Array:
    """Upstream quirk 2: the decode step's attention window is the contiguous slot range
    [prefix_start, prefill_size + step + 1), whatever the input mask says inside it. -> [B, T, P + steps]"""
    slots = jnp.arange(prefill_size + steps)
    step = jnp.atleast_1d(step)
    return (slots[None, None, :] >= prefix_start[:, None, None]) & (
        slots[None, None, :] < prefill_size + step[None, :, None] + 1
    )


def decode_positions(prefill_len: jax.Array, step: jax.Array) -> jax.Array:
    """Upstream quirk 1: the token chosen at step s is fed at RoPE position prefill_len + s + 1, so position
    prefill_len is never used (the last prefix token sits at prefill_len - 1). -> [B, T]"""
    return prefill_len[:, None] + jnp.atleast_1d(step)[None, :] + 1


def sample_tokens(
    params: dict,
    obs: Observation,
    rng: jax.Array,
    *,
    cfg: Pi0FASTConfig,
    max_decoding_steps: int,
    temperature: float,
    stop_token_ids: tuple[int, ...] = (),
    record_logits: bool = False,
    rows_alone: bool = False,
    record_signals: bool = False,
) -> tuple[jax.Array, jax.Array, jax.Array | None, dict[str, Any] | None]:
    """Prefill then KV-cache decoding in one compiled while-loop, as upstream's `sample_actions`.

    Returns (tokens int32 [B, S], number of loop iterations run, with `record_logits` the logits that chose each
    token [B, S, V], for parity checks, and with `record_signals` what a failure monitor reads of the call:
    `cameras` (camera -> [B, D]) and `prompt` [B, D], the prefix's last-layer outputs pooled per span
    (`paligemma.pool_prefix`), `hidden` [B, S, D], the pre-logits that chose each token, and `entropy` [B, S], the
    entropy (nats, float32) of the distribution each token was chosen from, zero past the loop's last step).
    The tokens are those of the call without signals: the served pass runs the same operations, the signals are
    computed beside it. Decoding stops when every row's current token is EOS; with `stop_token_ids` (opt-in, not
    upstream) a row is also finished once it has emitted one of them, and decoding stops when every row has
    finished. `rows_alone` (batched serving) makes each row's tokens what decoding it in a batch of one gives: a row
    is finished at its own EOS (or stop token) and its later slots stay zero, as they would after the loop stopped
    for it alone (upstream's rule, every row at EOS at the same step, only agrees for B = 1)."""
    if rows_alone and temperature > 0.0:
        raise ValueError("rows_alone decodes greedily only: sampling would need one rng per row")
    llm = params["PaliGemma"]["llm"]
    obs = preprocess_observation(obs, cfg.image_resolution)
    image_tokens = embed_images(params, obs, cfg)
    x, input_mask, ar_mask = embed_prefix(params, image_tokens, obs, cfg)
    last_pre, cache, prefill_len, prefix_start, outputs = _prefill(
        params, x, input_mask, ar_mask, cfg, max_decoding_steps, 0, record_signals
    )
    prefill_size = x.shape[1]
    batch = x.shape[0]
    stop_ids = jnp.asarray((EOS_TOKEN, *stop_token_ids), jnp.int32)

    def step_fn(carry):
        rng, last_logit, tokens, cache, _, finished, step, history, signals = carry
        if record_logits:
            history = history.at[:, step].set(last_logit.astype(history.dtype))
        if record_signals:
            signals = _record_choice(signals, step, last_logit)
        rng, rng_step = jax.random.split(rng)
        if temperature > 0.0:
            token = jax.random.categorical(rng_step, last_logit / temperature, axis=-1)
        else:
            token = jnp.argmax(last_logit, axis=-1)
        token = token.astype(jnp.int32)  # [B]
        if rows_alone:
            token = jnp.where(finished, 0, token)
        tokens = tokens.at[:, step].set(token)
        if rows_alone or stop_token_ids:
            finished = finished | jnp.isin(token, stop_ids)
            done = jnp.all(finished)
        else:
            done = jnp.all(token == EOS_TOKEN)  # upstream: every row at EOS *at this step*
        emb = gemma.embed_tokens(llm, token[:, None], jnp.dtype(cfg.dtype))
        mask = decode_window(prefix_start, prefill_size, max_decoding_steps, step)
        pre, cache = gemma.forward(llm, emb, decode_positions(prefill_len, step), mask, cfg.gemma, cache)
        if record_signals:
            signals = {**signals, "last_pre": pre[:, 0]}
        logit = gemma.logits_from_prelogits(llm, pre[:, 0])
        return rng, logit, tokens, cache, done, finished, step + 1, history, signals

    def cond_fn(carry):
        return (~carry[4]) & (carry[6] < max_decoding_steps)

    first_logit = gemma.logits_from_prelogits(llm, last_pre)
    history = jnp.zeros((batch, max_decoding_steps, first_logit.shape[-1]), jnp.float32) if record_logits else None
    signals = _no_choices(last_pre, max_decoding_steps) if record_signals else None
    init = (
        rng,
        first_logit,
        jnp.zeros((batch, max_decoding_steps), jnp.int32),
        cache,
        jnp.array(False),
        jnp.zeros((batch,), bool),
        jnp.array(0, jnp.int32),
        history,
        signals,
    )
    out = jax.lax.while_loop(cond_fn, step_fn, init)
    recorded = None
    if record_signals:
        cameras, prompt = pool_prefix(outputs, input_mask, list(obs.images), image_tokens.shape[2])
        recorded = {"cameras": cameras, "prompt": prompt, "hidden": out[8]["hidden"], "entropy": out[8]["entropy"]}
    return out[2], out[6], out[7], recorded


def _no_choices(last_pre: jax.Array, steps: int) -> dict[str, jax.Array]:
    """The decode loop's record of its choices before the first: each step's pre-logits and entropy (zeros), and
    the pre-logits the next token will be chosen from (the prefill's last slot's)."""
    batch, width = last_pre.shape
    return {
        "hidden": jnp.zeros((batch, steps, width), last_pre.dtype),
        "entropy": jnp.zeros((batch, steps), jnp.float32),
        "last_pre": last_pre,
    }


def _record_choice(signals: dict[str, jax.Array], step: jax.Array, logits: jax.Array) -> dict[str, jax.Array]:
    """The record with step `step`'s choice added: the pre-logits it is made from and the entropy of its logits."""
    return {
        "hidden": signals["hidden"].at[:, step].set(signals["last_pre"]),
        "entropy": signals["entropy"].at[:, step].set(_entropy(logits)),
        "last_pre": signals["last_pre"],
    }


def _entropy(logits: jax.Array) -> jax.Array:
    """The entropy (nats) of softmax(logits) along the last axis, in float32: [..., V] -> [...]."""
    log_p = jax.nn.log_softmax(logits.astype(jnp.float32), axis=-1)
    return -jnp.sum(jnp.exp(log_p) * log_p, axis=-1)


# One compiled program per (shape, config, decoding settings); shared by every model object. The stop tokens are data
# (only how many there are is compiled in), so policies whose stop tokens differ share the program.
sample_tokens_jit = jax.jit(
    sample_tokens,
    static_argnames=("cfg", "max_decoding_steps", "temperature", "record_logits", "rows_alone", "record_signals"),
)


def replay_prelogits(
    params: dict,
    image_tokens: jax.Array,
    obs: Observation,
    generated: jax.Array,
    cfg: Pi0FASTConfig,
    decode_len: int | None = None,
) -> jax.Array:
    """The pre-logits that upstream's decoding computed, as a differentiable function of the image tokens.

    `generated` [B, L] are the first L tokens fed back (teacher forcing) of a decode with `decode_len` =
    max_decoding_steps >= L (default L), which sizes upstream's KV cache. Returns [B, L, D] where row k is the output
    that predicts generated[:, k]: the last prefix slot for k = 0, else the output at generated[:, k - 1]. The
    prefill is upstream's; the L decode steps run as one multi-token append to the same cache with the per-step
    window and positions of the loop, which is the same computation because each decode step only attends to slots
    written before it. Steps past L would only add slots no earlier step sees, except through the uniform softmax
    of fully masked prefix rows, which `hidden_steps` keeps at the full cache size: so a replay cut at any L gives
    the same rows as the full-length one.
    """
    llm = params["PaliGemma"]["llm"]
    steps = generated.shape[1]
    decode_len = steps if decode_len is None else decode_len
    if decode_len < steps:
        raise ValueError(f"{steps} generated tokens do not fit a decode of {decode_len} steps")
    x, input_mask, ar_mask = embed_prefix(params, image_tokens, obs, cfg)
    last_pre, cache, prefill_len, prefix_start = prefill(
        params, x, input_mask, ar_mask, cfg, steps, hidden_steps=decode_len - steps
    )
    step = jnp.arange(steps)
    mask = decode_window(prefix_start, x.shape[1], steps, step)
    emb = gemma.embed_tokens(llm, generated, jnp.dtype(cfg.dtype))
    # The last fed token's output would predict step L, which no caller asks for.
    pre, _ = gemma.forward(llm, emb[:, :-1], decode_positions(prefill_len, step[:-1]), mask[:, :-1], cfg.gemma, cache)
    return jnp.concatenate([last_pre[:, None], pre], axis=1)


def compute_loss(params: dict, obs: Observation, cfg: Pi0FASTConfig, *, decode_offset: int = 0) -> jax.Array:
    """Upstream's training loss: next-token cross-entropy over `token_loss_mask`, one teacher-forced pass. -> [B]

    `decode_offset=1` moves the postfix (the `token_ar_mask` tokens) one RoPE position on, where upstream's decoder
    feeds generated tokens (quirk 1, `decode_positions`); upstream trains with 0. A model that leans on exact
    relative positions must be trained with 1 to be served by upstream's decoder."""
    llm = params["PaliGemma"]["llm"]
    obs = preprocess_observation(obs, cfg.image_resolution)
    x, input_mask, ar_mask = embed_prefix(params, embed_images(params, obs, cfg), obs, cfg)
    attn = make_attn_mask(input_mask, ar_mask)
    t = x.shape[1] - 1
    positions = jnp.broadcast_to(jnp.arange(t, dtype=jnp.int32), (x.shape[0], t))  # upstream passes none here
    positions = positions + decode_offset * (jnp.cumsum(ar_mask[:, :t], axis=1) > 0)
    pre, _ = gemma.forward(llm, x[:, :-1], positions, attn[:, :-1, :-1], cfg.gemma)
    targets = obs.tokenized_prompt[:, 1:]
    logits = gemma.logits_from_prelogits(llm, pre[:, -targets.shape[1] :])
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits.astype(jnp.float32), -1), targets[..., None], -1)[..., 0]
    loss_mask = obs.token_loss_mask[:, 1:]
    return -jnp.sum(logp * loss_mask, -1) / jnp.clip(jnp.sum(loss_mask, -1), 1)


class Pi0FAST:
    """A config, its params, and the compiled sampling and loss (each compiles once per input shape).

    The maps over its image tokens are free functions of this object (`openpi_cam.model.pi0_fast_maps`)."""

    family = "pi0_fast"

    def __init__(self, config: Pi0FASTConfig, params: dict):
        self.config = config
        self.params = params
        self._embed_images = jax.jit(functools.partial(embed_images, cfg=config))
        self._loss = jax.jit(functools.partial(compute_loss, cfg=config), static_argnames="decode_offset")

    @classmethod
    def from_params(cls, params: dict, *, scan: bool | None = None, **data_config: Any) -> Pi0FAST:
        """Architecture from the parameter shapes (`scan`: see `architecture_from_params`); `data_config` sets
        action_dim, action_horizon, max_token_len, dtype (compute dtype, default bfloat16 like upstream)."""
        gemma_cfg, siglip_cfg = architecture_from_params(flatten_dict(params), scan=scan)
        return cls(Pi0FASTConfig(gemma=gemma_cfg, siglip=siglip_cfg, **data_config), params)

    @classmethod
    def from_checkpoint(
        cls, params_dir: str | pathlib.Path, *, dtype: str = "bfloat16", scan: bool | None = None, **data_config: Any
    ) -> Pi0FAST:
        """Loads an OpenPI `<checkpoint>/params` directory. In bfloat16 the weights are restored as bfloat16, like
        upstream's `create_trained_policy`; in float32 they are kept at their stored precision."""
        params = load_params(params_dir, dtype=None if dtype == "float32" else dtype)
        return cls.from_params(params, scan=scan, dtype=dtype, **data_config)

    @property
    def camera_grid(self) -> tuple[int, int]:
        return self.config.siglip.grid

    def sample_actions(
        self,
        rng: jax.Array,
        observation: Observation,
        *,
        max_decoding_steps: int = MAX_DECODING_STEPS,
        temperature: float = 0.0,
        stop_token_ids: Sequence[int] = (),
        rows_alone: bool = False,
    ) -> jax.Array:
        """Generated token ids, int32 [B, max_decoding_steps] (zeros after the loop stopped), as upstream;
        `rows_alone`: each row as decoded in a batch of one (`sample_tokens`)."""
        return sample_tokens_jit(
            self.params,
            observation,
            rng,
            cfg=self.config,
            max_decoding_steps=int(max_decoding_steps),
            temperature=float(temperature),
            stop_token_ids=tuple(int(t) for t in stop_token_ids),
            rows_alone=rows_alone,
        )[0]

    def sample_with_signals(
        self,
        rng: jax.Array,
        observation: Observation,
        *,
        max_decoding_steps: int = MAX_DECODING_STEPS,
        stop_token_ids: Sequence[int] = (),
        rows_alone: bool = False,
    ) -> tuple[jax.Array, dict[str, Any]]:
        """`sample_actions` (greedy) and what a failure monitor reads of the same call (`sample_tokens`'s
        `record_signals`): (the same tokens, the signals)."""
        tokens, _, _, signals = sample_tokens_jit(
            self.params,
            observation,
            rng,
            cfg=self.config,
            max_decoding_steps=int(max_decoding_steps),
            temperature=0.0,
            stop_token_ids=tuple(int(t) for t in stop_token_ids),
            rows_alone=rows_alone,
            record_signals=True,
        )
        assert signals is not None
        return tokens, signals

    def embed_images(self, observation: Observation) -> jax.Array:
        return self._embed_images(self.params, preprocess_observation(observation, self.config.image_resolution))

    def compute_loss(self, observation: Observation, *, decode_offset: int = 0) -> jax.Array:
        return self._loss(self.params, observation, decode_offset=decode_offset)


def init_params(config: Pi0FASTConfig, rng: jax.Array) -> dict:
    """Fresh parameters with upstream's tree, for training from scratch (`model.init.init_from_shapes`)."""
    return init_from_shapes(param_shapes(config.gemma, config.siglip), rng)
