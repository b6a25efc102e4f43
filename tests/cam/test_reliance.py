"""Camera and prompt reliance (`cam.reliance`): the explained score's drop and the action chunk's change with a
camera replaced by the baseline frame, and with the prompt emptied, against a direct re-run of the model on the
intervened input, for both demo families; stored by the side channel and read back by `stats`."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from cam_support import demo_obs, policy_part

from openpi_cam import cli
from openpi_cam.cam.batching import explain_batch
from openpi_cam.cam.reliance import EMPTY_PROMPT, reliance, without_camera
from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.vocabulary import ExplainOptions, MapOptions

# The score drops are differences of two float32 scores of magnitude 5-20 computed by different programs (the
# re-scoring program vs the gradient-map program or the sampler): measured within 8e-6 of each other.
SCORE_ATOL = 5e-5
OPTIONS = ExplainOptions(maps=("gradnorm",), check_patches=0)


def _direct_score(policy, trace, observation) -> float:
    """The explained score of the traced call's own output when the model sees `observation` instead, computed
    without `Explainer.rescore`: pi0-FAST, the maps' forward pass over the same generated tokens; pi0.5, the chunk
    re-sampled from the same noise, weighted by the served chunk (the `chunk` target's fixed weighting)."""
    drawn = {k: np.asarray(v)[None] for k, v in trace.sample_inputs.items()}
    if policy.model.family == "pi0_fast":
        (explanation,) = policy.explainer.explain(observation, np.asarray(trace.output)[None], OPTIONS, drawn)
        return float(explanation.score)
    x = policy.model.sample_actions(jax.random.key(0), observation, noise=drawn["noise"])
    return float((np.asarray(x, np.float64)[0] * np.asarray(trace.output, np.float64)).sum())


@pytest.mark.parametrize("family", ["pi0_fast", "pi05"])
def test_reliance_equals_the_change_a_direct_rerun_measures(family, demo_policy, demo_pi05_policy):
    policy = demo_policy if family == "pi0_fast" else demo_pi05_policy
    for seed in (3, 4):
        obs = policy_part(demo_obs(seed))
        response, trace = policy.infer_traced(obs)
        # the re-runs start from the served call itself: its actions, its tokens
        np.testing.assert_array_equal(policy.resample(trace, trace.observation), response["actions"])
        np.testing.assert_array_equal(policy.served_actions(trace), response["actions"])
        same = policy.with_prompt(trace, trace.prompt)
        for field in ("state", "tokenized_prompt", "tokenized_prompt_mask"):
            np.testing.assert_array_equal(
                np.asarray(getattr(same, field)), np.asarray(getattr(trace.observation, field))
            )
        (explained,) = explain_batch(policy.explainer, [trace], OPTIONS, [seed])
        measured = reliance(policy, policy.explainer, trace, explained.result, MapOptions())
        score = _direct_score(policy, trace, trace.observation)
        assert measured.score == pytest.approx(score, abs=SCORE_ATOL)
        valid = [c for c, info in explained.result.cameras.items() if info["valid"]]
        assert list(measured.cameras) == valid  # pi0.5's masked blank camera has none
        for camera in valid:
            replaced = without_camera(trace.observation, camera, MapOptions())
            drop = score - _direct_score(policy, trace, replaced)
            assert measured.cameras[camera].score_drop == pytest.approx(drop, abs=SCORE_ATOL)
        emptied = policy.with_prompt(trace, EMPTY_PROMPT)
        drop = score - _direct_score(policy, trace, emptied)
        assert measured.prompt.score_drop == pytest.approx(drop, abs=SCORE_ATOL)
        # the prompt's action change is what serving the request with an empty prompt returns, the same noise drawn
        served = policy.infer({**obs, "prompt": EMPTY_PROMPT}, noise=trace.sample_inputs.get("noise"))["actions"]
        change = np.sqrt(np.mean((np.asarray(served, np.float64) - response["actions"]) ** 2))
        assert measured.prompt.action_change == change


def test_explain_batch_measures_reliance_only_with_the_policy_that_served(demo_policy):
    _, trace = demo_policy.infer_traced(policy_part(demo_obs(5)))
    options = ExplainOptions(maps=("gradnorm",), check_patches=0, reliance=True)
    with pytest.raises(ValueError, match="pass the policy that served"):
        explain_batch(demo_policy.explainer, [trace], options, [0])
    (explained,) = explain_batch(demo_policy.explainer, [trace], options, [0], policy=demo_policy)
    assert set(explained.reliance.cameras) == {"base_0_rgb", "wrist_0_rgb"} and explained.reliance.prompt is not None
    (plain,) = explain_batch(demo_policy.explainer, [trace], OPTIONS, [0], policy=demo_policy)
    assert plain.reliance is None


def test_the_side_channel_stores_reliance_per_step_and_stats_reads_it(tmp_path, demo_policy, capsys):
    options = CAMOptions(every_k=1, dir=tmp_path, save_frames="none", maps=("gradnorm",), reliance=True)
    wrapped = wrap_policy_with_cam(demo_policy, options)
    observations = [policy_part(demo_obs(seed)) for seed in (6, 7)]
    for obs in observations:
        wrapped.infer(obs)
    wrapped.close()
    run = load_run(wrapped.run_dir)
    assert run.run_info["options"]["reliance"] is True
    for obs, step in zip(observations, run.steps, strict=True):
        _, trace = demo_policy.infer_traced(obs)
        (explained,) = explain_batch(demo_policy.explainer, [trace], OPTIONS, [0])
        expected = reliance(demo_policy, demo_policy.explainer, trace, explained.result, MapOptions())
        assert step.meta.reliance.figures() == pytest.approx(expected.figures())
    out = tmp_path / "stats.json"
    cli.main(["stats", str(wrapped.run_dir), "--format", "json", "--out", str(out), "--kind", "gradnorm"])
    data = json.loads(out.read_text())
    for row, step in zip(data["steps"], run.steps, strict=True):
        assert row["prompt/reliance_score"] == pytest.approx(step.meta.reliance.prompt.score_drop)
        assert row["base_0_rgb/reliance_actions"] == pytest.approx(
            step.meta.reliance.cameras["base_0_rgb"].action_change
        )
    assert set(data["summary"]["mean_reliance"]) >= {"base_0_rgb/reliance_score", "prompt/reliance_actions"}
