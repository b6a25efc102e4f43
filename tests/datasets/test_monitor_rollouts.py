"""The failure monitor over recorded rollouts: `explain-dataset` writes every row's monitor columns (STAC-single
between explained frames one execution horizon apart, the token entropy, the pooled features when asked, the score
and flag with a monitor), `openpi-cam monitor fit` fits a monitor on them, and the same frames score the same live
(served through the real server and side channel) and offline (explained by `explain-dataset`).

The rollouts are the bundled pi0-FAST's own under the demo's perturbations (`demo --record`: one frame per executed
action, `next.success`), recorded once per module; frames are explained every 5th, where the robot asked."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from client_env import collect
from datasets_support import model_job
from paths import LEROBOT_DIR
from real_clients import send_observations

from openpi_cam import cli
from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.cam.run_format import load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import MONITOR_FILE, create_demo_policy
from openpi_cam.demo.run import ROLLOUT_FPS, DemoOptions, run_demo
from openpi_cam.lerobot.dataset import open_dataset
from openpi_cam.lerobot.rollouts import RolloutRecorder
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import _observation, run_local
from openpi_cam.maps.monitoring import read_rollouts
from openpi_cam.maps.views import compute_views
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.fit import episode_max
from openpi_cam.monitor.monitor_file import Standardised
from openpi_cam.monitor.stream import DEFAULT_EXECUTION_HORIZON
from openpi_cam.policies import demo_reach
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.vocabulary import ExplainOptions

HORIZON = DEFAULT_EXECUTION_HORIZON  # the demo robot executes 5 actions per call
# The options of tests/datasets' other jobs, so that compiled programs are shared.
OPTIONS = ExplainOptions(target="action-token", maps=("gradcam", "gradnorm"), check_patches=2)
FEATURES = ["features/base_0_rgb", "features/wrist_0_rgb", "features/prompt", "features/actions"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Six closed-loop episodes of at most 3 calls, clean and with the named block absent (which fail)."""
    root = tmp_path_factory.mktemp("rollouts") / "demo_rollouts"
    options = DemoOptions(num_episodes=6, max_calls=3, perturb=("clean", "absent"), explain=False)
    with RolloutRecorder(root, fps=ROLLOUT_FPS, robot_type=demo_reach.ASSET_ID) as recorder:
        result = run_demo(options, sink=recorder)
    assert 2 <= sum(e["success"] for e in result.episodes) < 6  # successes to calibrate on, failures to rank
    return root


@pytest.fixture(scope="module")
def featured(recorded, tmp_path_factory):
    """The rollouts explained with the pooled features written (what a monitor is fitted on)."""
    out = tmp_path_factory.mktemp("maps") / "featured.maps"
    run_local(model_job(recorded, out, OPTIONS, batch_size=4, every=HORIZON, monitor_features=True))
    return fmt.open_maps_dataset(out)


def test_rows_carry_stac_between_calls_a_horizon_apart_the_token_entropy_and_the_features(featured):
    info = featured.info
    assert info.execution_horizon == HORIZON and info.monitor is None and info.monitor_features == FEATURES
    rows = featured.table().to_pylist()
    assert rows
    for row in rows:
        first = row["frame_index"] == 0
        assert (row["monitor/stac"] is None) == first  # the episode's first call has no previous chunk
        assert row["monitor/stac"] is None or row["monitor/stac"] >= 0
        assert 0 < row["monitor/token_entropy"] < math.log(257_152)  # nats, over the action tokens
        assert row["monitor/score"] is None and row["monitor/flag"] is None  # no monitor
        for name in FEATURES:
            assert len(row["monitor/" + name]) == 128
    # the schema stores the features as float32, as the served call computed them
    assert featured.table(columns=["monitor/features/prompt"]).schema.field(0).type.value_type == "float"
    # read back as labelled episodes, each step with its source frame (what detection counts time in)
    rollouts = read_rollouts([featured.root])
    for (_, episode), e in zip(rollouts.names, rollouts.episodes, strict=True):
        frames = featured.table(episode, ["frame_index"]).column(0).to_pylist()
        assert e.frames.tolist() == frames and frames == list(range(0, HORIZON * len(frames), HORIZON))


def test_stac_is_null_where_explained_frames_do_not_lie_a_horizon_apart(recorded, tmp_path):
    """Explained every 5th frame but for a robot executing 10 actions per call: no two explained frames are one
    call apart, so no row has a STAC."""
    out = tmp_path / "ten.maps"
    run_local(model_job(recorded, out, OPTIONS, batch_size=4, every=HORIZON, episodes=(0,), execution_horizon=10))
    maps = fmt.open_maps_dataset(out)
    assert maps.info.execution_horizon == 10
    assert [r["monitor/stac"] for r in maps.table().to_pylist()] == [None] * maps.table().num_rows


def test_monitor_fit_saves_a_monitor_and_prints_its_auroc_and_threshold(featured, tmp_path, capsys):
    out = tmp_path / "probe.json"
    cli.main(["monitor", "fit", str(featured.root), "--out", str(out), "--alpha", "0.2"])
    printed = capsys.readouterr().out
    monitor = monitor_file.load(out)
    assert monitor.kind == "probe" and monitor.execution_horizon == HORIZON and monitor.alpha == 0.2
    assert [i.name for i in monitor.inputs] == sorted([*FEATURES, "stac", "token_entropy"])
    assert monitor.fit["maps"] == [str(featured.root)]
    for line in ("monitor ", "inputs ", "episodes ", "training ", "threshold ", "calibration "):
        assert any(row.startswith(line) for row in printed.splitlines()), printed
    assert "AUROC" in printed and "for alpha 0.2" in printed and "false alarms" in printed
    # the same episodes and flags give the same file
    again = tmp_path / "again.json"
    cli.main(["monitor", "fit", str(featured.root), "--out", str(again), "--alpha", "0.2"])
    assert again.read_text() == out.read_text()
    # a STAC monitor reads its one input, and --kind mahalanobis the inputs named
    cli.main(["monitor", "fit", str(featured.root), "--out", str(tmp_path / "stac.json"), "--kind", "stac"])
    assert [i.name for i in monitor_file.load(tmp_path / "stac.json").inputs] == ["stac"]
    named = ["--kind", "mahalanobis", "--inputs", "features/prompt", "stac", "--max-dims", "4"]
    cli.main(["monitor", "fit", str(featured.root), "--out", str(tmp_path / "m.json"), *named])
    mahalanobis = monitor_file.load(tmp_path / "m.json")
    # the feature projected onto at most 4 of its leading directions (fewer over these few steps), STAC kept beside
    basis = mahalanobis.basis
    assert [i.name for i in mahalanobis.inputs] == ["features/prompt", "stac"] and 2 <= basis.dims <= 4 + 1
    assert basis.components[-1].tolist() == [0.0] * 128 + [1.0]


def _fit_error(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["monitor", "fit", *argv])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("openpi-cam monitor fit: "), err
    return err


def test_monitor_fit_refuses_flags_of_another_kind_and_bad_input_in_one_line(featured, tmp_path, capsys):
    maps, out = str(featured.root), str(tmp_path / "m.json")
    assert "--l2 is read by --kind probe or union or gated, not mahalanobis" in _fit_error(
        [maps, "--out", out, "--kind", "mahalanobis", "--l2", "1"], capsys
    )
    assert "--temporal is read by" in _fit_error([maps, "--out", out, "--kind", "stac", "--temporal"], capsys)
    # these rollouts' successes end within a call or two: too few STAC values to put STAC on a union's scale
    for kind in ("union", "gated"):
        assert f"a {kind} monitor needs the training successes' stac scores to vary" in _fit_error(
            [maps, "--out", out, "--kind", kind], capsys
        )
    assert "--trained-prompts is read by --kind gated, not probe" in _fit_error(
        [maps, "--out", out, "--trained-prompts", "open the door"], capsys
    )
    gated = [maps, "--out", out, "--kind", "gated"]
    assert f"{tmp_path / 'meta' / 'info.json'}: missing" in _fit_error([*gated, "--trained-on", str(tmp_path)], capsys)
    assert "an empty instruction" in _fit_error([*gated, "--trained-prompts", "open the door", " "], capsys)
    assert "--alpha must be in (0, 1)" in _fit_error([maps, "--out", out, "--alpha", "1.5"], capsys)
    assert "no column 'features/elbow'" in _fit_error([maps, "--out", out, "--inputs", "features/elbow"], capsys)
    assert "is not a maps dataset" in _fit_error([str(tmp_path), "--out", out], capsys)
    for edit, wanted in [
        ({"outcome": None}, "carry no episode outcomes"),
        ({"execution_horizon": None}, "have no monitor columns"),
    ]:
        copy = tmp_path / f"copy-{len(wanted)}"
        shutil.copytree(featured.root, copy)
        info = json.loads((copy / fmt.INFO_JSON).read_text())
        (copy / fmt.INFO_JSON).write_text(json.dumps({**info, **edit}))
        assert wanted in _fit_error([str(copy), "--out", out], capsys)
    assert not (tmp_path / "m.json").exists()


@pytest.fixture(scope="module")
def fitted(featured, tmp_path_factory):
    """A gated monitor on the features and STAC: the probe `monitor fit` fits, trusted under the first episode's
    instruction alone, told that the policy was trained on one other (its episodes scored by STAC alone) and on no
    more (the rest flagged from their first call): what the live and offline paths must both read from the call's
    prompt. On the scales of every step, its threshold at the episodes' median maximum (so that some episodes are
    flagged and the flags are checked). These rollouts end within a call or two, too few
    STAC values among the training successes for `monitor fit --kind gated` to put STAC on a scale."""
    path = tmp_path_factory.mktemp("monitor") / "monitor.json"
    inputs = ["--inputs", "features/base_0_rgb", "features/prompt", "stac", "--max-dims", "4"]
    cli.main(["monitor", "fit", str(featured.root), "--out", str(path), "--kind", "probe", *inputs])
    rollouts = read_rollouts([featured.root])
    probe = monitor_file.load(path)
    steps = np.concatenate([e.matrix(probe.inputs) for e in rollouts.episodes])
    scores, stac = probe.score_steps(steps), steps[:, probe.stac_column]
    scales = Standardised((scores.mean(), scores.std()), (np.nanmean(stac), np.nanstd(stac)))
    instructions = [monitor_file.instruction(e.prompts[0]) for e in rollouts.episodes]
    other = next(i for i in instructions if i != instructions[0])
    trained = tuple(sorted({instructions[0], other}))
    gated = dataclasses.replace(
        probe, kind="gated", standardised=scales, prompts=(instructions[0],), trained_on=trained
    )
    trust = {gated.trust(i) for i in instructions}
    assert trust == {monitor_file.FITTED, monitor_file.TRAINED, monitor_file.UNTRAINED}, instructions
    maxima = [episode_max(gated.score_steps(e.matrix(gated.inputs), e.prompts)) for e in rollouts.episodes]
    monitor_file.save(dataclasses.replace(gated, threshold=float(np.median(maxima))), path)
    return path


def test_explain_dataset_scores_with_a_demo_models_own_monitor_unless_told_otherwise(
    recorded, fitted, tmp_path, capsys
):
    """A demo model's folder with a `monitor.json` beside its checkpoint: the command scores with it by default, with
    none under `--no-monitor`, with another under `--monitor`; both flags at once are refused in one line."""
    assets = tmp_path / "assets"
    shutil.copytree(demo_reach.ASSETS, assets)
    shutil.copy(fitted, assets / MONITOR_FILE)
    other = monitor_file.save(dataclasses.replace(monitor_file.load(fitted), alpha=0.3), tmp_path / "other.json")
    model = ["--checkpoint-dir", str(assets / "checkpoint"), "--config", "demo_reach"]
    base = [str(recorded), *model, "--episodes", "0", "--every-k", "100", "--maps", "gradnorm", "--no-progress"]
    for flags, expected in [
        ((), assets / MONITOR_FILE),
        (("--no-monitor",), None),
        (("--monitor", str(other)), other),
    ]:
        out = tmp_path / f"{len(flags)}.maps"
        cli.main(["explain-dataset", *base, "--out", str(out), *flags])
        monitor = fmt.open_maps_dataset(out).info.monitor
        assert monitor == (None if expected is None else str(expected.resolve())), flags
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        cli.main(
            ["explain-dataset", *base, "--out", str(tmp_path / "both.maps"), "--monitor", str(other), "--no-monitor"]
        )
    assert exit_info.value.code == 1
    (line,) = [x for x in capsys.readouterr().err.splitlines() if x.startswith("openpi-cam explain-dataset:")]
    assert "--monitor and --no-monitor name opposite things" in line


def _number(value: float | None) -> float:
    """A row's float column as a number (null: NaN, no value)."""
    return math.nan if value is None else value


def _scoring_job(recorded, out, monitor):
    return model_job(recorded, out, OPTIONS, batch_size=4, every=HORIZON, monitor=monitor)


@pytest.fixture(scope="module")
def scored(recorded, fitted, tmp_path_factory):
    out = tmp_path_factory.mktemp("maps") / "scored.maps"
    run_local(_scoring_job(recorded, out, fitted))
    return fmt.open_maps_dataset(out)


def test_explain_dataset_scores_each_episode_as_the_monitor_scores_it_whole(featured, scored, fitted):
    monitor = monitor_file.load(fitted)
    info = scored.info
    assert info.monitor == str(fitted.resolve()) and len(info.monitor_sha256) == 64
    rollouts = read_rollouts([featured.root])
    flagged = 0
    for (_, episode), e in zip(rollouts.names, rollouts.episodes, strict=True):
        rows = scored.table(episode).to_pylist()
        expected = monitor.score_steps(e.matrix(monitor.inputs), e.prompts)
        np.testing.assert_array_equal([_number(r["monitor/score"]) for r in rows], expected)
        trust = monitor.trust(rows[0]["task"])
        if trust != monitor_file.FITTED:  # an instruction it was not fitted on: STAC alone, raised if untrained
            mean, std = monitor.standardised.stac
            stac = (np.array([_number(r["monitor/stac"]) for r in rows]) - mean) / std
            if trust == monitor_file.UNTRAINED:
                stac = np.fmax(stac, monitor.threshold + monitor_file.UNTRAINED_MARGIN)
                assert rows[0]["monitor/flag"]
            np.testing.assert_array_equal(expected, stac)
        flags = np.fmax.accumulate(expected) > monitor.threshold  # a step without a score flags nothing
        assert [r["monitor/flag"] for r in rows] == flags.tolist()
        flagged += bool(flags[-1])
    assert 0 < flagged < len(rollouts.episodes)


def test_a_resumed_job_refuses_another_monitor(recorded, scored, fitted, tmp_path):
    other = dataclasses.replace(monitor_file.load(fitted), alpha=0.3)
    with pytest.raises(ValueError, match="monitor_sha256"):
        run_local(_scoring_job(recorded, scored.root, monitor_file.save(other, tmp_path / "other.json")))
    moved = shutil.copy(fitted, tmp_path / "moved.json")  # the same monitor elsewhere: its content decides
    summary = run_local(_scoring_job(recorded, scored.root, moved))
    assert summary.episodes_written == 0 and summary.episodes_already_written == 6


def test_the_same_frames_score_the_same_live_and_offline(recorded, scored, fitted, tmp_path):
    """Each episode's request frames (every 5th frame, where the robot asked) sent by the real openpi-client on one
    connection to the real server, the side channel explaining and the monitor scoring every call: each step file's
    score is the maps dataset's for that frame. Both run the same compiled program on the same inputs, so the
    scores are the same numbers (measured: no difference at all); a float32 difference of the signals, had the
    programs differed, would show here as one."""
    policy = create_demo_policy()
    live = LiveMonitor(monitor_file.load(fitted), fitted.name)
    options = CAMOptions(every_k=1, dir=tmp_path / "runs", save_frames="none", queue_size=64)  # room for every call
    cam = wrap_policy_with_cam(policy, options, monitor=live)
    server = start_server_in_thread(cam, metadata=policy.metadata)
    job = model_job(recorded, tmp_path / "unused", OPTIONS)
    ds = open_dataset(recorded)
    sent = {}
    try:
        for episode in ds.episodes:
            wanted = range(0, ds.episode_length(episode), HORIZON)
            frames = list(ds.frames(episode, features=sorted(set(job.keys.values())), frame_indices=wanted))
            observations = [_observation(frame, job) for frame in frames]
            collect(send_observations(server.port, tmp_path / f"client{episode}", observations))
            sent[episode] = [int(f["frame_index"]) for f in frames]
    finally:
        server.stop()
    steps = load_run(cam.run_dir).steps
    connections = sorted({s.meta.connection for s in steps})  # one per episode, numbered in the order they came
    assert len(connections) == len(sent)
    compared = 0
    for connection, episode in zip(connections, sorted(sent), strict=True):
        offline = {r["frame_index"]: _number(r["monitor/score"]) for r in scored.table(episode).to_pylist()}
        for step in (s for s in steps if s.meta.connection == connection):
            frame = sent[episode][step.meta.step]
            # the same number, or no score on both sides (STAC alone on a first call)
            np.testing.assert_array_equal(float(step.monitor["score"]), offline[frame], err_msg=f"{episode} {frame}")
            compared += 1
    assert compared == scored.table().num_rows


def _pairs_auc(failed: dict[int, bool], scores: dict[int, float]) -> float:
    """The share of (failure, success) pairs where the failure scores higher, ties one half: by hand."""
    pairs = [(scores[f], scores[s]) for f in scores if failed[f] for s in scores if not failed[s]]
    return sum(1.0 if a > b else 0.5 if a == b else 0.0 for a, b in pairs) / len(pairs)


def test_stats_rank_each_figures_maximum_over_an_episodes_first_frames(scored, tmp_path, capsys):
    out = tmp_path / "stats.json"
    cli.main(["stats", str(scored.root), "--format", "json", "--out", str(out), "--kind", "gradnorm"])
    data = json.loads(out.read_text())
    detection, rows = data["summary"]["outcomes"]["detection"], data["frames"]
    assert [d["frames"] for d in detection] == [1, 4, 8, 16, 32, "episode"]
    names = set(detection[0]["figures"])
    assert {"monitor", "stac", "token_entropy", "entropy", "distance", "base_0_rgb/mean_entropy_norm"} <= names
    assert all(set(d["figures"]) == names for d in detection)
    failed = {r["episode_index"]: not r["episode_success"] for r in rows}
    by_episode = {e: [r for r in rows if r["episode_index"] == e] for e in failed}
    for episode_rows in by_episode.values():
        episode_rows.sort(key=lambda r: r["frame_index"])
    assert [r["frame_index"] for r in by_episode[0]][:2] == [0, HORIZON]  # the frames the windows below hold
    # the monitor's score at N = 1 is its first frame's, over the whole episode the maximum of every frame's; an
    # episode without a score there is left out (the gated monitor's STAC alone has none on a first call)
    scores = {e: [r["monitor/score"] for r in rows if r["monitor/score"] is not None] for e, rows in by_episode.items()}
    first = {e: rows[0]["monitor/score"] for e, rows in by_episode.items() if rows[0]["monitor/score"] is not None}
    top = {e: max(s) for e, s in scores.items() if s}
    assert 0 < len(first) < len(top)  # the first calls of episodes scored by STAC alone have no score
    assert detection[0]["figures"]["monitor"]["auroc"] == pytest.approx(_pairs_auc(failed, first), abs=1e-12)
    assert detection[-1]["figures"]["monitor"]["auroc"] == pytest.approx(_pairs_auc(failed, top), abs=1e-12)
    assert detection[0]["figures"]["monitor"]["episodes"] == len(first)
    assert detection[-1]["figures"]["monitor"]["episodes"] == len(top)
    assert detection[-1]["figures"]["monitor"]["failures"] == sum(failed[e] for e in top)
    # N = 8 holds frames 0 and 5; the token entropy's maximum there, by hand
    early = {e: max(r["monitor/token_entropy"] for r in rows if r["frame_index"] < 8) for e, rows in by_episode.items()}
    assert detection[2]["figures"]["token_entropy"]["auroc"] == pytest.approx(_pairs_auc(failed, early), abs=1e-12)
    low, high = detection[-1]["figures"]["monitor"]["auroc_ci95"]
    assert low <= detection[-1]["figures"]["monitor"]["auroc"] <= high
    # STAC needs a previous call: no episode has it from its first frame alone
    assert detection[0]["figures"]["stac"] == {"auroc": None, "auroc_ci95": [None, None], "episodes": 0, "failures": 0}
    assert detection[1]["figures"]["stac"]["episodes"] == 0 < detection[-1]["figures"]["stac"]["episodes"]
    printed = capsys.readouterr().err.splitlines()
    at = printed.index(next(line for line in printed if line.startswith("failure detection")))
    assert printed[at + 1].split() == ["figure", "N=1", "N=4", "N=8", "N=16", "N=32", "episode"]
    assert printed[at + 2].split()[0] == "monitor"  # the monitor's line first


def test_monitor_fit_gated_records_the_instructions_it_trusts_its_probe_on(featured, tmp_path, capsys):
    """`monitor fit --kind gated` on a copy whose STAC column is rewritten with seeded values on every row (these
    rollouts' own successes end too soon to put STAC on a scale): the file names the episodes' instructions, the
    report prints them, and a step under another instruction scores its standardised STAC alone. Told what the
    policy was trained on (a LeRobot-written dataset's tasks and one more instruction), a step under an
    instruction outside those scores above the threshold from the first call."""
    copy = tmp_path / "stac.maps"
    shutil.copytree(featured.root, copy)
    rng = np.random.default_rng(0)
    for shard in sorted((copy / fmt.DATA_DIR).rglob("*.parquet")):
        table = pq.read_table(shard)
        i = table.column_names.index("monitor/stac")
        stac = pa.array(rng.uniform(0.0, 1.0, table.num_rows), table.schema.field(i).type)
        pq.write_table(table.set_column(i, table.schema.field(i), stac), shard)
    out = tmp_path / "gated.json"
    # alpha 0.5: these few calibration successes give no finite threshold at the default 0.1
    flags = ["--kind", "gated", "--inputs", "features/prompt", "stac", "--max-dims", "4", "--alpha", "0.5"]
    trained = ["--trained-on", str(LEROBOT_DIR / "demo_reach_v30_image"), "--trained-prompts", "Open the door"]
    cli.main(["monitor", "fit", str(copy), "--out", str(out), *flags, *trained])
    monitor = monitor_file.load(out)
    tasks = {r["task"] for r in fmt.open_maps_dataset(copy).table(columns=["task"]).to_pylist()}
    assert monitor.kind == "gated" and monitor.prompts == tuple(sorted(monitor_file.instruction(t) for t in tasks))
    lerobot_tasks = open_dataset(LEROBOT_DIR / "demo_reach_v30_image").tasks().values()
    assert monitor.trained_on == tuple(sorted({*lerobot_tasks, "open the door"}))
    printed = capsys.readouterr().out.splitlines()
    (line,) = [row for row in printed if row.startswith("trusted on")]
    assert all(p in line for p in monitor.prompts)
    assert [row.split()[2] for row in printed if row.startswith("trained on")] == [str(len(monitor.trained_on))]
    x = np.array([[*np.zeros(128), 0.7]])
    mean, std = monitor.standardised.stac
    assert monitor.score_steps(x, "open the door") == pytest.approx([(0.7 - mean) / std], rel=1e-12)
    assert monitor.score_steps(x, sorted(tasks)[0]) >= monitor.score_steps(x, "open the door")
    assert math.isfinite(monitor.threshold)
    floor = monitor.threshold + monitor_file.UNTRAINED_MARGIN
    first = np.array([[*np.zeros(128), np.nan]])  # a first call: no STAC yet
    assert np.isnan(monitor.score_steps(first, "open the door")) and monitor.score_steps(first, "open the window") == [
        floor
    ]


def test_a_score_that_rises_after_frame_8_finds_nothing_by_frame_8(featured, tmp_path):
    """The rows' monitor score rewritten in a copy: 0 on every frame up to frame 8, then 1 on failed episodes' frames
    (0 on successes'). Up to 8 frames every episode ties (AUROC 0.5); from 16 the failures that reached frame 10
    rank first."""
    copy = tmp_path / "late.maps"
    shutil.copytree(featured.root, copy)
    for shard in sorted((copy / fmt.DATA_DIR).rglob("*.parquet")):
        table = pq.read_table(shard)
        late = np.array(table.column("frame_index").to_pylist()) > 8
        failed = ~np.array(table.column(fmt.EPISODE_SUCCESS).to_pylist())
        score = pa.array((late & failed).astype(np.float64))
        i = table.column_names.index("monitor/score")
        pq.write_table(table.set_column(i, table.schema.field(i), score), shard)
    views = compute_views(fmt.open_maps_dataset(copy), "gradnorm")
    detection = {d["frames"]: d["figures"]["monitor"] for d in views.outcomes["detection"]}
    rows = views.rows
    failures = {r["episode_index"] for r in rows if not r["episode_success"]}
    reached = {r["episode_index"] for r in rows if not r["episode_success"] and r["frame_index"] > 8}
    assert reached  # the failures run to the step limit, past frame 8
    for n in (1, 4, 8):
        assert detection[n]["auroc"] == 0.5, n
    for n in (16, 32, "episode"):
        assert detection[n]["auroc"] == pytest.approx(0.5 + 0.5 * len(reached) / len(failures), abs=1e-12), n
