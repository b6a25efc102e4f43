"""`openpi-cam faithfulness` on runs the side channel wrote: steps rebuilt from their files re-score exactly, the
interventions are the ones the live maps used, and the figures separate a faithful map from a random one.

Runs on the bundled demo policies (pi0-FAST and pi0.5), whose actions depend on the observation (asserted first),
with every map kind logged."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from cam_support import assert_pairwise_different, demo_obs, policy_part
from heads import planted_head

from openpi_cam.cam import faithfulness as fm
from openpi_cam.cam.faithfulness_run import FaithfulnessOptions, evaluate_run, format_report, step_model_inputs
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.offline import Replay, ReplayOptions, explain_replays
from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.policies import demo_reach
from openpi_cam.policies.family import ExplainSkipped
from openpi_cam.viz.render import RenderOptions, render_run
from openpi_cam.viz.stats import compute_stats, to_rows, view_steps
from openpi_cam.vocabulary import MAP_KINDS, OCCLUSION_HEAD, HeadRef, MapOptions

SEEDS = (200, 201, 202, 203)
# Re-running the explained score from the step file: the model frames are exact (uint8 frames through the same
# float conversion), so only XLA's fusion order differs from the live call. Measured: <= 3e-6 on scores of
# magnitude 1-10 (pi0-FAST chunk log-probs, pi0.5 actions); 1e-4 absolute is 10x above that at the largest score.
REPLAY_ATOL = 1e-4
# Random patch orders of the deletion reference on the demo run (the command's default is 8): one painted-variant
# count, so the one-process reports and the commands share their re-scoring program.
RANDOM_ORDERS = 4


def _head(tmp_path, family: str, target: str) -> HeadRef:
    """A planted occlusion head (the gradient norm, normalised) for the bundled model of `family`."""
    return planted_head(tmp_path / "occlusion_head.json", model_spec.ModelSpec.demo(family), target)


def _logged_run(tmp_path, policy, target, save_frames="model", seeds=SEEDS, maps=MAP_KINDS, **request):
    observations = [demo_obs(s) for s in seeds]
    actions = [policy.infer(policy_part(o))["actions"] for o in observations]
    assert_pairwise_different(actions)  # the steps are distinct inferences, so a mixed-up replay would show
    family = "pi05" if policy.explainer.targets == ("action", "chunk") else "pi0_fast"
    if OCCLUSION_HEAD in maps:
        request.setdefault("occlusion_head", _head(tmp_path, family, target))
    options = CAMOptions(
        every_k=1, dir=tmp_path, save_frames=save_frames, target=target, maps=maps, queue_size=16, **request
    )
    wrapped = wrap_policy_with_cam(policy, options, run_config={"config": demo_reach.DEMO_CONFIGS[family].name})
    try:
        for obs in observations:
            wrapped.infer(obs)
    finally:
        # Every queued step must be explained: the drain's deadline is not under test here, and compiling the four
        # map kinds on a loaded machine can outlast the default one.
        wrapped.close(300)
    return load_run(wrapped.run_dir)


@pytest.fixture(scope="module")
def chunk_run(tmp_path_factory, demo_policy):
    """The demo (pi0-FAST) run most tests read: chunk target, every kind, model frames. Logged once: the tests only
    read it (the faithfulness command, which writes its report into the run, gets a copy)."""
    return _logged_run(tmp_path_factory.mktemp("chunk_run"), demo_policy, "chunk")


@pytest.mark.parametrize("family", ["pi0_fast", pytest.param("pi05", marks=pytest.mark.slow)])
def test_steps_rescore_exactly_and_occlusion_is_its_own_optimum(request, tmp_path, family):
    if family == "pi0_fast":
        policy, run = request.getfixturevalue("demo_policy"), request.getfixturevalue("chunk_run")
    else:
        policy = request.getfixturevalue("demo_pi05_policy")
        run = _logged_run(tmp_path, policy, "action", action_index=3, action_dim_index=1)
    assert len(run.steps) == len(SEEDS) and all(set(s.map_kinds) == set(MAP_KINDS) for s in run.steps)
    # One step per call of the randomised model: the programs the side channel compiled for the logged steps (batch
    # 1) serve it too (batched calls are the two-device test's). pi0.5 re-runs its whole denoising loop per painted
    # variant, so its deletion curves stop at k = 4, the deepest depth reported (AUC is not checked here).
    max_k = 4 if family == "pi05" else 16
    opts = FaithfulnessOptions(randomize="llm", random_orders=RANDOM_ORDERS, batch_size=1, max_k=max_k)
    report = evaluate_run(run, policy.explainer, opts)
    # JSON data as it is saved: a figure that was not measured is None, never NaN (which JSON lacks).
    json.dumps(report, allow_nan=False)

    assert report["steps_evaluated"] == len(SEEDS) and not report["skipped"]
    assert report["score_replay_max_abs_diff"] < REPLAY_ATOL
    ig = report["ig_completeness"]  # from the steps' stored checks (MapOptions.ig_tolerance: 2%)
    assert ig["steps"] == len(SEEDS) and ig["max_relative_error"] <= 0.02
    valid = run.steps[0].meta.valid_cameras()
    assert set(report["cameras"]) == set(valid)
    for camera, cam in report["cameras"].items():
        kinds = cam["kinds"]
        assert set(kinds) == {*MAP_KINDS, "random"}
        # The logged occlusion map is the single-patch drop of the same painting, so its top patch *is* the optimum:
        # exactly 1 at k = 1 in every step. A replay of other inputs, another camera's masks or another baseline
        # would break the equality.
        occlusion_k1 = kinds["occlusion"]["deletion_k1"]
        assert occlusion_k1["n"] == cam["steps_with_positive_optimum"] > 0
        assert occlusion_k1["median"] == pytest.approx(1.0, abs=1e-4)
        assert occlusion_k1["mean"] == pytest.approx(1.0, abs=1e-4)
        assert kinds["occlusion"]["top1_occlusion"]["mean"] == 1.0
        # A random order's first patch is (on average) far from the optimum on these 4 x 4 grids.
        assert kinds["random"]["deletion_k1"]["median"] < 0.5, camera
        for kind in MAP_KINDS:
            rand = kinds[kind].get("randomisation_abs_spearman")
            assert rand is not None and rand["n"] >= 2, (camera, kind)  # the re-initialised model's maps vary
    text = format_report(report)
    assert "occlusion | 1.00" in text
    _assert_step_figures_are_each_steps_own(run, report, policy)


def _assert_step_figures_are_each_steps_own(run, report, policy) -> None:
    """The per-step figures `render` shows beside a step's maps (report["steps"]) belong to that step: painting that
    step's own top gradient-norm patch, re-scored here independently, drops its score by the stated fraction of the
    best single patch's drop, where the best drop is its logged occlusion map's maximum. The steps' figures differ
    (asserted), so figures filed under the wrong step or camera would not match."""
    assert set(report["steps"]) == {str(s.seq) for s in run.steps}
    seen = []
    for step in run.steps:
        obs, outputs, sample_inputs = step_model_inputs(step)
        painting = MapOptions(**step.meta.map_options)
        figures = report["steps"][str(step.seq)]
        masks = {}
        for c in figures:
            gradnorm = step.maps_of("gradnorm")[c]
            masks[c] = fm.top_k_masks(fm.patch_order(gradnorm), gradnorm.shape)[:2]  # nothing painted, top patch
        scores = policy.explainer.rescore(obs, outputs, sample_inputs, step.meta.explained(), masks, painting)
        for c, f in figures.items():
            occlusion = step.maps_of("occlusion")[c]
            # As in the offline occlusion test: drops round at 1e-5 |score|; the optimum is the logged map's maximum.
            atol = 1e-5 * max(abs(float(scores[c][0])), 1.0)
            assert f["optimum"] == pytest.approx(float(occlusion.max()), abs=atol)
            if f["optimum"] <= 10 * atol:
                continue  # no patch lowers this score beyond rounding: its fractions are not meaningful
            assert f["deletion_k1"]["occlusion"] == pytest.approx(1.0, abs=atol / f["optimum"])
            assert f["top1_occlusion"]["occlusion"] is True
            drop = float(scores[c][0] - scores[c][1])
            assert f["deletion_k1"]["gradnorm"] == pytest.approx(drop / f["optimum"], abs=2 * atol / f["optimum"])
            seen.append(f["deletion_k1"]["gradnorm"])
    assert len(seen) >= 2 and len(set(np.round(seen, 3))) > 1, seen


@pytest.mark.slow
def test_logged_occlusion_maps_equal_the_single_patch_drops_rescored_offline(tmp_path, demo_policy):
    """The live side channel's occlusion map and the offline re-scoring of one patch at a time agree value by value:
    the step file holds everything the explained score depends on."""
    # Only the kind under test: the other kinds' programs for this target would be compiled for nothing.
    run = _logged_run(tmp_path, demo_policy, "action-token", maps=("occlusion",), action_index=1)
    for step in run.steps:
        obs, outputs, sample_inputs = step_model_inputs(step)
        cameras = list(step.meta.cameras)
        grid = step.maps_of("occlusion")[cameras[0]].shape
        masks = dict.fromkeys(cameras, fm.single_patch_masks(grid))
        painting = MapOptions(**step.meta.map_options)
        scores = demo_policy.explainer.rescore(obs, outputs, sample_inputs, step.meta.explained(), masks, painting)
        for c in cameras:
            drops = (scores[c][0] - scores[c][1:]).reshape(grid)
            logged = step.maps_of("occlusion")[c]
            # A drop is the difference of two float32 scores of magnitude |s| (a logit); the live program and this one
            # batch the variants differently, so each score may round differently. Measured: <= 5.7e-6 at |s| ~ 3-12;
            # 1e-5 |s| bounds that and stays far below the drops the map ranks (1e-3 - 3e-2 here).
            atol = 1e-5 * max(abs(float(scores[c][0])), 1.0)
            np.testing.assert_allclose(logged, drops, rtol=0, atol=atol)
        assert abs(scores[cameras[0]][0] - step.meta.score) < REPLAY_ATOL


def test_ig_completeness_is_stored_per_step_and_holds(chunk_run):
    run = chunk_run
    for step in run.steps:
        check = step.meta.ig_completeness
        total = sum(float(np.sum(m)) for m in step.maps_of("ig").values())
        # The stored attribution sum is the logged ig maps' sum (float32 maps summed in float64: 1e-5 relative).
        assert total == pytest.approx(check["attribution_sum"], rel=1e-5, abs=1e-6)
        gap = check["score"] - check["baseline_score"]
        assert abs(check["attribution_sum"] - gap) <= 0.02 * max(abs(gap), 1e-3)  # MapOptions.ig_tolerance
        assert check["score"] == pytest.approx(step.meta.score, abs=REPLAY_ATOL)
        assert step.meta.map_options["baseline"] == "mean"


def test_steps_without_model_frames_are_reported_not_replayable(tmp_path, demo_policy):
    seeds = SEEDS[:2]  # every step is refused alike: two show it is counted per step
    run = _logged_run(tmp_path, demo_policy, "chunk", save_frames="raw", seeds=seeds)
    with pytest.raises(ExplainSkipped, match="frame"):
        step_model_inputs(run.steps[0])
    report = evaluate_run(run, demo_policy.explainer, FaithfulnessOptions(randomize="none"))
    assert report["steps_evaluated"] == 0 and report["skipped"] == {"not_replayable": len(seeds)}


def test_faithfulness_command_on_a_demo_run(tmp_path, chunk_run):
    """The CLI finds the bundled model from the run's config, prints the table and saves the JSON report beside the
    run, where `render` finds it: the rendered report then shows each step's own figure beside its maps."""
    run = load_run(shutil.copytree(chunk_run.run_dir, tmp_path / "cam" / chunk_run.run_dir.name))
    cmd = [sys.executable, "-m", "openpi_cam", "faithfulness", str(run.run_dir), "--random-orders", str(RANDOM_ORDERS)]
    done = subprocess.run([*cmd, "--randomize", "none", "--no-progress"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "camera base_0_rgb" in done.stdout and "occlusion | 1.00" in done.stdout
    report = json.loads((run.run_dir / "faithfulness.json").read_text())
    assert report["steps_evaluated"] == len(SEEDS) and report["run_id"] == run.run_dir.name
    rendered = render_run(load_run(run.run_dir), tmp_path / "render", RenderOptions(videos=False, progress=False))
    doc = rendered.report.read_text()
    assert 'data-status="measured"' in doc
    for step in run.steps:
        f = report["steps"][str(step.seq)]["base_0_rgb"]["deletion_k1"]
        section = doc[doc.index(f'id="step-{step.seq}"') :]
        cell = section[section.index('<td class="evidence">') :].split(">", 1)[1].split("<", 1)[0]
        assert (
            cell == f"{f['occlusion']:.2f} of best (random {f['random']:.2f})"
        )  # the drawn kind (the run's most trusted)
    bad = subprocess.run(
        [sys.executable, "-m", "openpi_cam", "faithfulness", str(tmp_path / "missing")], capture_output=True, text=True
    )
    assert bad.returncode == 1 and "openpi-cam faithfulness" in bad.stderr


def test_nuisance_mass_ratio_in_stats_uses_the_clients_box(chunk_run):
    """`openpi-cam stats` reports the share of each map's positive mass outside the box the client sent, on the
    camera the box belongs to (the first one) only. Expected value by hand: the demo's 64 px frames are not
    letterboxed, so patch (r, c) covers pixels [16 r, 16 r + 16) x [16 c, 16 c + 16)."""
    run = chunk_run
    rows = to_rows(compute_stats(view_steps(run.steps, "gradnorm")))
    seen = []
    for step, row in zip(run.steps, rows, strict=True):
        x0, y0, x1, y1 = step.extra["target_box"]
        edges = np.arange(4) * 16
        inside = ((edges < y1) & (edges + 16 > y0))[:, None] & ((edges < x1) & (edges + 16 > x0))[None, :]
        m = np.maximum(step.maps_of("gradnorm")["base_0_rgb"].astype(np.float64), 0)
        expected = 1.0 - m[inside].sum() / m.sum()
        assert row["base_0_rgb/nuisance_mass"] == pytest.approx(expected, abs=1e-12)
        assert row["wrist_0_rgb/nuisance_mass"] is None  # no box for the wrist view
        seen.append(expected)
    assert max(seen) > min(seen)  # different scenes, different ratios


@pytest.mark.slow
def test_offline_explain_render_stats_and_faithfulness_on_a_pi05_run(tmp_path, demo_pi05_policy):
    """The run tools know no family: a pi0.5 policy explained offline (action target, all four kinds) gives a run that
    renders, has statistics and re-scores exactly, with maps of the very chunks the replays returned."""
    observations = [demo_obs(s) for s in SEEDS[:3]]
    replays = [
        Replay(f"obs{i}", "offline", i, policy_part(o), {"target_box": o["cam_extra/target_box"].tolist()})
        for i, o in enumerate(observations)
    ]
    # The live pi0.5 test's target, so that the re-scoring below reuses that test's program.
    head = _head(tmp_path, "pi05", "action")
    options = ReplayOptions(
        target="action", action_index=3, action_dim_index=1, maps=MAP_KINDS, batch_size=2, occlusion_head=head
    )
    with CAMLogger(tmp_path / "cam", run_config={"config": "demo_reach_pi05"}, checkpoint="demo", options={}) as log:
        summary = explain_replays(demo_pi05_policy, replays, options, log, mesh=None)
    assert summary["completed"] == 3
    run = load_run(log.run_dir)
    for step in run.steps:
        assert step.meta.action_index == (3, 1) and set(step.map_kinds) == set(MAP_KINDS)
        # the explained chunk is the returned one (float32 re-run)
        assert step.meta.details["replay_max_abs_diff"] < 1e-4
    result = render_run(run, tmp_path / "render", RenderOptions(map="ig", videos=False, progress=False))
    assert result.report is not None and "nuisance mass ratio" in result.report.read_text()
    rows = to_rows(compute_stats(view_steps(run.steps, "occlusion")))
    assert [r["seq"] for r in rows] == [0, 1, 2] and all(r["base_0_rgb/nuisance_mass"] is not None for r in rows)
    # Depth 4 is the deepest k reported; pi0.5 re-runs its whole denoising loop per painted variant.
    opts = FaithfulnessOptions(randomize="none", random_orders=RANDOM_ORDERS, max_k=4)
    report = evaluate_run(run, demo_pi05_policy.explainer, opts)
    assert report["steps_evaluated"] == 3 and report["score_replay_max_abs_diff"] < REPLAY_ATOL
    occlusion = report["cameras"]["base_0_rgb"]["kinds"]["occlusion"]["deletion_k1"]
    assert occlusion["median"] == pytest.approx(1.0, abs=1e-4)


@pytest.mark.slow
def test_faithfulness_over_two_host_devices_matches_one_device(tmp_path, demo_policy, chunk_run):
    """The report's work spread over two devices (painted variants split between them, the randomised model's steps
    sharded in calls of 3 rows padded to 4) gives the one-device figures: the devices only share the work."""
    run = chunk_run
    # The one-device reference explains one step per call (the batch-1 programs the side channel compiled; rows are
    # independent, so the batch does not change a figure) with the command's painted variants (same random orders).
    opts = FaithfulnessOptions(randomize="llm", random_orders=RANDOM_ORDERS, batch_size=1)
    one = evaluate_run(run, demo_policy.explainer, opts, mesh=None)
    out = tmp_path / "two.json"
    env = os.environ | {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "openpi_cam", "faithfulness", str(run.run_dir), "--json-out", str(out)]
    cmd += ["--random-orders", str(RANDOM_ORDERS)]
    done = subprocess.run(
        [*cmd, "--batch-size", "3", "--no-progress"], capture_output=True, text=True, timeout=900, env=env
    )
    assert done.returncode == 0, done.stderr[-3000:]
    two = json.loads(out.read_text())
    assert (one["devices"], two["devices"]) == (1, 2)
    assert one["steps_evaluated"] == two["steps_evaluated"] == len(SEEDS)
    compared = 0
    for camera, cam in one["cameras"].items():
        for kind, entry in cam["kinds"].items():
            for name, summary in entry.items():
                if isinstance(summary, dict) and summary.get("mean") is not None:
                    other = two["cameras"][camera]["kinds"][kind][name]
                    # Measured: equal (0 difference in all 84 figures); allowed 1e-3 (ratios and correlations of
                    # order 1: XLA may fuse a sharded program differently), far below what one wrong patch or one
                    # wrong step's map moves them.
                    assert other["mean"] == pytest.approx(summary["mean"], abs=1e-3), (camera, kind, name)
                    compared += 1
    assert compared > 20
