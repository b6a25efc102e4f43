"""The failure monitor live (`serve --monitor`): every served call scored in its connection's order from the call's
own signals, the explained steps' files carrying their score, `/stats` counting flagged connections, the response
upstream's to the byte unless the monitor's key is asked for, and the monitor running with the side channel off.

The monitor here is fitted on the bundled demo model's own signals, and each test's expected scores are computed
apart from the side channel: the calls' inputs assembled by hand (the pooled features, STAC-single of consecutive
normalised chunks) and scored by `Monitor.score_steps` over the whole connection at once."""

from __future__ import annotations

import dataclasses
import itertools
import json
import shutil
import time

import numpy as np
import pytest
from cam_support import REPLAY_CLIENT, demo_obs, policy_part, strip_timing, write_packed
from client_env import run_client
from paths import GOLDEN_DIR
from real_clients import get_stats, read_packed

from openpi_cam import cli
from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import BUNDLED_CONFIGS, MONITOR_FILE, ModelSpec, create_demo_policy
from openpi_cam.cli import serve
from openpi_cam.demo import metaworld_sim
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.fit import Episode, FitOptions, fit_monitor
from openpi_cam.monitor.monitor_file import Monitor
from openpi_cam.monitor.signals import STAC, stac_single
from openpi_cam.policies import demo_reach
from openpi_cam.serving import RequestContext, msgpack_numpy
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.vocabulary import NORMALIZED_CHUNK

FEATURE = "features/base_0_rgb"
INPUTS = (FEATURE, "features/prompt", STAC)


def _signals(policy, observations: list[dict]) -> list[dict[str, np.ndarray]]:
    return [policy.infer_traced(o, signals=True)[1].signals for o in observations]


def _columns(signals: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One connection's monitor inputs, assembled apart from `monitor.stream`: the features as served, STAC-single
    of consecutive chunks over the demo robot's 5 executed actions (NaN for the first call)."""
    chunks = [s[NORMALIZED_CHUNK] for s in signals]
    stac = [np.nan] + [stac_single(a, b, 5) for a, b in itertools.pairwise(chunks)]
    return {name: np.array([s[name] for s in signals]) for name in INPUTS if name != STAC} | {STAC: np.array(stac)}


def _scores(monitor: Monitor, policy, observations: list[dict]) -> np.ndarray:
    """What the monitor scores a connection's calls, the whole connection at once."""
    return monitor.score_steps(Episode(_columns(_signals(policy, observations)), True).matrix(monitor.inputs))


@pytest.fixture(scope="module")
def monitor(demo_policy) -> Monitor:
    """A Mahalanobis monitor fitted on six 'successful' connections of the demo model's calls (features and STAC);
    each test sets its threshold."""
    connections = [[policy_part(demo_obs(1000 + 10 * e + t)) for t in range(3)] for e in range(6)]
    episodes = [Episode(_columns(_signals(demo_policy, c)), True) for c in connections]
    return fit_monitor(episodes, FitOptions(kind="mahalanobis", inputs=INPUTS, execution_horizon=5))


def _threshold_between(monitor: Monitor, scores: list[np.ndarray]) -> Monitor:
    """The monitor with its threshold between the connections' two largest maxima: one connection flagged (the
    one with the largest), not the rest."""
    maxima = sorted((np.nanmax(s) for s in scores), reverse=True)
    assert maxima[0] > maxima[1]
    return dataclasses.replace(monitor, threshold=(maxima[0] + maxima[1]) / 2)


def _connections(n: int, calls: int) -> list[list[dict]]:
    return [[policy_part(demo_obs(300 + 17 * c + t)) for t in range(calls)] for c in range(n)]


def test_every_call_is_scored_in_its_connections_order_and_explained_steps_carry_their_score(
    demo_policy, monitor, tmp_path
):
    connections = _connections(2, 4)
    expected = [_scores(monitor, demo_policy, c) for c in connections]
    monitor = _threshold_between(monitor, expected)
    plain = [[msgpack_numpy.packb(strip_timing(demo_policy.infer(o))) for o in c] for c in connections]
    live = LiveMonitor(monitor, "m.json")
    wrapped = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=2, dir=tmp_path, save_frames="none"), monitor=live)
    try:
        for t in range(4):  # the connections' calls interleaved, as a server with two robots serves them
            for c, observations in enumerate(connections):
                response = wrapped.infer(observations[t], RequestContext(f"conn{c}", t))
                assert msgpack_numpy.packb(strip_timing(response)) == plain[c][t]  # upstream's response, to the byte
    finally:
        wrapped.close(120)
    stats = wrapped.stats()["monitor"]
    assert stats["calls_scored"] == 8 and stats["connections_flagged"] == 1 and stats["connections_open_flagged"] == 1
    steps = load_run(wrapped.run_dir).steps
    assert sorted((s.meta.connection, s.meta.step) for s in steps) == [(f"conn{c}", t) for c in (0, 1) for t in (0, 2)]
    for step in steps:
        c, t = int(step.meta.connection[-1]), step.meta.step
        record = step.monitor
        np.testing.assert_array_equal(record["score"], expected[c][t])  # the same numbers, computed apart
        assert bool(record["flag"]) == bool((expected[c][: t + 1] > monitor.threshold).any())
        assert set(record) == {"score", "flag", STAC, "token_entropy", *(n for n in INPUTS if n != STAC)} | {
            "features/wrist_0_rgb",
            "features/actions",
        }


def test_the_response_carries_the_calls_score_only_when_asked(demo_policy, monitor, tmp_path):
    # A connection whose score rises after its first call (which of them does depends on the JAX build's numerics),
    # so that a threshold can lie between them.
    rising = [(c, s) for c in _connections(4, 3) if (s := _scores(monitor, demo_policy, c))[1:].max() > s[0]]
    assert rising, "no connection's score rises after its first call"
    observations, expected = rising[0]
    # between the first call's score and the largest: flagged from the call that first crosses it, for good
    monitor = dataclasses.replace(monitor, threshold=float(expected[0] + expected.max()) / 2)
    flags = np.maximum.accumulate(expected) > monitor.threshold
    assert not flags[0] and flags[-1]
    plain = [strip_timing(demo_policy.infer(o)) for o in observations]
    options = CAMOptions(every_k=0, dir=tmp_path, monitor_response=True)
    wrapped = wrap_policy_with_cam(demo_policy, options, monitor=LiveMonitor(monitor, "m.json"))
    try:
        for t, obs in enumerate(observations):
            response = strip_timing(wrapped.infer(obs, RequestContext("conn0", t)))
            entry = response.pop("monitor")
            assert msgpack_numpy.packb(response) == msgpack_numpy.packb(plain[t])  # the rest is upstream's
            assert entry == {"score": expected[t], "flag": bool(flags[t])}
    finally:
        wrapped.close(60)
    with pytest.raises(ValueError, match="needs a monitor"):
        wrap_policy_with_cam(demo_policy, options)


def test_the_monitor_runs_with_the_side_channel_off_and_counts_open_and_flagged_connections(
    demo_policy, monitor, tmp_path
):
    """`--monitor` with `--cam.every-k 0`: the side channel scores every call in its worker and explains nothing (no
    run directory); a closed connection's episode ends, and it leaves the open counts."""
    connections = _connections(3, 2)
    expected = [_scores(monitor, demo_policy, c) for c in connections]
    monitor = _threshold_between(monitor, expected)
    wrapped = wrap_policy_with_cam(
        demo_policy, CAMOptions(every_k=0, dir=tmp_path / "runs"), monitor=LiveMonitor(monitor, "m.json")
    )
    try:
        for c, observations in enumerate(connections):
            for t, obs in enumerate(observations):
                assert "monitor" not in wrapped.infer(obs, RequestContext(f"conn{c}", t))
        _until(lambda: wrapped.stats()["monitor"]["calls_scored"] == 6)
        stats = wrapped.stats()["monitor"]
        assert (stats["connections_open"], stats["connections_flagged"], stats["connections_open_flagged"]) == (3, 1, 1)
        flagged = int(np.argmax([s.max() for s in expected]))
        wrapped.connection_closed(f"conn{flagged}")
        _until(lambda: wrapped.stats()["monitor"]["connections_open"] == 2)
        stats = wrapped.stats()["monitor"]
        assert (stats["connections_flagged"], stats["connections_open_flagged"]) == (1, 0)
        assert stats["file"] == "m.json" and stats["threshold"] == monitor.threshold and stats["execution_horizon"] == 5
    finally:
        wrapped.close(60)
    assert wrapped.run_dir is None and not (tmp_path / "runs").exists()
    assert "scheduled" not in wrapped.stats()["explanations"]


def _until(condition, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "the worker did not get there in time"
        time.sleep(0.01)


def test_a_real_client_through_the_server_gets_upstreams_bytes_and_stats_count_its_connection(
    demo_policy, monitor, tmp_path
):
    observations = [demo_obs(500 + i) for i in range(3)]
    plain = [strip_timing(demo_policy.infer(policy_part(o))) for o in observations]
    monitor = dataclasses.replace(monitor, threshold=-np.inf)  # every scored call flags: the connection is flagged
    wrapped = wrap_policy_with_cam(
        demo_policy, CAMOptions(every_k=0, dir=tmp_path), monitor=LiveMonitor(monitor, "m.json")
    )
    server = start_server_in_thread(wrapped, metadata=demo_policy.metadata)
    wire = tmp_path / "wire"
    wire.mkdir()
    for i, obs in enumerate(observations):
        write_packed(wire / f"obs{i}.msgpack", obs)
    try:
        run_client(REPLAY_CLIENT, json.dumps({"port": server.port, "dir": str(wire), "n": len(observations)}))
        _until(lambda: get_stats(server.port)["policy"]["monitor"]["connections_open"] == 0)  # closed: episode over
        stats = get_stats(server.port)["policy"]["monitor"]
    finally:
        server.stop()
    assert stats["calls_scored"] == 3 and stats["connections_flagged"] == 1 and stats["threshold"] is None
    for i, local in enumerate(plain):
        served = strip_timing(read_packed(wire / f"response{i}.msgpack"))
        assert set(served) == set(local)
        for key, value in local.items():
            np.testing.assert_array_equal(served[key], value, err_msg=key)


def test_serve_refuses_a_bad_monitor_a_response_key_without_one_and_an_input_the_model_lacks(monitor, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    for argv, wanted in [
        (["--monitor", str(bad)], f"--monitor {bad}: not a monitor file"),
        (["--no-monitor", "--cam.monitor-response"], "--cam.monitor-response needs a failure monitor"),
        (["--monitor", str(bad), "--no-monitor"], "--monitor and --no-monitor"),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            cli.main(["serve", "--port", "0", *argv])
        assert exit_info.value.code == 2
        _assert_one_error_line(capsys.readouterr().err, wanted)
    # a pi0-FAST monitor reading token entropy, served with pi0.5, whose calls have none: refused at warm-up
    entropy = fit_monitor(
        [Episode({"token_entropy": np.random.default_rng(i).random(4)}, True) for i in range(4)],
        FitOptions(kind="mahalanobis", inputs=("token_entropy",)),
    )
    path = monitor_file.save(entropy, tmp_path / "entropy.json")
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["serve", "--port", "0", "--config", "demo_reach_pi05", "--monitor", str(path)])
    assert exit_info.value.code == 2
    _assert_one_error_line(
        capsys.readouterr().err, f"monitor {path.name}: the step has no monitor input 'token_entropy'"
    )


def _assert_one_error_line(stderr: str, wanted: str) -> None:
    """The command's own message (beside its log lines) is one line naming the problem."""
    (line,) = [line for line in stderr.splitlines() if line.startswith("openpi-cam serve:")]
    assert wanted in line, line


def test_a_demo_model_serves_with_its_own_monitor_unless_told_otherwise(monitor, tmp_path):
    # the installed bundled model ships its own (`benchmarks/monitor_transfer.py` fitted it)
    assert ModelSpec().default_monitor() == demo_reach.ASSETS / MONITOR_FILE
    assets = tmp_path / "assets"
    shutil.copytree(demo_reach.ASSETS, assets, ignore=shutil.ignore_patterns(MONITOR_FILE))
    spec = ModelSpec(checkpoint_dir=assets / "checkpoint", config="demo_reach")
    assert spec.default_monitor() is None and serve._monitor(spec, None, False) is None
    monitor_file.save(monitor, assets / MONITOR_FILE)
    assert spec.default_monitor() == assets / MONITOR_FILE
    live = serve._monitor(spec, None, False)
    assert live is not None and monitor_file.to_json(live.monitor) == monitor_file.to_json(monitor)
    assert serve._monitor(spec, None, True) is None  # --no-monitor
    other = monitor_file.save(dataclasses.replace(monitor, threshold=1.0), tmp_path / "other.json")
    assert serve._monitor(spec, other, False).monitor.threshold == 1.0  # --monitor names another
    # an OpenPI checkpoint or LeRobot folder has no monitor of its own
    assert ModelSpec(checkpoint_dir=GOLDEN_DIR / "tiny_policy_droid" / "checkpoint").default_monitor() is None


def test_a_fleet_call_under_the_monitor_serves_each_row_its_own_actions_and_scores_each_connection(
    demo_policy, monitor, tmp_path
):
    """Batched serving (`--batch-window-ms`): one model call for several connections' requests, each answered as
    plain serving answers it, and each row scored in its own connection's stream (as its lone calls score)."""
    connections = _connections(3, 2)
    expected = [_scores(monitor, demo_policy, c) for c in connections]
    plain = [[msgpack_numpy.packb(strip_timing(demo_policy.infer(o))) for o in c] for c in connections]
    wrapped = wrap_policy_with_cam(
        demo_policy, CAMOptions(every_k=0, dir=tmp_path, monitor_response=True), monitor=LiveMonitor(monitor, "m.json")
    )
    try:
        for t in range(2):
            rows = [c[t] for c in connections]
            contexts = [RequestContext(f"conn{c}", t) for c in range(3)]
            for c, response in enumerate(wrapped.infer_batch(rows, contexts)):
                response = strip_timing(response)
                # the features of a batched row are a lone request's to float32 rounding (batched matrix products
                # sum in another order), so its score is too: measured 1e-7 of the score here
                assert response.pop("monitor")["score"] == pytest.approx(expected[c][t], rel=1e-5)
                assert msgpack_numpy.packb(response) == plain[c][t]  # the actions themselves are the same bits
    finally:
        wrapped.close(60)
    assert wrapped.stats()["monitor"]["calls_scored"] == 6


def test_the_multi_task_models_monitors_trust_their_probe_under_the_instructions_they_were_fitted_on():
    """The shipped multi-task monitors are gated (docs/MONITOR.md, rounds 4 and 5), fitted on rollouts of four of
    the six trained tasks and told every phrasing the policy was trained on: the demo's instruction for each of those
    four is one they trust their probe under; under the other two trained tasks' they score by STAC alone; under the
    held-out tasks' they flag from the first call. A change to the demo's instructions that the monitors were not
    refitted for would leave every task to STAC, or flag it, silently: this is where it shows."""
    fitted_on = {"button-press-topdown-v3", "reach-v3", "push-v3", "drawer-close-v3"}
    trained = {metaworld_sim.TRAINED_TASKS: monitor_file.TRAINED, metaworld_sim.HELD_OUT_TASKS: monitor_file.UNTRAINED}
    phrasings = [p for task in metaworld_sim.TRAINED_TASKS for p in metaworld_sim.TASKS[task].prompts]
    for name in ("metaworld_mt_pi05", "metaworld_mt_pi0_fast"):
        monitor = monitor_file.load(ModelSpec.demo(name).default_monitor())
        assert monitor.kind == "gated" and len(monitor.prompts) == len(fitted_on), name
        assert monitor.trained_on == tuple(sorted(monitor_file.instruction(p) for p in phrasings)), name
        for tasks, trust in trained.items():
            for task in tasks:
                expected = monitor_file.FITTED if task in fitted_on else trust
                assert monitor.trust(metaworld_sim.TASKS[task].prompt) == expected, (name, task)


# The bundled models the demo drives each ship a monitor; the one-task Meta-World button pi0.5, kept for the maps
# bench and `--config demo_metaworld_pi05`, is no longer one the demo drives and ships none.
MONITORED = sorted(set(BUNDLED_CONFIGS) - {"metaworld"})


def test_the_models_the_demo_drives_ship_a_monitor_and_the_one_task_model_none():
    assert {m for m in BUNDLED_CONFIGS if ModelSpec.demo(m).default_monitor() is not None} == set(MONITORED)


@pytest.mark.slow
@pytest.mark.parametrize("model", MONITORED)
def test_each_bundled_models_monitor_scores_its_own_calls(model):
    """What `serve` checks before it reports ready, for every bundled model and the monitor it ships: the monitor
    reads only inputs of the widths the model's served call gives, under the call's own prompt."""
    path = ModelSpec.demo(model).default_monitor()
    live = LiveMonitor(monitor_file.load(path), path.name)
    trace = create_demo_policy(model).warm_up(signals=True)
    live.check(trace.signals, trace.prompt)
    scored = live.score("example", trace.signals, trace.prompt)
    assert np.isnan(scored.inputs[STAC]) and scored.score is not None  # a first call: no previous chunk
