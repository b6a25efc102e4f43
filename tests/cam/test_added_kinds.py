"""The kinds added beside the four compared ones (gradxinput, taylor, smoothgrad, rise) through everything a kind goes
through: the side channel's step files and spot check, the faithfulness report, render and stats (pi0-FAST demo
model), a maps dataset and its refusal to resume with other options (pi0.5 demo model), and the options' record.

Short runs: two served requests, one episode; few SmoothGrad samples and RISE masks (the options under test are
recorded, whatever their values).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from cam_support import demo_obs, policy_part
from paths import LEROBOT_DIR

from openpi_cam import cli
from openpi_cam.cam.faithfulness_run import FaithfulnessOptions, evaluate_run
from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import DatasetJob, dataset_keys, run_local
from openpi_cam.viz.render import RenderOptions, render_run
from openpi_cam.vocabulary import MAP_KIND_INFO, ExplainOptions, MapOptions

ADDED = ("gradxinput", "taylor", "smoothgrad", "rise")
OPTIONS = MapOptions(smoothgrad_samples=3, smoothgrad_sigma=0.4, rise_masks=16, rise_keep_prob=0.6, seed=2)
DEMO_CAMERAS = ("base_0_rgb", "wrist_0_rgb")


def test_each_added_kind_through_the_side_channel_spot_check_faithfulness_render_and_stats(tmp_path, demo_policy):
    """Two served pi0-FAST requests explained with the added kinds: each step file holds every kind's maps under its
    prefix, equal to the explainer's own maps of that call; the step records the options; the spot check paints each
    kind's top patch; the faithfulness report, render and stats take each kind."""
    options = CAMOptions(
        every_k=1, dir=tmp_path / "cam", save_frames="both", maps=ADDED, map_options=OPTIONS, check_patches=2
    )
    wrapped = wrap_policy_with_cam(demo_policy, options, run_config={"config": "demo_reach"}, checkpoint="demo")
    observations = [policy_part(demo_obs(300 + i)) for i in range(2)]
    try:
        for obs in observations:
            wrapped.infer(obs)
    finally:
        wrapped.close()
    run = load_run(wrapped.run_dir)
    assert len(run.steps) == 2
    explainer = demo_policy.explainer
    for obs, step in zip(observations, run.steps, strict=True):
        assert step.map_kinds == ADDED
        _, trace = demo_policy.infer_traced(obs)
        [direct] = explainer.explain(
            trace.observation,
            np.asarray(trace.output)[None],
            ExplainOptions(maps=ADDED, map_options=OPTIONS),
            {k: np.asarray(v)[None] for k, v in trace.sample_inputs.items()},
        )
        with np.load(step.file) as npz:
            members = set(npz.files)
        for kind in ADDED:
            for camera in DEMO_CAMERAS:
                assert MAP_KIND_INFO[kind].prefix + camera in members
                logged, want = step.maps_of(kind)[camera], direct.maps[kind][camera]
                np.testing.assert_allclose(logged, want, rtol=0, atol=1e-5 * (np.abs(want).max() + 1e-30))
            assert np.abs(step.maps_of(kind)["base_0_rgb"]).max() > 0
        recorded = step.meta.map_options
        assert {k: recorded[k] for k in ADDED_OPTIONS} == {k: getattr(OPTIONS, k) for k in ADDED_OPTIONS}
        check = step.meta.check
        assert check.skipped is None and set(check.cameras["base_0_rgb"].top_patch_drop) == set(ADDED)

    report = evaluate_run(run, explainer, FaithfulnessOptions(randomize="none"))
    for kind in ADDED:
        entry = report["cameras"]["base_0_rgb"]["kinds"][kind]
        assert entry["deletion_k1"]["n"] == 2 and entry["top1_occlusion"] is not None, (kind, entry)

    out = tmp_path / "render"
    result = render_run(run, out, RenderOptions(map="taylor", videos=False, progress=False))
    assert result.report is not None and result.report.exists()
    stats_out = tmp_path / "stats.json"
    cli.main(["stats", str(run.run_dir), "--format", "json", "--out", str(stats_out), "--kind", "rise"])
    assert len(json.loads(stats_out.read_text())["steps"]) == 2


def test_a_maps_dataset_of_the_added_kinds_refuses_to_resume_with_other_options(tmp_path):
    """pi0.5, one episode: a column per added kind and camera holding every frame's maps; a second job with the same
    options adds nothing, one with another SmoothGrad noise level, sample count or RISE mask count is refused naming
    the option."""
    source = LEROBOT_DIR / "demo_reach_v30_image"
    model = ModelSpec(config="demo_reach_pi05")
    options = ExplainOptions(target="chunk", maps=ADDED, map_options=OPTIONS, check_patches=0)
    policy = model.create()
    out = tmp_path / "pi05.maps"
    keys, nested = dataset_keys(model, {})
    job = DatasetJob(source, out, model, options, keys, nested_keys=nested, episodes=(0,), batch_size=2)
    summary = run_local(job, policy=policy)
    assert summary.episodes_written == 1
    maps = fmt.open_maps_dataset(out)
    assert maps.kinds == list(ADDED)
    for kind in ADDED:
        for camera in maps.cameras:
            stack = maps.maps(kind, camera)
            assert np.isfinite(stack).all() and stack.shape[0] == summary.counts["explained"]
    again = run_local(job, policy=policy)
    assert again.episodes_written == 0 and again.episodes_already_written == 1
    for change in ({"smoothgrad_sigma": 0.5}, {"smoothgrad_samples": 4}, {"rise_masks": 32}, {"rise_keep_prob": 0.5}):
        other = dataclasses.replace(options, map_options=dataclasses.replace(OPTIONS, **change))
        with pytest.raises(ValueError, match=next(iter(change))):
            run_local(dataclasses.replace(job, options=other), policy=policy)


def test_the_added_options_are_recorded_and_read_back():
    """`to_json` records the added kinds' options and `from_json` restores them; what runs recorded before them
    reads as the defaults, so an old run resumes with default options and refuses others."""
    options = ExplainOptions(maps=ADDED, map_options=OPTIONS)
    recorded = json.loads(json.dumps(options.to_json()))
    added = {k: getattr(OPTIONS, k) for k in ADDED_OPTIONS}
    assert ExplainOptions.from_json(recorded).map_options == dataclasses.replace(MapOptions(), **added)
    assert options.mismatch(recorded) == []
    before = {k: v for k, v in ExplainOptions().to_json().items() if k not in ADDED_OPTIONS}
    assert ExplainOptions().mismatch(before) == []
    refused = ExplainOptions(map_options=MapOptions(rise_masks=32)).mismatch(before)
    assert refused == [f"rise_masks: {MapOptions.rise_masks!r} != 32"]


ADDED_OPTIONS = ("smoothgrad_samples", "smoothgrad_sigma", "rise_masks", "rise_keep_prob")
