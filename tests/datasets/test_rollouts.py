"""Closed-loop rollouts recorded as a LeRobot dataset (`openpi-cam demo --record`): the bundled pi0-FAST served
through the websocket server, driven under perturbations and read back with our LeRobot reader. LeRobot 0.6.1's own
reader opening such a recording is checked outside CI (`benchmarks/check_lerobot_reads.py`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from openpi_cam import cli
from openpi_cam.datasets.lerobot import DatasetError, open_dataset
from openpi_cam.datasets.rollouts import RolloutRecorder
from openpi_cam.demo import perturb, quality
from openpi_cam.demo.run import ROLLOUT_FPS, DemoOptions, run_demo
from openpi_cam.policies import demo_reach

PERTURB = ("clean", "absent")
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
