"""The `lrp` kind on real models: upstream's golden tiny pi0-FAST, pi0 and pi0.5 and the bundled demo models.

- The forward pass is bit-identical under either rules (what is served cannot change).
- Relevance balances on the whole model: what the pixels carry (the kind's map, summed), plus the other inputs'
  relevance, plus what every bias absorbs (its value x its modified gradient) and what every softmax's remainder
  absorbs (sum R_s - sum R_x of each softmax row, read back as the cotangent of one scalar that the two softmax
  seams, `gemma.attend` and `siglip.attention_weights`, are instrumented to report), equals the explained score.
  Inputs: pi0-FAST's pixels and embedded tokens (prompt and fed-back generation: the embedding table's uses, less the
  tied output projection's, which is the score itself); pi0's pixels, prompt, state, noise and the time embedding
  (the time half of its action-time MLP's input). pi0.5 is left out of this balance: its adaRMS shift, a function of
  the time alone held constant by the rules, absorbs relevance that no input or parameter gradient reads back (its
  rule is checked in tests/model/test_lrp.py); its maps are checked for the rest below.
- Every target of both families gives finite maps, and asking for `lrp` beside the other kinds leaves their maps
  bit-identical.

Tolerance of the balance: the terms are float32 sums over the whole model (pixels: 3 x 224 x 224 x 3 values);
measured within 4.5e-7 of the largest term (12 explained logits of the golden and demo pi0-FAST; 1.5e-7 for the
pi0 action), so BALANCE_REL = 1e-5 of it. On those logits the pixels carry 0.6-3.5 of scores of 6-8 (golden) and
0.6-2.8 of 13.5 (the demo's first action token); the softmaxes' remainders take 1-5.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.model import baseline_maps, gemma, lrp, pi0, pi0_maps, siglip
from openpi_cam.model import pi0_fast_maps as fast_maps
from openpi_cam.model.observation import Observation, preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits
from openpi_cam.nested import flatten_dict

FAST_CAMERAS = ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
FLOW_CAMERAS = ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"]
BALANCE_REL = 1e-5


# ----------------------------------------------------------------------------------------------------------------
# The softmaxes' remainder, read back through one scalar


def _ledger_attend(ledger: jax.Array):
    """`gemma.attend` with its own forward and backward, whose backward also reports what the softmax absorbs as the
    cotangent of `ledger`. The output's cotangent d_out meets A V: the weights' half is R_s = s * (d_out . v) / 2,
    the logits' R_x = x * (softmax VJP of the same) (the rules' quarter-gradients at q and k give it); absorbed:
    sum R_s - sum R_x over the rows the mask lets through."""

    @functools.partial(jax.custom_vjp, nondiff_argnums=(5,))
    def attend(q, k, v, mask, ledger, hidden_slots):
        return gemma._masked_softmax_attention(q, k, v, mask, hidden_slots)[0]

    def fwd(q, k, v, mask, ledger, hidden_slots):
        out, res = gemma._attend_fwd(q, k, v, mask, hidden_slots)
        return out, res

    def bwd(hidden_slots, res, d_out):
        d_q, d_k, d_v, _ = gemma._attend_bwd(hidden_slots, res, d_out)
        q, k, v, mask, probs = res
        d_probs = jnp.einsum("BTKGH,BSKH->BKGTS", d_out, v, preferred_element_type=jnp.float32)
        d_logits = probs * (d_probs - jnp.sum(probs * d_probs, axis=-1, keepdims=True))
        d_logits = jnp.where(mask[:, None, None], d_logits, 0.0)
        logits = jnp.einsum("BTKGH,BSKH->BKGTS", q, k, preferred_element_type=jnp.float32)
        absorbed = 0.5 * (jnp.sum(probs * d_probs) - jnp.sum(logits * d_logits))
        return d_q, d_k, d_v, None, absorbed

    attend.defvjp(fwd, bwd)
    return lambda q, k, v, mask, hidden_slots: attend(q, k, v, mask, ledger, hidden_slots)


def _ledger_weights(ledger: jax.Array):
    """`siglip.attention_weights` reporting its softmax's remainder: the cotangent g reaching the weights already
    carries the uniform rule's half, so R_s = s * g and R_x = x * (softmax VJP of g)."""

    @jax.custom_vjp
    def weights(logits, ledger):
        return jax.nn.softmax(logits, axis=-1)

    def fwd(logits, ledger):
        probs = jax.nn.softmax(logits, axis=-1)
        return probs, (logits, probs)

    def bwd(res, g):
        logits, probs = res
        d_logits = probs * (g - jnp.sum(probs * g, axis=-1, keepdims=True))
        return d_logits, jnp.sum(probs * g) - jnp.sum(logits * d_logits)

    weights.defvjp(fwd, bwd)
    return lambda logits, dtype: weights(logits, ledger).astype(dtype)


@contextlib.contextmanager
def softmax_ledger(ledger: jax.Array):
    """While tracing: both softmax seams report into `ledger` (restored after)."""
    saved = gemma.attend, siglip.attention_weights
    gemma.attend, siglip.attention_weights = _ledger_attend(ledger), _ledger_weights(ledger)
    try:
        yield
    finally:
        gemma.attend, siglip.attention_weights = saved


def _bias_relevance(params: dict, grads: dict, extra: tuple[str, ...] = ()) -> float:
    """What the biases absorb: sum of leaf x modified gradient over SigLIP's biases and position embedding and the
    leaves named in `extra`."""
    flat, flat_g = flatten_dict(params), flatten_dict(grads)
    names = [
        p
        for p in flat
        if (p.startswith("PaliGemma/img/") and (p.endswith("/bias") or p.endswith("pos_embedding"))) or p in extra
    ]
    assert names
    return float(sum(np.sum(np.asarray(flat[p], np.float64) * np.asarray(flat_g[p], np.float64)) for p in names))


def _table_relevance(params: dict, grads: dict) -> float:
    table = "PaliGemma/llm/embedder/input_embedding"
    return float(np.sum(np.asarray(flatten_dict(params)[table], np.float64) * flatten_dict(grads)[table]))


def _assert_balanced(score: float, terms: dict[str, float]) -> None:
    scale = max(max(abs(v) for v in terms.values()), abs(score))
    total = sum(terms.values())
    assert total == pytest.approx(score, abs=BALANCE_REL * scale), f"score {score} != sum {total} of {terms}"


# ----------------------------------------------------------------------------------------------------------------
# pi0-FAST


def _fast_case(name: str) -> tuple[dict, Observation]:
    with np.load(GOLDEN_DIR / "tiny_pi0_fast" / f"{name}.npz") as npz:
        data = {k: npz[k] for k in npz.files}
    return data, golden.load_observation(data, FAST_CAMERAS)


def _fast_balance(model: Pi0FAST, obs: Observation, generated: np.ndarray, step: int) -> tuple[float, dict]:
    """The logit of generated[:, step] (summed over rows) and its relevance balance terms."""
    cfg = lrp.with_rules(model.config, "lrp")
    obs = preprocess_observation(obs, cfg.image_resolution)
    images, _ = baseline_maps.camera_stack(obs)
    replay = jnp.asarray(generated)[:, : fast_maps.replay_length(step, generated.shape[1])]

    def score(images, params, ledger):
        with softmax_ledger(ledger):
            o = baseline_maps.with_images(obs, dict(zip(obs.images, images, strict=True)))
            pre = replay_prelogits(params, embed_images(params, o, cfg), o, replay, cfg, generated.shape[1])
            table = params["PaliGemma"]["llm"]["embedder"]["input_embedding"]
            return jnp.sum(pre[:, step] * table[replay[:, step]])

    value, (g_images, g_params, g_ledger) = jax.jit(jax.value_and_grad(score, argnums=(0, 1, 2)))(
        images, model.params, jnp.float32(0.0)
    )
    value = float(value)
    pixels = np.asarray(images, np.float64) * np.asarray(g_images, np.float64)  # [C, B, H, W, 3]
    terms = {
        "pixels": float(pixels.sum()),
        "embedded tokens": _table_relevance(model.params, g_params) - value,
        "biases": _bias_relevance(model.params, g_params),
        "softmaxes": float(g_ledger),
    }
    return value, {"terms": terms, "per_camera": pixels.sum(axis=(1, 2, 3, 4))}


@pytest.mark.parametrize("name", ["case_a", pytest.param("case_b", marks=pytest.mark.slow)])
def test_pi0_fast_relevance_balances_over_the_whole_model(tiny_fast_model: Pi0FAST, name: str):
    """Golden tiny pi0-FAST (case_b has a masked camera, which upstream's decode window still lets the generated
    tokens see): the balance holds, and the kind's maps (through `maps_for_steps`, the explainer's entry point) are
    the pixels' term, camera by camera."""
    data, obs = _fast_case(name)
    tokens, step = data["output_tokens"], 3
    score, balance = _fast_balance(tiny_fast_model, obs, tokens, step)
    _assert_balanced(score, balance["terms"])
    res = fast_maps.maps_for_steps(tiny_fast_model, obs, tokens, [step], kinds=("lrp",))
    assert float(res.score.sum()) == pytest.approx(score, rel=1e-5)
    sums = [float(res.by_kind["lrp"][c].sum()) for c in FAST_CAMERAS]
    np.testing.assert_allclose(sums, balance["per_camera"], rtol=1e-4, atol=1e-4 * np.abs(sums).max())


def test_demo_pi0_fast_relevance_balances(demo_policy):
    """The bundled pi0-FAST (trained: its relevance is not noise), first action token of a demo request."""
    from demo_inputs import demo_observation

    _, trace = demo_policy.infer_traced(demo_observation(0))
    step = int(demo_policy.explainer.tokenizer.action_token_steps(trace.output)[0])
    score, balance = _fast_balance(demo_policy.model, trace.observation, np.asarray(trace.output)[None], step)
    _assert_balanced(score, balance["terms"])
    # the pixels carry a real share of a trained policy's logit, not a rounding residue
    assert abs(balance["terms"]["pixels"]) > 0.01 * abs(score)


@pytest.mark.slow
def test_pi0_fast_lrp_for_every_target_entry_point(tiny_fast_model: Pi0FAST):
    """`maps_for_steps` (one and several tokens), `maps_for_chunk` (a sum of log-probabilities),
    `gradcam_for_action_token` and `gradcam_for_token` (a counterfactual token): finite signed maps on the grid, the
    explained score the gradient pass's, and the other kinds' maps unchanged by asking for `lrp` beside them."""
    data, obs = _fast_case("case_a")
    tokens = data["output_tokens"]
    grid = tiny_fast_model.config.siglip.grid
    both = fast_maps.maps_for_steps(tiny_fast_model, obs, tokens, [2, 5], kinds=("gradcam", "gradnorm", "lrp"))
    alone = fast_maps.maps_for_steps(tiny_fast_model, obs, tokens, [2, 5])
    for kind in ("gradcam", "gradnorm"):
        for c in FAST_CAMERAS:
            np.testing.assert_array_equal(both.by_kind[kind][c], alone.by_kind[kind][c])
    np.testing.assert_array_equal(both.score, alone.score)
    np.testing.assert_array_equal(both.logits, alone.logits)
    assert both.by_kind["lrp"]["base_0_rgb"].shape == (1, 2, *grid)
    chunk = fast_maps.maps_for_chunk(tiny_fast_model, obs, tokens, list(range(8)), kinds=("lrp",))
    one = fast_maps.gradcam_for_action_token(tiny_fast_model, obs, tokens, 4, kinds=("lrp",))
    counter = fast_maps.gradcam_for_token(
        tiny_fast_model,
        obs,
        step=4,
        token_id=7,
        generated_prefix=tokens[0, :4],
        max_decoding_steps=tokens.shape[1],
        kinds=("lrp",),
    )
    for res, shape in ((chunk, (1, *grid)), (one, (1, *grid)), (counter, (1, *grid))):
        maps = np.stack([res.by_kind["lrp"][c] for c in FAST_CAMERAS])
        assert maps.shape[1:] == shape and np.all(np.isfinite(maps)) and np.any(maps > 0) and np.any(maps < 0)
    logp = fast_maps.maps_for_chunk(tiny_fast_model, obs, tokens, list(range(8)), kinds=("gradnorm",))
    # The same log-probability through LRP's rewritten forward pass (its own float32 op order): 1.2e-6 apart relative
    # with jax 0.10.2, about ten float32 steps of the sum; the bound leaves a margin of eight.
    assert float(chunk.score[0]) == pytest.approx(float(logp.score[0]), rel=1e-5)
    assert one.logits is not None and counter.logits is not None  # token targets report their logit vectors
    assert int(np.ravel(counter.token_ids)[0]) == 7
    assert not np.array_equal(one.by_kind["lrp"]["base_0_rgb"], counter.by_kind["lrp"]["base_0_rgb"])


# ----------------------------------------------------------------------------------------------------------------
# pi0 / pi0.5


@functools.cache
def _flow_model(folder: str) -> pi0.Pi0:
    root = GOLDEN_DIR / folder
    data_cfg = json.loads((root / "config.json").read_text())["pi0_config"]
    return pi0.Pi0.from_checkpoint(
        root / "checkpoint" / "params",
        dtype="float32",
        action_horizon=data_cfg["action_horizon"],
        max_token_len=data_cfg["max_token_len"],
    )


def _flow_case(folder: str) -> tuple[dict, Observation]:
    with np.load(GOLDEN_DIR / folder / "case_a.npz") as npz:
        data = {k: npz[k] for k in npz.files}
    return data, golden.load_observation(data, FLOW_CAMERAS)


def test_pi0_relevance_balances_over_the_whole_model():
    """Golden tiny pi0, one action dimension (x_0 is linear in it, so the score is the action itself): pixels,
    prompt, state, noise and the time embedding, with the projections' and SigLIP's biases and the softmaxes."""
    model = _flow_model("tiny_pi0")
    data, obs = _flow_case("tiny_pi0")
    cfg = lrp.with_rules(model.config, "lrp")
    obs = pi0.preprocess(obs, cfg)
    images, _ = baseline_maps.camera_stack(obs)
    h, d = 2, 5

    def score(images, state, noise, params, ledger):
        with softmax_ledger(ledger):
            o = baseline_maps.with_images(obs, dict(zip(obs.images, images, strict=True)))
            o = dataclasses.replace(o, state=state)
            return jnp.sum(pi0.denoise(params, pi0.embed_images(params, o, cfg), o, noise, cfg)[:, h, d])

    noise = jnp.asarray(data["noise"], jnp.float32)
    state = jnp.asarray(obs.state, jnp.float32)
    value, grads = jax.jit(jax.value_and_grad(score, argnums=(0, 1, 2, 3, 4)))(
        images, state, noise, model.params, jnp.float32(0.0)
    )
    g_images, g_state, g_noise, g_params, g_ledger = grads
    width = cfg.expert.width
    time_rows = slice(width, 2 * width)  # action_time_mlp_in's input is [action token | time embedding]
    kernel = np.asarray(model.params["action_time_mlp_in"]["kernel"], np.float64)[time_rows]
    projections = ("action_in_proj", "action_out_proj", "state_proj", "action_time_mlp_in", "action_time_mlp_out")
    terms = {
        "pixels": float(np.sum(np.asarray(images, np.float64) * np.asarray(g_images))),
        "state": float(np.sum(np.asarray(state, np.float64) * np.asarray(g_state))),
        "noise": float(np.sum(np.asarray(noise, np.float64) * np.asarray(g_noise))),
        "time": float(np.sum(kernel * np.asarray(g_params["action_time_mlp_in"]["kernel"])[time_rows])),
        "prompt": _table_relevance(model.params, g_params),
        "biases": _bias_relevance(model.params, g_params, tuple(f"{p}/bias" for p in projections)),
        "softmaxes": float(g_ledger),
    }
    _assert_balanced(float(value), terms)
    res = pi0_maps.maps_for_actions(model, obs, noise, [(h, d)], kinds=("lrp",))
    assert float(res.score.sum()) == pytest.approx(float(value), rel=1e-5)
    total = sum(float(m.sum()) for m in res.by_kind["lrp"].values())
    assert total == pytest.approx(terms["pixels"], rel=1e-4, abs=1e-4 * abs(float(value)))


@pytest.mark.parametrize("folder", [pytest.param("tiny_pi0", marks=pytest.mark.slow), "tiny_pi05"])
def test_flow_lrp_for_both_targets(folder: str):
    """`maps_for_actions` with `action` and `chunk` targets in one call: finite signed maps per camera, the score and
    chunk the gradient pass gives, and the gradient kinds unchanged by asking for `lrp` beside them."""
    model = _flow_model(folder)
    data, obs = _flow_case(folder)
    targets = [(0, 6), pi0_maps.CHUNK]
    both = pi0_maps.maps_for_actions(model, obs, data["noise"], targets, kinds=("gradnorm", "lrp"))
    alone = pi0_maps.maps_for_actions(model, obs, data["noise"], targets, kinds=("gradnorm",))
    for c in FLOW_CAMERAS:
        np.testing.assert_array_equal(both.by_kind["gradnorm"][c], alone.by_kind["gradnorm"][c])
        m = both.by_kind["lrp"][c]
        assert m.shape == (1, 2, *model.config.siglip.grid) and np.all(np.isfinite(m))
    maps = np.stack([both.by_kind["lrp"][c] for c in FLOW_CAMERAS])
    assert np.any(maps > 0) and np.any(maps < 0)
    only = pi0_maps.maps_for_actions(model, obs, data["noise"], targets, kinds=("lrp",))
    np.testing.assert_allclose(only.score, alone.score, rtol=1e-5)
    np.testing.assert_allclose(only.actions, alone.actions, rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------------------------------------------
# The forward pass


def _bitwise(f, params, *args, cfg) -> None:
    jitted = jax.jit(f, static_argnames="cfg")
    plain = jax.tree.leaves(jitted(params, *args, cfg=cfg))
    ruled = jax.tree.leaves(jitted(params, *args, cfg=lrp.with_rules(cfg, "lrp")))
    for a, b in zip(plain, ruled, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _fast_forward(params, obs, generated, *, cfg):
    obs = preprocess_observation(obs, cfg.image_resolution)
    return replay_prelogits(params, embed_images(params, obs, cfg), obs, generated, cfg)


def _flow_forward(params, obs, noise, *, cfg):
    obs = pi0.preprocess(obs, cfg)
    return pi0.denoise(params, pi0.embed_images(params, obs, cfg), obs, noise, cfg)


def test_forward_is_bit_identical_under_either_rules(tiny_fast_model: Pi0FAST, demo_policy, demo_pi05_policy):
    """SigLIP, the decoding replay and the Euler integration give the same bits with rules "gradient" and "lrp":
    the golden tiny pi0-FAST, pi0 and pi0.5 and the two bundled demo models."""
    from demo_inputs import demo_observation

    data, obs = _fast_case("case_b")
    _bitwise(_fast_forward, tiny_fast_model.params, obs, jnp.asarray(data["output_tokens"]), cfg=tiny_fast_model.config)
    for folder in ("tiny_pi0", "tiny_pi05"):
        model = _flow_model(folder)
        data, obs = _flow_case(folder)
        _bitwise(_flow_forward, model.params, obs, jnp.asarray(data["noise"]), cfg=model.config)
    _, trace = demo_policy.infer_traced(demo_observation(1))
    generated = jnp.asarray(np.asarray(trace.output)[None, :16])
    _bitwise(_fast_forward, demo_policy.model.params, trace.observation, generated, cfg=demo_policy.model.config)
    _, trace = demo_pi05_policy.infer_traced(demo_observation(1))
    noise = jnp.asarray(trace.sample_inputs["noise"])[None]
    _bitwise(_flow_forward, demo_pi05_policy.model.params, trace.observation, noise, cfg=demo_pi05_policy.model.config)
