"""The action-sample spread (`cam.sample_spread`) on the bundled pi0.5: other noises give other chunks of the same
call, the spread is a pure function of the call (its input and served noise), and it flows end to end:
`explain-dataset --sample-spread N` writes it, `monitor fit` fits on it and records N, and explain-dataset and the
live side channel draw N samples a call to score with that monitor. pi0-FAST, which decodes greedily, is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cam_support import demo_obs, policy_part
from one_line import assert_one_line

from openpi_cam import cli
from openpi_cam.auroc import roc_auc
from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.sample_spread import extra_noises, with_sample_spread
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import ModelSpec, create_demo_policy
from openpi_cam.demo.run import ROLLOUT_FPS, DemoOptions, run_demo
from openpi_cam.lerobot.rollouts import RolloutRecorder
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import DatasetJob, dataset_keys, run_local
from openpi_cam.maps.monitoring import read_rollouts
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.signals import SAMPLE_SPREAD
from openpi_cam.policies import demo_reach
from openpi_cam.serving import RequestContext
from openpi_cam.vocabulary import NORMALIZED_CHUNK, ExplainOptions

PI05 = ModelSpec(config="demo_reach_pi05")
OPTIONS = ExplainOptions(target="chunk", maps=("gradnorm",), check_patches=0)
SAMPLES = 3


def model_job(source, out, options, model, **kw) -> DatasetJob:
    keys, nested = dataset_keys(model, {})
    return DatasetJob(source, out, model, options, keys, nested_keys=nested, **kw)


@pytest.fixture(scope="module")
def pi05():
    return create_demo_policy(model="pi05")


@pytest.fixture(scope="module")
def call(pi05):
    """One traced call with its signals, and its served noise."""
    _, trace = pi05.infer_traced(policy_part(demo_obs(11)), signals=True)
    return trace, np.asarray(trace.sample_inputs["noise"])


def _by_hand(chunks: np.ndarray) -> float:
    """The spread written out: per step, the root of the summed unbiased variances over the action dimensions of
    the N samples; then the mean over the steps."""
    n = chunks.shape[0]
    mean = chunks.mean(axis=0)
    variance = ((chunks - mean) ** 2).sum(axis=0) / (n - 1)  # [H, A]
    return float(np.sqrt(variance.sum(axis=-1)).mean())


def test_the_served_noise_gives_the_served_chunk_and_other_noises_other_chunks(pi05, call):
    trace, noise = call
    served = np.asarray(trace.signals[NORMALIZED_CHUNK])
    again, other = pi05.normalized_chunks(trace, np.stack([noise, -noise]))
    assert again.shape == other.shape == served.shape
    # the served program but for its signals: equal up to float32 rounding of chunks whose entries are at most ~1
    np.testing.assert_allclose(again, served, rtol=0, atol=1e-5)
    assert np.abs(other - served).max() > 100 * 1e-5  # another noise, another chunk


def test_the_spread_is_a_pure_function_of_the_call(pi05, call):
    trace, noise = call
    first = with_sample_spread(pi05, trace, SAMPLES)
    assert set(first) == set(trace.signals) | {SAMPLE_SPREAD}
    spread = float(first[SAMPLE_SPREAD])
    assert spread > 0 and float(with_sample_spread(pi05, trace, SAMPLES)[SAMPLE_SPREAD]) == spread
    # the served chunk beside the chunks of the noises its own bytes seed
    extra = extra_noises(noise, SAMPLES)
    assert extra.shape == (SAMPLES - 1, *noise.shape) and not np.allclose(extra[0], noise)
    np.testing.assert_array_equal(extra, extra_noises(noise.copy(), SAMPLES))
    assert not np.array_equal(extra, extra_noises(noise + 1e-3, SAMPLES))
    chunks = np.concatenate([np.asarray(trace.signals[NORMALIZED_CHUNK])[None], pi05.normalized_chunks(trace, extra)])
    assert spread == pytest.approx(_by_hand(chunks), rel=1e-12)


def test_pi0_fast_and_fewer_than_two_samples_are_refused_in_one_line(demo_policy, pi05, call):
    _, fast = demo_policy.infer_traced(policy_part(demo_obs(11)), signals=True)
    with pytest.raises(ValueError) as e:
        with_sample_spread(demo_policy, fast, SAMPLES)
    assert_one_line(e.value, "pi0-FAST decodes greedily")
    with pytest.raises(ValueError) as e:
        with_sample_spread(pi05, call[0], 1)
    assert_one_line(e.value, ">= 2 action samples", "got 1")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The bundled pi0.5's closed loops, clean and with the named block absent (which fail), recorded as lerobot-eval
    records them."""
    root = tmp_path_factory.mktemp("rollouts") / "pi05_rollouts"
    options = DemoOptions(model="pi05", num_episodes=6, max_calls=3, perturb=("clean", "absent"), explain=False)
    with RolloutRecorder(root, fps=ROLLOUT_FPS, robot_type=demo_reach.ASSET_ID) as recorder:
        result = run_demo(options, sink=recorder)
    assert 2 <= sum(e["success"] for e in result.episodes) < 6
    return root


@pytest.fixture(scope="module")
def spread_maps(recorded, tmp_path_factory):
    out = tmp_path_factory.mktemp("maps") / "spread.maps"
    run_local(
        model_job(recorded, out, OPTIONS, PI05, batch_size=4, every=5, sample_spread=SAMPLES, monitor_features=True)
    )
    return fmt.open_maps_dataset(out)


def test_explain_dataset_writes_each_frames_spread_and_monitor_fit_records_its_samples(
    pi05, recorded, spread_maps, tmp_path, capsys
):
    assert spread_maps.info.sample_spread == SAMPLES
    rows = spread_maps.table().to_pylist()
    spreads = [r["monitor/sample_spread"] for r in rows]
    assert rows and all(s is not None and s > 0 for s in spreads) and len(set(spreads)) == len(spreads)
    # each frame's noise comes from its index: explaining the frames again gives the same spreads
    again = tmp_path / "again.maps"
    run_local(model_job(recorded, again, OPTIONS, PI05, batch_size=2, every=5, sample_spread=SAMPLES))
    assert [r["monitor/sample_spread"] for r in fmt.open_maps_dataset(again).table().to_pylist()] == spreads
    rollouts = read_rollouts([spread_maps.root])
    assert rollouts.sample_spread == SAMPLES and SAMPLE_SPREAD in rollouts.inputs
    # `stats` ranks it beside the other baselines: over whole episodes, by each episode's largest spread
    stats = tmp_path / "stats.json"
    cli.main(["stats", str(spread_maps.root), "--format", "json", "--out", str(stats), "--kind", "gradnorm"])
    whole = json.loads(stats.read_text())["summary"]["outcomes"]["detection"][-1]
    largest = [float(np.max(e.columns[SAMPLE_SPREAD])) for e in rollouts.episodes]
    failed = [not e.success for e in rollouts.episodes]
    assert whole["frames"] == "episode"
    assert whole["figures"][SAMPLE_SPREAD]["auroc"] == pytest.approx(roc_auc(failed, largest), abs=1e-12)
    out = tmp_path / "spread.json"
    argv = ["monitor", "fit", str(spread_maps.root), "--out", str(out), "--kind", "mahalanobis"]
    cli.main([*argv, "--inputs", SAMPLE_SPREAD, "features/prompt", "--max-dims", "2"])
    assert f"samples      {SAMPLES} action chunks a call" in capsys.readouterr().out
    monitor = monitor_file.load(out)
    assert monitor.sample_spread == SAMPLES and [i.name for i in monitor.inputs] == [SAMPLE_SPREAD, "features/prompt"]
    # a maps dataset without the column beside one with it: one line, not a silent mix
    plain = tmp_path / "plain.maps"
    run_local(model_job(recorded, plain, OPTIONS, PI05, batch_size=4, every=5, episodes=(0,)))
    with pytest.raises(ValueError) as e:
        read_rollouts([spread_maps.root, plain])
    assert_one_line(e.value, "different samples per call", SAMPLE_SPREAD)


def test_a_spread_monitor_scores_datasets_and_live_calls_with_its_own_samples(pi05, recorded, spread_maps, tmp_path):
    fitted = tmp_path / "spread.json"
    argv = ["monitor", "fit", str(spread_maps.root), "--out", str(fitted), "--kind", "mahalanobis"]
    cli.main([*argv, "--inputs", SAMPLE_SPREAD, "--alpha", "0.2"])
    monitor = monitor_file.load(fitted)
    # explain-dataset with the monitor and no flag draws the monitor's samples: the same spreads, now scored
    scored = tmp_path / "scored.maps"
    run_local(model_job(recorded, scored, OPTIONS, PI05, batch_size=4, every=5, monitor=fitted))
    rows = fmt.open_maps_dataset(scored).table().to_pylist()
    assert fmt.open_maps_dataset(scored).info.sample_spread == SAMPLES
    assert [r["monitor/sample_spread"] for r in rows] == [
        r["monitor/sample_spread"] for r in spread_maps.table().to_pylist()
    ]
    assert all(r["monitor/score"] == monitor.score({SAMPLE_SPREAD: r["monitor/sample_spread"]}) for r in rows)
    # live: the worker draws them after the response; each step's spread is its served call's (input and noise)
    live = LiveMonitor(monitor, fitted.name)
    options = CAMOptions(every_k=1, dir=tmp_path / "runs", save_frames="none", queue_size=16)
    wrapped = wrap_policy_with_cam(pi05, options, monitor=live)
    observations = [policy_part(demo_obs(40 + t)) for t in range(3)]
    try:
        wrapped.warm_up()
        for t, obs in enumerate(observations):
            wrapped.infer(obs, RequestContext("robot", t))
    finally:
        wrapped.close(120)
    steps = sorted(load_run(wrapped.run_dir).steps, key=lambda s: s.meta.step)
    assert [s.meta.step for s in steps] == [0, 1, 2]
    for step, obs in zip(steps, observations, strict=True):
        _, trace = pi05.infer_traced(obs, noise=step.inputs["noise"], signals=True)
        expected = with_sample_spread(pi05, trace, SAMPLES)[SAMPLE_SPREAD]
        np.testing.assert_array_equal(step.monitor[SAMPLE_SPREAD], expected)
        assert float(step.monitor["score"]) == monitor.score({SAMPLE_SPREAD: expected})


def test_a_spread_monitor_is_refused_where_it_cannot_be_honoured_in_one_line(demo_policy, recorded, tmp_path, capsys):
    data = {
        "format": "openpi-cam monitor",
        "format_version": 1,
        "kind": "mahalanobis",
        "inputs": [{"name": SAMPLE_SPREAD, "dim": 1}],
        "sample_spread": SAMPLES,
        "alpha": 0.1,
        "threshold": 1.0,
        "basis": {"mean": [0.0], "scale": [1.0], "components": None},
        "mahalanobis": {"center": [0.0], "precision": [[1.0]], "residual_variance": 0.0},
    }
    path = tmp_path / "spread.json"
    path.write_text(json.dumps(data))
    live = LiveMonitor(monitor_file.load(path), path.name)
    # the response would wait for the extra samples
    with pytest.raises(ValueError) as e:
        wrap_policy_with_cam(
            create_demo_policy(model="pi05"), CAMOptions(every_k=0, monitor_response=True), monitor=live
        )
    assert_one_line(e.value, "--cam.monitor-response", "3 action samples a call")
    # pi0-FAST has no other samples of a call: refused before serving, naming the monitor
    wrapped = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=0), monitor=live)
    with pytest.raises(ValueError) as e:
        wrapped.warm_up()
    assert_one_line(e.value, "monitor spread.json", "pi0-FAST decodes greedily")
    wrapped.close(10)
    # explain-dataset: pi0-FAST, a count against the monitor's, one sample
    for argv, named in (
        (["--sample-spread", "3"], "pi0-FAST decodes greedily"),
        (["--config", PI05.config, "--monitor", str(path), "--sample-spread", "5"], "fitted on 3"),
        (["--config", PI05.config, "--sample-spread", "1"], "got 1"),
    ):
        capsys.readouterr()
        with pytest.raises(SystemExit) as exit_code:
            cli.main(["explain-dataset", str(recorded), "--out", str(tmp_path / "x.maps"), "--no-progress", *argv])
        err = capsys.readouterr().err.strip()
        assert exit_code.value.code == 1 and len(err.splitlines()) == 1 and named in err, (argv, err)
