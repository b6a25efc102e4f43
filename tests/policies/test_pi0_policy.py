"""pi0 / pi0.5 policies end to end against upstream's `create_trained_policy` + `Policy.infer(obs, noise=...)`:
raw client observation -> model inputs -> actions, for `pi05_droid` and `pi0_libero` (the goldens in
`../shared/golden/tiny_policy_*`), plus the noise stream, the noise check and the family check.

Tolerance: actions within REL of their largest magnitude (`golden.FLOW_REL`, the golden criterion of pi0's values,
where the reasoning is). Model inputs (tokens, masks) exactly; images to float32 rounding of the uint8 -> [-1, 1]
map.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.errors import InvalidRequest
from openpi_cam.policies.policy import create_policy

REL = golden.FLOW_REL
CASES = {"pi05_droid": "tiny_policy_pi05_droid", "pi0_libero": "tiny_policy_pi0_libero"}


def golden_policy(config: str, **kwargs):
    root = GOLDEN_DIR / CASES[config]
    return create_policy(
        config,
        root / "checkpoint",
        paligemma_tokenizer=root / "paligemma_tokenizer_tiny.model",
        dtype="float32",
        **kwargs,
    )


def raw_observation(config: str, case: str) -> tuple[dict, dict]:
    root = GOLDEN_DIR / CASES[config]
    with np.load(root / f"{case}.npz") as npz:
        d = {k: npz[k] for k in npz.files}
    prompt = json.loads((root / "case.json").read_text())["cases"][case]["prompt"]
    obs = {"observation/" + k[len("raw/") :]: v for k, v in d.items() if k.startswith("raw/")}
    return {**obs, "prompt": prompt}, d


@pytest.fixture(scope="module", params=list(CASES))
def config_and_policy(request):
    return request.param, golden_policy(request.param)


def test_raw_observation_to_upstreams_model_inputs_and_actions(config_and_policy):
    config, policy = config_and_policy
    results = []
    for case in ("case_1", "case_2"):
        obs, d = raw_observation(config, case)
        response, trace = policy.infer_traced(obs, noise=d["noise"])
        o = trace.observation
        np.testing.assert_array_equal(np.asarray(o.tokenized_prompt)[0], d["model_input/tokenized_prompt"])
        np.testing.assert_array_equal(np.asarray(o.tokenized_prompt_mask)[0], d["model_input/tokenized_prompt_mask"])
        for camera, image in o.images.items():
            want = d[f"model_input/image/{camera}"].astype(np.float32) / 255 * 2 - 1
            np.testing.assert_allclose(np.asarray(image)[0], want, atol=1e-6)
            assert bool(np.asarray(o.image_masks[camera])[0]) == bool(d[f"model_input/image_mask/{camera}"])
        np.testing.assert_allclose(np.asarray(o.state)[0], d["model_input/state"], atol=1e-6)
        np.testing.assert_array_equal(trace.sample_inputs["noise"], d["noise"])
        want = d["model_output/actions"]
        assert (c := golden.compare(config, "model output", trace.output, want, rel=REL)).ok, c.line()
        want = d["policy_output/actions"]
        assert (c := golden.compare(config, "actions", response["actions"], want, rel=REL)).ok, c.line()
        results.append(response["actions"])
    assert np.abs(results[0] - results[1]).max() > 0.1  # the two observations lead to different actions


def test_default_noise_is_upstreams_stream(config_and_policy):
    """Without `noise`, the policy splits its rng once per call and draws the noise as upstream's sample_actions does
    from that key; the trace keeps it, and passing it back reproduces the call."""
    config, _ = config_and_policy
    policy = golden_policy(config, rng=jax.random.key(7))
    obs, _ = raw_observation(config, "case_1")
    response, trace = policy.infer_traced(obs)
    _, split = jax.random.split(jax.random.key(7))
    shape = trace.sample_inputs["noise"].shape
    np.testing.assert_array_equal(trace.sample_inputs["noise"], np.asarray(jax.random.normal(split, (1, *shape)))[0])
    again = golden_policy(config).infer(obs, noise=trace.sample_inputs["noise"])
    np.testing.assert_array_equal(again["actions"], response["actions"])
    second = policy.infer(obs)  # the stream moves on: a new noise, other actions
    assert np.abs(second["actions"] - response["actions"]).max() > 1e-3


def test_bad_noise_and_wrong_family_are_named(config_and_policy):
    config, policy = config_and_policy
    obs, _ = raw_observation(config, "case_1")
    with pytest.raises(InvalidRequest, match=r"noise must have shape \["):
        policy.infer(obs, noise=np.zeros((3, 32), np.float32))
    root = GOLDEN_DIR / CASES[config]
    with pytest.raises(ValueError, match=r"serves pi0_fast, the checkpoint .* is pi0"):
        create_policy(
            "pi0_fast_droid", root / "checkpoint", paligemma_tokenizer=root / "paligemma_tokenizer_tiny.model"
        )
