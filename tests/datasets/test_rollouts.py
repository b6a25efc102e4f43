"""Closed-loop rollouts recorded as a LeRobot dataset (`openpi-cam demo --record`): the bundled pi0-FAST served
through the websocket server, driven under perturbations and read back with our LeRobot reader. LeRobot 0.6.1's own
reader opening such a recording is checked outside CI (`benchmarks/check_lerobot_reads.py`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from datasets_support import model_job

from openpi_cam import cli
from openpi_cam.cam.run_format import Reliance
from openpi_cam.demo import perturb, quality
from openpi_cam.demo.recorded import PERTURBATION_FEATURE, perturbation_names, recorded_episodes_file
from openpi_cam.demo.run import ROLLOUT_FPS, DemoOptions, run_demo
from openpi_cam.lerobot.dataset import DatasetError, open_dataset
from openpi_cam.lerobot.rollouts import RolloutRecorder
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.dataset import open_maps_dataset
from openpi_cam.maps.explain import run_local
from openpi_cam.maps.views import TARGET_BOX, ViewOptions, compute_views, normalised
from openpi_cam.policies import demo_reach
from openpi_cam.vocabulary import ExplainOptions

PERTURB = ("clean", "absent")
# The carried name of each frame's perturbation: the condition `stats` and `render` set episodes side by side by.
GROUP = PERTURBATION_FEATURE
# AV1 at LeRobot's crf 30 on these 64 px frames: a mean error of 1.5 to 6 of 255 per frame (check_lerobot_reads.py)
CODEC_MEAN_ERROR = 8.0


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    root = tmp_path_factory.mktemp("rollouts") / "demo_rollouts"
    options = DemoOptions(num_episodes=4, max_calls=2, perturb=PERTURB, explain=False)
    with RolloutRecorder(root, fps=ROLLOUT_FPS, robot_type=demo_reach.ASSET_ID) as recorder:
        result = run_demo(options, sink=recorder)
    return root, result


def test_every_executed_action_is_a_frame_with_lerobot_evals_outcomes(recorded):
    root, result = recorded
    ds = open_dataset(root)
    keys = demo_reach.LEROBOT_KEYS
    assert ds.version == "v3.0" and ds.fps == ROLLOUT_FPS and ds.episodes == [0, 1, 2, 3]
    assert [e["perturbation"] for e in result.episodes] == ["clean", "absent"] * 2
    assert not result.episodes[1]["success"] and not result.episodes[3]["success"]  # nothing named is there to reach
    for i, outcome in enumerate(result.episodes):
        frames = list(ds.frames(i))
        assert len(frames) == outcome["steps"] <= 2 * DemoOptions.execute
        success = np.array([bool(f["next.success"]) for f in frames])
        done = np.array([bool(f["next.done"]) for f in frames])
        # lerobot-eval's episode: done on the last frame only, success there when the block was reached
        assert done.tolist() == [False] * (len(frames) - 1) + [True]
        assert success.tolist() == [False] * (len(frames) - 1) + [outcome["success"]]
        assert [float(f["next.reward"]) for f in frames] == success.astype(float).tolist()
        assert {f["task"] for f in frames} == {outcome["prompt"]}
        assert {int(f["perturbation"]) for f in frames} == {PERTURB.index(outcome["perturbation"])}
        # each frame is what the robot saw before its action: the next frame's state is this one moved by it
        episode = perturb.Perturbation.parse(outcome["perturbation"]).episode(outcome["seed"])
        for frame, following in zip(frames, [*frames[1:], None], strict=True):
            state = np.asarray(frame[keys[demo_reach.STATE_KEY]])
            # the robot moved by the float64 action, the frame holds it as float32: a rounding of 1e-8 per step
            np.testing.assert_allclose(state, episode.state, rtol=0, atol=1e-6)
            episode.state = state
            seen = episode.observe()
            np.testing.assert_array_equal(frame[demo_reach.LEROBOT_TARGET_BOX], np.float32(seen.target_box))
            for key, image in ((demo_reach.IMAGE_KEY, seen.base_image), (demo_reach.WRIST_KEY, seen.wrist_image)):
                error = np.abs(frame[keys[key]].astype(np.int16) - image).mean()
                assert error < CODEC_MEAN_ERROR, (i, int(frame["frame_index"]), key, error)
            episode.execute(np.asarray(frame[keys["actions"]])[None])
            if following is None:
                assert episode.success == outcome["success"]


def test_the_demo_command_records_and_names_each_episodes_perturbation(tmp_path, capsys):
    out = tmp_path / "rec"
    argv = ["demo", "--no-explain", "--num-episodes", "2", "--max-calls", "1", "--perturb", "hue=45", "absent"]
    cli.main([*argv, "--record", str(out)])
    rollouts = json.loads((out / "meta" / quality.EPISODES_FILE).read_text())
    assert rollouts["perturbations"] == ["hue=45", "absent"]
    assert [(e["episode_index"], e["perturbation"]) for e in rollouts["episodes"]] == [(0, "hue=45"), (1, "absent")]
    assert "absent: 0/1" in capsys.readouterr().out
    assert open_dataset(out).episodes == [0, 1]
    with pytest.raises(SystemExit) as exit_info:  # a recording never lands on an earlier one
        cli.main([*argv, "--record", str(out)])
    assert exit_info.value.code == 1 and "is not an empty folder" in capsys.readouterr().out


def test_steps_with_and_without_an_outcome_do_not_mix(tmp_path):
    frame = {"observation.state": np.zeros(2, np.float32), "action": np.zeros(2, np.float32)}
    with RolloutRecorder(tmp_path / "ds", fps=10) as recorder:
        recorder.step(frame, task="t", reward=0.0, success=False, done=False)
        with pytest.raises(DatasetError, match="every step gives an outcome, or none does"):
            recorder.step(frame, task="t")
        with pytest.raises(DatasetError, match="reward, success and done together"):
            recorder.step(frame, task="t", reward=1.0)
        assert recorder.end_episode() == 0
    assert open_dataset(tmp_path / "ds").episode_length(0) == 1


@pytest.fixture(scope="module")
def explained(recorded, tmp_path_factory):
    """The recorded rollouts explained into a maps dataset, carrying the named block's box and each episode's
    perturbation (every 5th frame: where the robot asked the server). The options of tests/datasets' other jobs, so
    compiled programs are shared."""
    root, _ = recorded
    out = tmp_path_factory.mktemp("maps") / "rollouts.maps"
    options = ExplainOptions(target="action-token", maps=("gradcam", "gradnorm"), check_patches=2)
    extra = {demo_reach.LEROBOT_TARGET_BOX: TARGET_BOX, PERTURBATION_FEATURE: GROUP}
    run_local(model_job(root, out, options, batch_size=4, every=5, extra=extra))
    return out


def test_outcome_names_the_feature_an_episodes_success_is_read_from(recorded, tmp_path):
    """`--outcome FEATURE`: an episode succeeded when any of its frames has FEATURE true. Here the perturbation's
    index, true on the `absent` episodes, which all fail by `next.success`: the rows follow the feature named."""
    root, result = recorded
    out = tmp_path / "by_perturbation.maps"
    options = ["--maps", "gradcam", "gradnorm", "--target", "action-token", "--check-patches", "2", "--batch-size", "4"]
    cli.main(["explain-dataset", str(root), "--out", str(out), "--outcome", PERTURBATION_FEATURE, "--every-k", "100",
              *options, "--no-progress"])  # fmt: skip
    maps = open_maps_dataset(out)
    assert maps.info.outcome == PERTURBATION_FEATURE
    by_feature = {i: e["perturbation"] != PERTURB[0] for i, e in enumerate(result.episodes)}
    assert by_feature != {i: e["success"] for i, e in enumerate(result.episodes)}  # not what next.success says
    rows = maps.table(columns=["episode_index", "episode_success"]).to_pylist()
    assert {r["episode_index"] for r in rows} == set(by_feature)
    assert all(r["episode_success"] == by_feature[r["episode_index"]] for r in rows)


def _counted_outcomes(root) -> dict[int, tuple[int, bool, float]]:
    """(length, success, return) of every episode, counted from the LeRobot dataset's frames."""
    ds = open_dataset(root)
    out = {}
    for e in ds.episodes:
        frames = list(ds.frames(e, features=["next.success", "next.reward"]))
        out[e] = (
            len(frames),
            any(bool(f["next.success"]) for f in frames),
            sum(float(f["next.reward"]) for f in frames),
        )
    return out


def test_rows_carry_their_episodes_outcome_read_from_next_success(recorded, explained):
    root, result = recorded
    maps = open_maps_dataset(explained)
    assert maps.info.outcome == "next.success" and maps.info.reward == "next.reward"
    counted = _counted_outcomes(root)
    assert [counted[e][1] for e in sorted(counted)] == [r["success"] for r in result.episodes]
    table = maps.table().to_pylist()
    assert {r["episode_index"] for r in table} == set(counted)
    for row in table:
        assert (row["episode_length"], row["episode_success"], row["episode_return"]) == counted[row["episode_index"]]


def test_stats_show_failures_beside_successes_and_how_well_each_figure_finds_them(recorded, explained, tmp_path):
    out = tmp_path / "stats.json"
    cli.main(["stats", str(explained), "--format", "json", "--out", str(out), "--kind", "gradnorm"])
    data = json.loads(out.read_text())
    outcomes, frames = data["summary"]["outcomes"], data["frames"]
    ranked = {e["episode_index"]: e for e in data["summary"]["episode_ranking"]}
    failed = {e: not ranked[e]["success"] for e in ranked}
    assert 0 < outcomes["failures"] == sum(failed.values()) < outcomes["episodes"] == len(ranked)
    # per outcome: the frames of that outcome's episodes, and the mean of their per-frame figures
    for name, group in outcomes["by_outcome"].items():
        rows = [r for r in frames if failed[r["episode_index"]] == (name == "failure")]
        assert group["frames"] == len(rows) and group["episodes"] == sum(
            f == (name == "failure") for f in failed.values()
        )
        shares = [r["base_0_rgb/share"] for r in rows]
        assert group["cameras"]["base_0_rgb"]["mean_share"] == pytest.approx(np.mean(shares), rel=1e-12)
        nuisance = [r["base_0_rgb/nuisance_mass"] for r in rows]
        assert group["cameras"]["base_0_rgb"]["mean_nuisance_mass"] == pytest.approx(np.mean(nuisance), rel=1e-12)
    # AUROC by hand over the episode ranking's own figures: its entropy (what ranks the episodes), the distance to the
    # prior and the length
    assert all(ranked[e]["entropy"] is not None for e in ranked)
    for figure in ("entropy", "distance", "length"):
        auc = _pair_auc(failed, {e: ranked[e][figure] for e in ranked})
        assert outcomes["failure_finding"][figure]["auroc"] == pytest.approx(auc)
    # early warning: the same from each episode's first explained frame (length is no figure there)
    early = outcomes["early_warning"]
    assert early["frames"] == 1 and "length" not in early["figures"]
    firsts = {e: [r for r in frames if r["episode_index"] == e and r["frame_index"] == 0] for e in ranked}
    nuisance = {e: np.mean([r["base_0_rgb/nuisance_mass"] for r in rows]) for e, rows in firsts.items()}
    auc = _pair_auc(failed, nuisance)
    assert early["figures"]["base_0_rgb/mean_nuisance_mass"]["auroc"] == pytest.approx(auc)


def test_each_perturbation_sets_its_failures_beside_its_successes_with_their_mean_maps(recorded, explained, tmp_path):
    _, result = recorded
    ds = open_maps_dataset(explained)
    views = compute_views(ds, "gradnorm", ViewOptions(group=GROUP))
    table = ds.table(columns=["episode_index", "episode_success"]).to_pydict()
    episode, success = np.array(table["episode_index"]), np.array(table["episode_success"])
    maps = normalised(ds.maps("gradnorm", "base_0_rgb"))[0]
    assert [g[GROUP] for g in views.groups] == list(range(len(PERTURB)))
    for g in views.groups:
        mine = [i for i, e in enumerate(result.episodes) if e["perturbation"] == PERTURB[g[GROUP]]]  # episode i
        assert g["episodes"] == len(mine) and g["successes"] == sum(result.episodes[i]["success"] for i in mine)
        assert g["name"] is None  # recorded without `openpi-cam demo --record`'s episode list
        for name, group in g["by_outcome"].items():
            frames = np.isin(episode, mine) & (success == (name == "success"))
            assert group["frames"] == frames.sum()
            mean = g["mean_maps"][name]["base_0_rgb"]
            if frames.any():  # float32 maps summed in another order: a few float32 ulps of values near 1/16
                np.testing.assert_allclose(mean, maps[frames].mean(axis=0), rtol=1e-5, atol=1e-7)
            else:
                assert mean is None
    out = tmp_path / "render"
    cli.main(["render", str(explained), "--out", str(out), "--no-progress", "--no-videos", "--kind", "gradnorm"])
    html = (out / "index.html").read_text()
    for g in views.groups:
        assert f"{GROUP} {g[GROUP]}: {g['successes']}/{g['episodes']} episodes succeeded" in html
    listed = tmp_path / "listed"
    recorded_episodes_file(listed).parent.mkdir(parents=True)
    recorded_episodes_file(listed).write_text(json.dumps({"perturbations": list(PERTURB)}))
    assert perturbation_names(listed) == list(PERTURB) and perturbation_names(tmp_path / "absent") == []


def _pair_auc(failed: dict[int, bool], values: dict[int, float]) -> float:
    """Over every failed-successful pair of episodes: 1 when the failure's value is larger, 1/2 when tied."""
    pairs = [
        (values[f] > values[s]) + 0.5 * (values[f] == values[s])
        for f in values
        if failed[f]
        for s in values
        if not failed[s]
    ]
    return float(np.mean(pairs))


def test_an_outcome_feature_the_dataset_lacks_is_refused_in_one_line(recorded, tmp_path, capsys):
    root, _ = recorded
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["explain-dataset", str(root), "--out", str(tmp_path / "m"), "--outcome", "next.win", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 1 and len(err.splitlines()) == 1
    assert "feature 'next.win' (--outcome) is not in the dataset" in err


def test_the_report_and_recording_show_each_episodes_outcome(explained, tmp_path):
    from rerun.chunk import RrdReader

    out, rrd = tmp_path / "render", tmp_path / "maps.rrd"
    cli.main(["render", str(explained), "--out", str(out), "--no-progress", "--no-videos", "--rerun", str(rrd)])
    views = compute_views(open_maps_dataset(explained), "gradnorm")
    html = (out / "index.html").read_text()
    assert "failed and successful episodes" in html and "which figure finds the failures?" in html
    for e in views.episodes:  # every episode's section names its outcome
        section = html[html.index(f"id='episode-{e['episode_index']}'") :].split("</h3>")[0]
        assert ("success" if e["success"] else "failure") in section
    logged = {}
    for chunk in RrdReader(str(rrd)).store().stream():
        if chunk.entity_path == "/openpi_cam/success":
            batch = chunk.to_record_batch()
            for episode, value in zip(
                batch.column("episode_index").to_pylist(), batch.column("Scalars:scalars").to_pylist(), strict=True
            ):
                logged.setdefault(episode, set()).add(value[0])
    assert logged == {e["episode_index"]: {float(e["success"])} for e in views.episodes}


def test_reliance_columns_hold_each_frames_reliance_and_the_views_average_them(recorded, tmp_path, capsys):
    root, _ = recorded
    out = tmp_path / "relied.maps"
    argv = ["explain-dataset", str(root), "--out", str(out), "--maps", "gradnorm", "--check-patches", "0"]
    cli.main([*argv, "--every-k", "5", "--episodes", "0,1", "--reliance", "--no-progress"])
    maps = open_maps_dataset(out)
    assert maps.info.reliance and fmt.reliance_columns(maps.info) == [
        f"{name}/reliance_{what}" for name in ("base_0_rgb", "wrist_0_rgb", "prompt") for what in ("score", "actions")
    ]
    rows = maps.table().to_pylist()
    for row in rows:
        assert {k: row[k] for k in fmt.reliance_columns(maps.info)} == Reliance.from_json(
            json.loads(row["reliance"])
        ).figures()
    views = compute_views(maps, "gradnorm")
    for name, group in views.outcomes["by_outcome"].items():
        chosen = [r for r in rows if r["episode_success"] == (name == "success")]
        for column, summary in (
            ("base_0_rgb/reliance_score", group["cameras"]["base_0_rgb"]["mean_reliance_score"]),
            ("prompt/reliance_actions", group["prompt"]["mean_reliance_actions"]),
        ):
            assert summary == pytest.approx(np.mean([r[column] for r in chosen]), rel=1e-12)
    assert "prompt/mean_reliance_score" in views.outcomes["failure_finding"]
