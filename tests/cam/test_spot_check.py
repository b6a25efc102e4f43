"""The spot check stored with every explained step (`meta.check`, `cam.spot_check`): its drops are the model's own
re-runs of the logged step with the named patches painted, its top patches are the logged maps' peaks in row-major
order, and occlusion's top patch is the best single patch by construction.

Runs the real side channel over the bundled pi0-FAST demo policy, whose actions depend on the observation (asserted
first), so every step is a different inference."""

from __future__ import annotations

import numpy as np
import pytest
from cam_support import assert_pairwise_different, demo_obs, policy_part

from openpi_cam.cam import faithfulness as fm
from openpi_cam.cam.faithfulness_run import step_model_inputs
from openpi_cam.cam.run_format import SpotCheck, load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.cam.spot_check import spot_check_masks
from openpi_cam.vocabulary import MapOptions

SEEDS = (310, 311, 312, 313)
# The logged score against the same score re-run from the step file: float32 fusion order only (measured <= 3e-6 at
# scores of magnitude 1-10, tests/cam/test_faithfulness_run.py).
REPLAY_ATOL = 1e-4


def _run(tmp_path, policy, target="chunk", **options):
    observations = [demo_obs(s) for s in SEEDS]
    assert_pairwise_different([policy.infer(policy_part(o))["actions"] for o in observations])
    opts = CAMOptions(every_k=1, dir=tmp_path, target=target, queue_size=16, **options)
    wrapped = wrap_policy_with_cam(policy, opts, run_config={"config": "demo_reach"})
    try:
        for obs in observations:
            wrapped.infer(obs)
    finally:
        wrapped.close(120)
    run = load_run(wrapped.run_dir)
    assert len(run.steps) == len(SEEDS)
    return run


def test_masks_paint_each_maps_peak_in_row_major_order():
    """On a 2 x 3 grid (not square, so a transposed index lands elsewhere or out of range) a peak at (1, 0) is flat
    index 3; random patches are distinct, never painted twice, and fixed by the seed."""
    hot = np.zeros((2, 3), np.float32)
    hot[1, 0] = 5.0
    signed = -np.ones((2, 3), np.float32)
    signed[0, 2] = -0.5  # all negative: the highest signed value is the peak
    masks, tops, randoms = spot_check_masks({"a": hot, "b": signed}, (2, 3), patches=4, seed=7)
    assert tops == [3, 2] and masks.shape == (1 + 2 + 4, 2, 3)
    assert not masks[0].any() and masks[1, 1, 0] and masks[2, 0, 2]
    assert (masks[1:].reshape(6, -1).sum(axis=1) == 1).all()  # one patch per row
    assert len(set(randoms)) == 4 and all(masks[3 + i].ravel()[r] for i, r in enumerate(randoms))
    assert spot_check_masks({"a": hot}, (2, 3), patches=4, seed=7)[2] == randoms
    assert spot_check_masks({"a": hot}, (2, 3), patches=9, seed=7)[2].__len__() == 6  # at most every patch once


def test_logged_checks_are_the_models_own_rescores(tmp_path, demo_policy):
    run = _run(tmp_path, demo_policy, maps=("gradcam", "gradnorm", "occlusion"), check_patches=4)
    seen = []
    for step in run.steps:
        check = step.meta.check
        assert check.patches == 4 and check.seed == step.meta.step
        obs, outputs, sample_inputs = step_model_inputs(step)
        painting = MapOptions(**step.meta.map_options)
        for camera, c in check.cameras.items():
            grid = np.shape(step.maps_of("gradnorm")[camera])
            n = grid[0] * grid[1]
            for kind in ("gradcam", "gradnorm", "occlusion"):  # the logged maps' peaks, row-major
                assert c.top_patch[kind] == int(np.argmax(fm.reduce_map(step.maps_of(kind)[camera]))), kind
            assert len(set(c.random_patches)) == 4 and all(0 <= i < n for i in c.random_patches)
            # Re-run here, one single patch per row, from the step file alone.
            cells = [c.top_patch[k] for k in ("gradcam", "gradnorm", "occlusion")] + list(c.random_patches)
            masks = np.zeros((1 + len(cells), n), bool)
            masks[np.arange(1, len(masks)), cells] = True
            scores = demo_policy.explainer.rescore(
                obs, outputs, sample_inputs, step.meta.explained(), {camera: masks.reshape(-1, *grid)}, painting
            )[camera]
            drops = scores[0] - scores[1:]
            # Two float32 programs batching the variants differently: 1e-5 |score| (test_faithfulness_run.py).
            atol = 1e-5 * max(abs(float(scores[0])), 1.0)
            assert c.score == pytest.approx(step.meta.score, abs=REPLAY_ATOL)
            logged = [c.top_patch_drop[k] for k in ("gradcam", "gradnorm", "occlusion")] + list(c.random_patch_drops)
            np.testing.assert_allclose(logged, drops, rtol=0, atol=atol)
            # Occlusion's top patch is the best single patch: its drop is the occlusion map's maximum, and no random
            # patch drops the score more.
            occlusion = step.maps_of("occlusion")[camera]
            assert c.top_patch_drop["occlusion"] == pytest.approx(float(occlusion.max()), abs=atol)
            assert max(c.random_patch_drops) <= c.top_patch_drop["occlusion"] + atol
            seen.append(c.top_patch_drop["gradnorm"])
    assert len(set(np.round(seen, 4))) > 1, seen  # the steps differ, so a check filed under another step would show


def test_no_check_when_off_and_a_named_skip_for_multi_score_targets(tmp_path, demo_policy):
    """`check_patches=0` stores no check; a target with one score per token (`all-action-tokens`) cannot be checked
    with one number and says so in every step, which keeps its maps."""
    off = _run(tmp_path / "off", demo_policy, check_patches=0)
    assert all(s.meta.check is None and "check" not in s.meta.to_json() and s.map_kinds for s in off.steps)
    tokens = _run(tmp_path / "tokens", demo_policy, target="all-action-tokens")
    assert all(s.meta.check == SpotCheck(skipped="multi_score_target") and s.map_kinds for s in tokens.steps)
