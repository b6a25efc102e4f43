"""AttnLRP's rules (`model.lrp`), each checked where a wrong rule would fail.

Per rule, a case computed by hand: the identity rule passes relevance through GELU and SiLU unchanged, a bilinear
product gives each factor half, the softmax gives its logits the paper's formula (a 3-element example whose
softmax is rational), a log-probability score the same rule with its entropy absorbed, a normaliser is held
constant. A hand-built bias-free network (linear, RMSNorm, gated-GELU
MLP, linear) conserves relevance exactly; a one-head attention block conserves it up to what its softmax absorbs,
computed here from the paper's formula. Tolerances: these sums are float32 evaluations of exact identities over a
few hundred terms; measured within 5.5e-8 (the network) and 2.5e-7 (the attention block) of the largest term, so
REL = 1e-5 of it; the per-rule cases are single float32 operations on values <= 10 (1e-6).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from openpi_cam.model import gemma, lrp, pi0, siglip
from openpi_cam.model.config import GemmaConfig, SiglipConfig

REL = 1e-5


def relevance(fn, *inputs, cotangent=None):
    """(output, input x modified gradient of each input) of fn(*inputs) for the output cotangent (default ones)."""
    out, vjp_fn = jax.vjp(fn, *inputs)
    grads = vjp_fn(jnp.ones_like(out) if cotangent is None else cotangent)
    return out, [np.asarray(x, np.float64) * np.asarray(g, np.float64) for x, g in zip(inputs, grads, strict=True)]


def test_with_rules_reaches_every_layer_stack_and_refuses_unknown_rules():
    from openpi_cam.model.config import Pi0Config

    cfg = lrp.with_rules(Pi0Config(), "lrp")
    assert (cfg.gemma.rules, cfg.expert.rules, cfg.siglip.rules) == ("lrp", "lrp", "lrp")
    assert lrp.with_rules(SiglipConfig(), "lrp").rules == "lrp"
    assert lrp.with_rules(cfg, "gradient") == Pi0Config()
    with pytest.raises(ValueError, match="rules must be one of"):
        lrp.with_rules(GemmaConfig(), "lrp-epsilon")


@pytest.mark.parametrize("name", ["gelu", "swish"])
def test_identity_rule_passes_relevance_through_unchanged(name):
    """R_x = R_y element by element: x * g_x equals f(x) * g_y, finite at x = 0 (where f(x) / x is GELU's 0.5 and
    SiLU's 0.5). The plain gradient gives something else (f'(x) != f(x) / x off 0)."""
    f = getattr(lrp, name)
    x = jnp.asarray([-2.0, -0.5, 0.0, 0.3, 1.7])
    g_y = jnp.asarray([0.5, -1.0, 2.0, 3.0, 0.25])
    y, (r_x,) = relevance(lambda v: f(v, "lrp"), x, cotangent=g_y)
    np.testing.assert_allclose(r_x, np.asarray(y, np.float64) * np.asarray(g_y), rtol=1e-6, atol=1e-7)
    (g_x,) = jax.vjp(lambda v: f(v, "lrp"), x)[1](g_y)
    assert float(g_x[2]) == pytest.approx(0.5 * 2.0)
    _, (plain,) = relevance(lambda v: f(v, "gradient"), x, cotangent=g_y)
    assert not np.allclose(plain, r_x, atol=1e-3)


def test_bilinear_product_gives_each_factor_half():
    """a * b = 3 * -2 = -6: a and b carry -3 each; for q k^T (a sum of products) each side carries half of every
    logit's relevance."""
    a, b = jnp.float32(3.0), jnp.float32(-2.0)
    y, (r_a, r_b) = relevance(lambda u, v: lrp.split(u * v, "lrp"), a, b)
    assert float(y) == -6.0 and float(r_a) == -3.0 and float(r_b) == -3.0
    q = jnp.asarray([[1.0, -2.0]])
    k = jnp.asarray([[0.5, 1.0], [2.0, 0.25], [-1.0, 3.0]])
    logits, (r_q, r_k) = relevance(lambda u, v: lrp.split(u @ v.T, "lrp"), q, k)
    half = float(np.sum(np.asarray(logits, np.float64))) / 2
    assert r_q.sum() == pytest.approx(half) and r_k.sum() == pytest.approx(half)
    np.testing.assert_allclose(r_k.sum(axis=1), np.asarray(logits, np.float64)[0] / 2, rtol=1e-6)


# The paper's softmax rule on a 3-element example: logits x = (0, ln 2, ln 5) give the softmax s = (1, 2, 5) / 8.
# Behind it, attention weights times v = w = (4, 0, 8): the output is sum s w = 11 / 2, and the uniform rule gives
# the weights half of each term, R_s = s w / 2 = (1/4, 0, 5/2), sum 11/4. The rule R_x_i = x_i (R_i - s_i sum_j R_j)
# gives R_x = (0, ln 2 (0 - 2/8 * 11/4), ln 5 (5/2 - 5/8 * 11/4)) = (0, -11/16 ln 2, 25/32 ln 5).
SOFTMAX_X = (0.0, math.log(2.0), math.log(5.0))
SOFTMAX_W = (4.0, 0.0, 8.0)
SOFTMAX_R_S = (0.25, 0.0, 2.5)
SOFTMAX_R_X = (0.0, -11 / 16 * math.log(2.0), 25 / 32 * math.log(5.0))


def test_softmax_rule_is_the_papers_formula():
    """SigLIP's softmax (`siglip.attention_weights`): input x gradient at the logits is the paper's rule, given the
    relevance R_s at its output (as a cotangent R_s / s)."""
    x = jnp.asarray(SOFTMAX_X)
    s = np.asarray([1, 2, 5]) / 8
    _, (r_x,) = relevance(lambda v: siglip.attention_weights(v, jnp.float32), x, cotangent=jnp.asarray(SOFTMAX_R_S / s))
    np.testing.assert_allclose(r_x, SOFTMAX_R_X, atol=1e-6)


def test_gemma_attention_applies_the_uniform_and_softmax_rules():
    """One query attending over three keys through `gemma.attend` with the rules' operands (q = 1, keys = the
    logits, values = w): v carries R_s, each key half its logit's R_x (q k^T is bilinear), q the other halves; the
    rest of the output, sum R_s - sum R_x, is what the softmax absorbs."""
    q = jnp.ones((1, 1, 1, 1, 1))
    k = jnp.asarray(SOFTMAX_X).reshape(1, 3, 1, 1)
    v = jnp.asarray(SOFTMAX_W).reshape(1, 3, 1, 1)
    mask = jnp.ones((1, 1, 3), bool)

    def attention(q, k, v):
        return gemma.attend(*lrp.attention_operands(q, k, v, "lrp"), mask, 0)

    out, (r_q, r_k, r_v) = relevance(attention, q, k, v)
    assert float(out.squeeze()) == pytest.approx(5.5, rel=1e-6)
    np.testing.assert_allclose(r_v.ravel(), SOFTMAX_R_S, atol=1e-6)
    np.testing.assert_allclose(r_k.ravel(), np.asarray(SOFTMAX_R_X) / 2, atol=1e-6)
    assert float(r_q.sum()) == pytest.approx(sum(SOFTMAX_R_X) / 2, abs=1e-6)
    absorbed = sum(SOFTMAX_R_S) - sum(SOFTMAX_R_X)
    assert r_q.sum() + r_k.sum() + r_v.sum() + absorbed == pytest.approx(5.5, abs=1e-5)


def test_a_log_probability_score_gets_the_softmax_rule_and_absorbs_the_entropy():
    """pi0-FAST's `chunk` score (`pi0_fast_maps._scores_of` over a weights target), one step with the tied projection
    the identity, so the logits are z = (0, ln 2, ln 5) and p = (1, 2, 5) / 8, explaining token 2: the logits get
    z_i (1[i = 2] - p_i) = (0, -ln 2 / 4, 3 ln 5 / 8), which sums to log p_2 + H(p); the bias takes -H(p)."""
    from openpi_cam.model import pi0_fast_maps

    params = {"PaliGemma": {"llm": {"embedder": {"input_embedding": jnp.eye(3)}}}}
    generated = jnp.asarray([[2]])
    target = pi0_fast_maps._weights_target(np.ones((1, 1), np.float32))
    pre = jnp.asarray(SOFTMAX_X).reshape(1, 1, 3)
    score, (r_z,) = relevance(lambda z: pi0_fast_maps._scores_of(params, z, generated, target)[0, 0], pre)
    p = np.asarray([1, 2, 5]) / 8
    assert float(score) == pytest.approx(math.log(5 / 8), abs=1e-6)
    np.testing.assert_allclose(r_z.ravel(), [0.0, -math.log(2.0) / 4, 3 * math.log(5.0) / 8], atol=1e-6)
    entropy = -float(np.sum(p * np.log(p)))
    assert r_z.sum() == pytest.approx(math.log(5 / 8) + entropy, abs=1e-6)


def test_norms_hold_their_normaliser_constant():
    """RMSNorm passes relevance unchanged element by element; LayerNorm's centring keeps its (linear) gradient, so its
    inputs carry what its output carries less its bias's share; pi0.5's adaptive norm treats its time modulation as a
    constant (no gradient reaches the condition) and its shift as a bias."""
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(2, 3, 8)), jnp.float32)
    g_y = jnp.asarray(rng.normal(size=(2, 3, 8)), jnp.float32)
    scale = jnp.asarray(rng.normal(size=8), jnp.float32)
    y, (r_x,) = relevance(lambda v: gemma.rms_norm(v, scale, "lrp"), x, cotangent=g_y)
    np.testing.assert_allclose(r_x, np.asarray(y, np.float64) * np.asarray(g_y), rtol=1e-5, atol=1e-6)
    _, (plain,) = relevance(lambda v: gemma.rms_norm(v, scale), x, cotangent=g_y)
    assert not np.allclose(plain, r_x, atol=1e-3)

    ln = {"scale": jnp.asarray(rng.normal(size=8), jnp.float32), "bias": jnp.asarray(rng.normal(size=8), jnp.float32)}
    y, (r_x,) = relevance(lambda v: siglip.layer_norm(v, ln, jnp.float32, "lrp"), x, cotangent=g_y)
    carried = (np.asarray(y, np.float64) - np.asarray(ln["bias"])) * np.asarray(g_y)
    np.testing.assert_allclose(r_x.sum(-1), carried.sum(-1), rtol=1e-5, atol=1e-5)

    ada = {"Dense_0": {"kernel": jnp.asarray(rng.normal(size=(4, 24)), jnp.float32), "bias": jnp.zeros(24)}}
    cond = jnp.asarray(rng.normal(size=(2, 4)), jnp.float32)

    def adaptive(v, c):
        normed, gate = pi0._norm(v, ada, c, "lrp")
        return normed * gate

    out, vjp_fn = jax.vjp(adaptive, x, cond)
    g_x, g_cond = vjp_fn(g_y)
    assert not np.any(np.asarray(g_cond))
    shift = np.split(np.asarray(cond @ ada["Dense_0"]["kernel"], np.float64), 3, axis=-1)[1][:, None, :]
    gate = np.split(np.asarray(cond @ ada["Dense_0"]["kernel"], np.float64), 3, axis=-1)[2][:, None, :]
    r_x = np.asarray(x, np.float64) * np.asarray(g_x, np.float64)
    r_out = np.asarray(out, np.float64) * np.asarray(g_y, np.float64)
    np.testing.assert_allclose(r_x.sum(-1) + (shift * gate * np.asarray(g_y)).sum(-1), r_out.sum(-1), atol=1e-5)


def _mlp_params(rng, width, hidden):
    return {
        "gating_einsum": jnp.asarray(rng.normal(size=(2, width, hidden)) / math.sqrt(width), jnp.float32),
        "linear": jnp.asarray(rng.normal(size=(hidden, width)) / math.sqrt(hidden), jnp.float32),
    }


def test_a_bias_free_two_layer_network_conserves_relevance():
    """linear -> RMSNorm -> gated-GELU MLP (Gemma's) -> linear, no bias: the inputs' relevance sums to the score."""
    rng = np.random.default_rng(1)
    w1 = jnp.asarray(rng.normal(size=(8, 8)) / math.sqrt(8), jnp.float32)
    w2 = jnp.asarray(rng.normal(size=(8, 3)) / math.sqrt(8), jnp.float32)
    scale = jnp.asarray(rng.normal(size=8) * 0.3, jnp.float32)
    mlp = _mlp_params(rng, 8, 16)
    weights = jnp.asarray(rng.normal(size=(2, 5, 3)), jnp.float32)

    def network(x, rules):
        h = gemma.rms_norm(x @ w1, scale, rules)
        return jnp.sum(weights * (gemma.feed_forward(h, mlp, rules) @ w2))

    x = jnp.asarray(rng.normal(size=(2, 5, 8)), jnp.float32)
    score, (r_x,) = relevance(lambda v: network(v, "lrp"), x)
    assert r_x.sum() == pytest.approx(float(score), abs=REL * np.abs(r_x).max())
    # The plain gradient (input x gradient) does not conserve here: the rules are what makes the sum hold.
    _, (plain,) = relevance(lambda v: network(v, "gradient"), x)
    assert abs(plain.sum() - float(score)) > 100 * REL * np.abs(r_x).max()


def test_a_one_head_attention_block_conserves_relevance_up_to_its_softmax():
    """x -> q, k, v (bias-free) -> Gemma's attention with the rules' operands -> output projection: the inputs'
    relevance plus what the softmax absorbs (sum R_s - sum R_x over its rows, from the paper's formula, here in
    float64 from the block's own weights) equals the score."""
    rng = np.random.default_rng(2)
    t, d, h = 5, 8, 4
    wq, wk, wv = (jnp.asarray(rng.normal(size=(d, h)) / math.sqrt(d), jnp.float32) for _ in range(3))
    wo = jnp.asarray(rng.normal(size=(h, d)) / math.sqrt(h), jnp.float32)
    weights = jnp.asarray(rng.normal(size=(1, t, d)), jnp.float32)
    mask = jnp.asarray(np.tril(np.ones((t, t), bool))[None])

    def block(x):
        q, k, v = (x @ wq) * h**-0.5, x @ wk, x @ wv
        q, k, v = lrp.attention_operands(q[:, :, None, None], k[:, :, None], v[:, :, None], "lrp")
        return jnp.sum(weights * (gemma.attend(q, k, v, mask, 0)[:, :, 0, 0] @ wo))

    x = jnp.asarray(rng.normal(size=(1, t, d)), jnp.float32)
    score, (r_x,) = relevance(block, x)
    x64, w64 = np.asarray(x, np.float64)[0], np.asarray(weights, np.float64)[0]
    q, k, v = (x64 @ np.asarray(wq)) * h**-0.5, x64 @ np.asarray(wk), x64 @ np.asarray(wv)
    logits = np.where(mask[0], q @ k.T, -np.inf)
    s = np.exp(logits - logits.max(-1, keepdims=True))
    s /= s.sum(-1, keepdims=True)
    g_s = 0.5 * (w64 @ np.asarray(wo, np.float64).T) @ v.T  # the weights' half of the output's relevance, per s
    r_s = s * g_s
    r_logits = np.where(mask[0], q @ k.T, 0.0) * (r_s - s * r_s.sum(-1, keepdims=True))
    absorbed = r_s.sum() - r_logits.sum()
    assert abs(absorbed) > 0.05 * abs(float(score))  # the softmax's share is not negligible here
    assert r_x.sum() + absorbed == pytest.approx(float(score), abs=REL * max(np.abs(r_x).max(), 1.0))
