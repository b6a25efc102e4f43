"""What a served call gives a failure monitor (`InferenceTrace.signals`), computed by the served call itself: the
response is the one without signals, to the bit, in both families, for one request and (slow tier; the fast tier's
fleet call is the monitored server's, tests/cam/test_monitor_live.py) for a batched fleet call;
and each signal is the quantity it names, checked against the same quantity computed along another path (a full
last-layer pass, the recorded decode logits, a teacher-forced replay, the denoising's recorded last step).

The bundled demo models serve: their actions depend on the observation (asserted), so a signal path that served
another request's chunk would fail the identity checks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from demo_inputs import demo_observation

from openpi_cam.model import gemma, pi0, pi0_fast
from openpi_cam.model.observation import preprocess_observation
from openpi_cam.model.paligemma import embed_images, embed_prefix, make_attn_mask
from openpi_cam.monitor.signals import entropies_from_logits, pool_spans
from openpi_cam.policies.policy import create_policy
from openpi_cam.vocabulary import (
    ACTION_FEATURES,
    ACTION_TOKENS,
    FEATURES_PREFIX,
    NORMALIZED_CHUNK,
    PROMPT_FEATURES,
    TOKEN_ENTROPIES,
)

SEEDS = (0, 1, 2, 3)
# Each signal against the same quantity from a program of other shapes (a full pass instead of the last-slot one, a
# replay instead of the loop, a joint prefix + suffix pass): measured at most 5e-7 of the quantity's peak on the demo
# models in float32; 1e-5 of the peak leaves room for float32 rounding in another summation order only.
RELATIVE = 1e-5


def _close(got: np.ndarray, want: np.ndarray, what: str) -> None:
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape, what
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=what)  # a masked camera: NaN in both
    if np.isfinite(want).any():
        peak = np.nanmax(np.abs(want))
        np.testing.assert_allclose(got, want, rtol=0, atol=RELATIVE * peak, equal_nan=True, err_msg=what)


def _noise(policy, seed: int) -> np.ndarray:
    cfg = policy.model.config
    return np.random.default_rng(seed).standard_normal((cfg.action_horizon, cfg.action_dim)).astype(np.float32)


def _spans(cameras, per_camera: int, length: int) -> dict[str, tuple[int, int]]:
    spans = {c: (i * per_camera, (i + 1) * per_camera) for i, c in enumerate(cameras)}
    return spans | {"prompt": (len(spans) * per_camera, length)}


def test_pi0_fast_signals_leave_the_served_call_unchanged(demo_policy):
    observations = [demo_observation(s) for s in SEEDS]
    plain = [demo_policy.infer_traced(o) for o in observations]
    assert len({p[0]["actions"].tobytes() for p in plain}) == len(SEEDS)
    for (response, trace), obs in zip(plain, observations, strict=True):
        signalled, traced = demo_policy.infer_traced(obs, signals=True)
        np.testing.assert_array_equal(traced.output, trace.output)
        np.testing.assert_array_equal(signalled["actions"], response["actions"])
        assert trace.signals == {}  # none unless asked


@pytest.mark.slow
def test_signals_leave_a_fleet_calls_actions_unchanged(demo_policy, demo_pi05_policy):
    """The batched rows of a fleet call (`infer_batch_traced`): pi0-FAST's decode as if alone, so with signals they
    are the lone requests' without; pi0.5's, from one noise stream drawn twice, are the same batch's without."""
    observations = [demo_observation(s) for s in SEEDS]
    alone = [demo_policy.infer_traced(o) for o in observations]
    for (response, trace), (batched, batch_trace) in zip(
        alone, demo_policy.infer_batch_traced(observations, signals=True), strict=True
    ):
        np.testing.assert_array_equal(batch_trace.output, trace.output)
        np.testing.assert_array_equal(batched["actions"], response["actions"])
        assert {PROMPT_FEATURES, ACTION_FEATURES, TOKEN_ENTROPIES} <= set(batch_trace.signals)
    policy = demo_pi05_policy
    rng = policy._rng
    without = policy.infer_batch_traced(observations)
    policy._rng = rng
    for (a, ta), (b, tb) in zip(without, policy.infer_batch_traced(observations, signals=True), strict=True):
        np.testing.assert_array_equal(tb.sample_inputs["noise"], ta.sample_inputs["noise"])
        np.testing.assert_array_equal(b["actions"], a["actions"])
        assert {PROMPT_FEATURES, ACTION_FEATURES, NORMALIZED_CHUNK} <= set(tb.signals)


def test_pi0_fast_signals_are_the_pooled_last_layer_the_token_entropies_and_the_action_tokens(demo_policy):
    model, cfg = demo_policy.model, demo_policy.model.config
    tokenizer = demo_policy.explainer.tokenizer
    llm = model.params["PaliGemma"]["llm"]
    for seed in SEEDS[:2]:
        _, trace = demo_policy.infer_traced(demo_observation(seed), signals=True)
        signals, generated = trace.signals, np.asarray(trace.output)
        obs = preprocess_observation(trace.observation, cfg.image_resolution)
        image_tokens = embed_images(model.params, obs, cfg)
        x, mask, ar = embed_prefix(model.params, image_tokens, obs, cfg)
        # every prefix token's last layer by a plain full pass (no alignment, no last-slot shortcut), pooled in NumPy
        full, _ = gemma.forward(llm, x, jnp.cumsum(mask, axis=-1) - 1, make_attn_mask(mask, ar), cfg.gemma)
        spans = _spans(obs.images, image_tokens.shape[2], x.shape[1])
        for name, want in pool_spans(np.asarray(full[0]), spans, np.asarray(mask[0])).items():
            assert signals[FEATURES_PREFIX + name].dtype == np.float32
            _close(signals[FEATURES_PREFIX + name], want, name)
        # the entropies of the logits the loop chose each token from, as recorded for parity checks
        _, steps, logits, _ = pi0_fast.sample_tokens_jit(
            model.params, trace.observation, jax.random.key(0), cfg=cfg, max_decoding_steps=generated.size,
            temperature=0.0, record_logits=True,
        )  # fmt: skip
        steps = int(steps)
        _close(signals[TOKEN_ENTROPIES][:steps], entropies_from_logits(np.asarray(logits[0, :steps])), "entropies")
        # the action tokens are those the actions are decoded from
        action_steps = tokenizer.action_token_steps(generated)
        assert action_steps.size > 2
        np.testing.assert_array_equal(np.flatnonzero(signals[ACTION_TOKENS]), action_steps)
        # features/actions: the pre-logits that chose each action token, averaged, from a teacher-forced replay
        replay = pi0_fast.replay_prelogits(model.params, image_tokens, obs, jnp.asarray(generated[None]), cfg)
        _close(signals[ACTION_FEATURES], np.asarray(replay[0, action_steps]).mean(axis=0), "features/actions")


def test_the_chunk_is_the_normalised_one_the_decoder_gives_over_the_robots_dimensions(demo_policy):
    response, trace = demo_policy.infer_traced(demo_observation(5), signals=True)
    normalised, _ = demo_policy._decoder.extract(trace.output)
    chunk = trace.signals[NORMALIZED_CHUNK]
    assert chunk.shape == np.shape(response["actions"])  # [horizon, the robot's action dimensions]
    np.testing.assert_array_equal(chunk, np.asarray(normalised, np.float64)[:, : chunk.shape[1]])
    assert not np.array_equal(chunk, response["actions"])  # before unnormalisation


def test_flow_signals_leave_the_served_call_unchanged(demo_pi05_policy):
    policy = demo_pi05_policy
    observations = [demo_observation(s) for s in SEEDS]
    plain = [policy.infer_traced(o, noise=_noise(policy, s)) for o, s in zip(observations, SEEDS, strict=True)]
    assert len({p[0]["actions"].tobytes() for p in plain}) == len(SEEDS)
    for (response, trace), obs, seed in zip(plain, observations, SEEDS, strict=True):
        signalled, traced = policy.infer_traced(obs, noise=_noise(policy, seed), signals=True)
        np.testing.assert_array_equal(traced.output, trace.output)
        np.testing.assert_array_equal(signalled["actions"], response["actions"])


def test_flow_signals_are_the_prefix_pass_pooled_and_the_last_euler_steps_expert_outputs(demo_pi05_policy):
    policy = demo_pi05_policy
    model, cfg = policy.model, policy.model.config
    noise = _noise(policy, 7)
    _, trace = policy.infer_traced(demo_observation(7), noise=noise, signals=True)
    signals = trace.signals
    assert TOKEN_ENTROPIES not in signals  # a flow family generates no tokens
    obs = pi0.preprocess(trace.observation, cfg)
    image_tokens = embed_images(model.params, obs, cfg)
    x, mask, ar = embed_prefix(model.params, image_tokens, obs, cfg)
    # the prefix's outputs from the training pass (prefix and suffix together: the prefix never sees the suffix)
    suffix, suffix_mask, suffix_ar, cond = pi0.embed_suffix(model.params, cfg, obs.state, noise[None], jnp.ones(1) / 2)
    joint = jnp.concatenate([mask, suffix_mask], 1)
    joint_ar = jnp.concatenate([jnp.broadcast_to(ar, mask.shape), jnp.broadcast_to(suffix_ar, suffix_mask.shape)], 1)
    (prefix_out, _), _ = pi0.mixture_forward(
        model.params["PaliGemma"]["llm"], [x, suffix], jnp.cumsum(joint, 1) - 1, make_attn_mask(joint, joint_ar),
        (cfg.gemma, cfg.expert), [None, cond],
    )  # fmt: skip
    spans = _spans(obs.images, image_tokens.shape[2], x.shape[1])
    pooled = pool_spans(np.asarray(prefix_out[0]), spans, np.asarray(mask[0]))
    assert any(np.isnan(v).all() for v in pooled.values())  # the demo robot's blank camera is masked: NaN, not 0
    for name, want in pooled.items():
        _close(signals[FEATURES_PREFIX + name], want, name)
    # the expert's outputs at the action tokens in the last Euler step, from the recorded integration's last x and t
    _, (xs, _, ts) = pi0.denoise(model.params, image_tokens, obs, jnp.asarray(noise[None]), cfg, record=True)
    cache, prefix_mask = pi0.fill_prefix_cache(model.params, image_tokens, obs, cfg)
    _, out = pi0._velocity(model.params, cfg, cache, prefix_mask, obs.state, xs[:, -1], ts[-1:], None)
    _close(signals[ACTION_FEATURES], np.asarray(out[0]).mean(axis=0), "features/actions")
    assert signals[ACTION_FEATURES].shape == (cfg.expert.width,)


@pytest.mark.slow
def test_pi0_signals_leave_the_served_call_unchanged(golden_dir):
    """pi0 (a state token before the action tokens in the suffix) beside pi0.5: upstream's tiny LIBERO policy."""
    root = golden_dir / "tiny_policy_pi0_libero"
    policy = create_policy(
        "pi0_libero", root / "checkpoint", paligemma_tokenizer=root / "paligemma_tokenizer_tiny.model", dtype="float32"
    )
    rng = np.random.default_rng(0)
    obs = {
        "observation/state": rng.random(8),
        "observation/image": rng.integers(0, 256, (224, 224, 3), np.uint8),
        "observation/wrist_image": rng.integers(0, 256, (224, 224, 3), np.uint8),
        "prompt": "do something",
    }
    noise = _noise(policy, 0)
    response, trace = policy.infer_traced(obs, noise=noise)
    signalled, traced = policy.infer_traced(obs, noise=noise, signals=True)
    np.testing.assert_array_equal(traced.output, trace.output)
    np.testing.assert_array_equal(signalled["actions"], response["actions"])
    assert traced.signals[ACTION_FEATURES].shape == (policy.model.config.expert.width,)
