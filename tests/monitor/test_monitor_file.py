"""The monitor file (a round trip that scores alike, bad files refused in one line) and the running episode score
(live, one step at a time, equal to the offline score of the whole episode)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from monitor_support import FEATURE, episode, episodes
from one_line import assert_one_line

from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.fit import FitOptions, fit_monitor
from openpi_cam.monitor.monitor_file import Monitor

PROMPT = "press the button"


@pytest.fixture(scope="module")
def monitors() -> dict[str, Monitor]:
    data = episodes(0, 30, 30)
    prompted = [dataclasses.replace(e, prompts=(PROMPT,) * len(e.columns["stac"])) for e in data]
    return {
        "gated": fit_monitor(
            prompted, FitOptions(kind="gated", inputs=(FEATURE, "stac"), temporal=True, trained_on=(PROMPT, "x"))
        ),
        "probe": fit_monitor(data, FitOptions(kind="probe", inputs=(FEATURE, "stac"), temporal=True)),
        "mahalanobis": fit_monitor(data, FitOptions(kind="mahalanobis", inputs=(FEATURE,), max_dims=4)),
        "stac": fit_monitor(data, FitOptions(kind="stac", execution_horizon=5)),
        "union": fit_monitor(data, FitOptions(kind="union", inputs=(FEATURE, "stac"), temporal=True)),
    }


def _steps(e) -> list[dict[str, np.ndarray]]:
    return [{name: column[t] for name, column in e.columns.items()} for t in range(len(e.columns["stac"]))]


@pytest.mark.parametrize("kind", monitor_file.KINDS)
def test_a_saved_monitor_loads_to_the_same_scores(monitors, kind, tmp_path):
    monitor = monitors[kind]
    path = monitor_file.save(monitor, tmp_path / "monitor.json")
    loaded = monitor_file.load(path)
    assert monitor_file.to_json(loaded) == monitor_file.to_json(monitor)
    fresh = episode(np.random.default_rng(9), False)
    x = fresh.matrix(monitor.inputs)
    # float64 arrays survive JSON exactly, so the scores are the same numbers, not merely close ones
    np.testing.assert_array_equal(loaded.score_steps(x, PROMPT), monitor.score_steps(x, PROMPT))
    assert loaded.threshold == monitor.threshold and loaded.execution_horizon == monitor.execution_horizon


@pytest.mark.parametrize("kind", monitor_file.KINDS)
def test_the_running_score_is_the_offline_score_step_by_step(monitors, kind):
    """What the side channel computes one call at a time equals what a maps dataset computes over the episode,
    the temporal probe's running mean and a first step without STAC included."""
    monitor = monitors[kind]
    e = episode(np.random.default_rng(10), False, onset=3, drift=4.0)
    offline = monitor.score_steps(e.matrix(monitor.inputs), PROMPT)
    running = monitor.episode()
    live = [running.update(step, PROMPT) for step in _steps(e)]
    np.testing.assert_array_equal(live, offline)  # the same numbers (NaN where STAC has none)
    assert running.score == np.nanmax(offline) and running.steps == len(offline)
    crossed = np.flatnonzero(offline > monitor.threshold)
    assert running.flagged_at == (int(crossed[0]) if crossed.size else None)
    assert running.flagged  # a failure drifting far from step 3 on is caught by every monitor here


def test_a_step_scored_alone_is_scored_as_in_its_episode(monitors):
    monitor = monitors["mahalanobis"]
    e = episode(np.random.default_rng(12), True)
    assert [monitor.score(step) for step in _steps(e)] == list(monitor.score_steps(e.matrix(monitor.inputs)))
    with pytest.raises(ValueError) as err:
        monitors["probe"].score(_steps(e)[0])  # temporal: its score needs the episode so far
    assert_one_line(err.value, "temporal", "Monitor.episode()")


def test_a_monitor_that_never_flags_saves_its_threshold_as_null(monitors, tmp_path):
    monitor = monitors["stac"]
    never = Monitor(kind="stac", inputs=monitor.inputs, threshold=math.inf, alpha=0.01)
    path = monitor_file.save(never, tmp_path / "never.json")
    assert json.loads(path.read_text())["threshold"] is None
    running = monitor_file.load(path).episode()
    running.update({"stac": 1e300})
    assert not running.flagged


def test_a_step_without_a_monitor_input_is_refused_in_one_line(monitors):
    step = _steps(episode(np.random.default_rng(11), True))[1]
    with pytest.raises(ValueError) as e:
        monitors["probe"].episode().update({FEATURE: step[FEATURE]})
    assert_one_line(e.value, "'stac'")
    with pytest.raises(ValueError) as e:
        monitors["probe"].episode().update({FEATURE: step[FEATURE][:3], "stac": 0.1})
    assert_one_line(e.value, FEATURE, "3 values", "expects 6")


def _corrupt(data: dict, change: str) -> dict | str:
    if change == "truncated":
        return json.dumps(data)[:200]
    if change == "format":
        data["format"] = "something else"
    elif change == "version":
        data["format_version"] = 99
    elif change == "kind":
        data["kind"] = "vibes"
    elif change == "weights":
        data["probe"]["weights"] = data["probe"]["weights"][:-1]
    elif change == "ragged":
        data["basis"]["components"] = [[0.0], [1.0, 2.0]]
    elif change == "scale":
        data["basis"]["scale"][0] = 0.0
    elif change == "basis":
        del data["basis"]
    elif change == "alpha":
        data["alpha"] = 1.5
    elif change == "threshold":
        data["threshold"] = "high"
    elif change == "inputs":
        data["inputs"].append(dict(data["inputs"][0]))
    return data


@pytest.mark.parametrize(
    ("change", "named"),
    [
        ("truncated", "not a JSON monitor file"),
        ("format", "something else"),
        ("version", "format_version 99"),
        ("kind", "vibes"),
        ("weights", "probe.weights"),
        ("ragged", "basis.components"),
        ("scale", "basis.scale"),
        ("basis", "basis"),
        ("alpha", "alpha 1.5"),
        ("threshold", "threshold 'high'"),
        ("inputs", "twice"),
    ],
)
def test_a_bad_monitor_file_is_refused_in_one_line_naming_it(monitors, tmp_path, change, named):
    data = monitor_file.to_json(monitors["probe"])
    data["basis"]["components"] = [list(data["basis"]["mean"])]  # a projection, so its shape can go wrong
    data["probe"]["weights"] = [0.0]
    bad = _corrupt(json.loads(json.dumps(data)), change)
    path = Path(tmp_path / "monitor.json")
    path.write_text(bad if isinstance(bad, str) else json.dumps(bad))
    with pytest.raises(ValueError) as e:
        monitor_file.load(path)
    assert_one_line(e.value, str(path), named)


@pytest.mark.parametrize(
    ("change", "named"),
    [("union", "union is missing"), ("scale", "standard deviation <= 0"), ("stac", "reads 'stac' among its inputs")],
)
def test_a_bad_union_monitor_file_is_refused_in_one_line(monitors, tmp_path, change, named):
    data = json.loads(json.dumps(monitor_file.to_json(monitors["union"])))
    if change == "union":
        del data["union"]
    elif change == "scale":
        data["union"]["stac"][1] = 0.0
    else:  # the STAC input renamed: the union has nothing to read its second score from
        data["inputs"] = [i if i["name"] != "stac" else {**i, "name": "other"} for i in data["inputs"]]
    path = tmp_path / "monitor.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError) as e:
        monitor_file.load(path)
    assert_one_line(e.value, str(path), named)


@pytest.mark.parametrize(
    ("prompts", "named"),
    [([], "prompts is empty"), (["Press the button"], "not a list of instructions"), ("press", "not a list")],
)
def test_a_bad_gated_monitor_file_is_refused_in_one_line(monitors, tmp_path, prompts, named):
    data = {**monitor_file.to_json(monitors["gated"]), "prompts": prompts}
    path = tmp_path / "monitor.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError) as e:
        monitor_file.load(path)
    assert_one_line(e.value, str(path), named)


@pytest.mark.parametrize(
    ("kind", "trained_on", "named"),
    [
        ("gated", ["Open the door"], "trained_on is not a list of instructions"),
        ("gated", "open the door", "trained_on is not a list"),
        ("union", ["open the door"], "only a gated one"),
    ],
)
def test_a_bad_list_of_the_policys_instructions_is_refused_in_one_line(monitors, tmp_path, kind, trained_on, named):
    data = {**monitor_file.to_json(monitors[kind]), "trained_on": trained_on}
    path = tmp_path / "monitor.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError) as e:
        monitor_file.load(path)
    assert_one_line(e.value, str(path), named)


def test_a_format_2_gated_file_loads_not_knowing_the_policys_instructions(monitors, tmp_path):
    """Files written before `trained_on` (format 2, the shipped monitors of round 4) load as monitors that know only
    the instructions they were fitted on: a step under any other is scored by STAC alone, never flagged outright."""
    data = monitor_file.to_json(monitors["gated"])
    del data["trained_on"]
    path = tmp_path / "monitor.json"
    path.write_text(json.dumps({**data, "format_version": 2}))
    loaded = monitor_file.load(path)
    assert loaded.trained_on == () and loaded.trust("open the door") == monitor_file.TRAINED
    assert monitors["gated"].trust("open the door") == monitor_file.UNTRAINED


def test_a_saved_monitor_puts_each_list_of_numbers_on_one_line(monitors, tmp_path):
    """A refitted monitor's file (and its diff) grows with its rows: one line per vector and per matrix row, the
    structure around them indented."""
    wide = episodes(0, 30, 30, noise_dims=90)  # a feature wider than max_dims: a projection matrix to save
    monitor = fit_monitor(wide, FitOptions(kind="union", inputs=(FEATURE, "stac"), max_dims=4))
    text = monitor_file.save(monitor, tmp_path / "monitor.json").read_text()
    data = monitor_file.to_json(monitor)
    assert json.loads(text) == data
    rows = len(data["basis"]["components"])
    numbers = rows * len(data["basis"]["components"][0])
    lines = text.splitlines()
    assert len(lines) < rows + 60 < numbers  # a row a line, not a number a line
    assert any(line.strip().startswith('"weights": [') and line.rstrip().endswith("],") for line in lines)
    assert lines[1].startswith(' "format"')  # the structure indented, one key a line


def _spread_data(monitors) -> dict:
    """A probe's file rewritten to read `sample_spread` in place of `stac`, its samples per call named."""
    data = json.loads(json.dumps(monitor_file.to_json(monitors["probe"])))
    data["inputs"] = [i if i["name"] != "stac" else {**i, "name": "sample_spread"} for i in data["inputs"]]
    data["sample_spread"] = 4
    return data


def test_a_monitor_reading_the_sample_spread_names_its_samples_and_round_trips(monitors, tmp_path):
    path = tmp_path / "spread.json"
    path.write_text(json.dumps(_spread_data(monitors)))
    loaded = monitor_file.load(path)
    assert loaded.sample_spread == 4 and "sample_spread" in [i.name for i in loaded.inputs]
    again = monitor_file.load(monitor_file.save(loaded, tmp_path / "again.json"))
    assert again.sample_spread == 4 and monitor_file.to_json(again) == monitor_file.to_json(loaded)
    assert monitors["probe"].sample_spread is None  # one that reads no spread names no count


def _refused(data: dict, tmp_path: Path, *named: str) -> None:
    path = tmp_path / "monitor.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError) as e:
        monitor_file.load(path)
    assert_one_line(e.value, str(path), *named)


@pytest.mark.parametrize(
    ("count", "named"),
    [
        (None, "sample_spread None: a monitor that reads 'sample_spread' names its samples"),
        (1, "sample_spread 1"),
        ("four", "sample_spread 'four' is not an integer"),
    ],
)
def test_a_spread_monitor_without_a_usable_sample_count_is_refused_in_one_line(monitors, tmp_path, count, named):
    _refused({**_spread_data(monitors), "sample_spread": count}, tmp_path, named)


def test_a_sample_count_on_a_monitor_that_reads_no_spread_is_refused_in_one_line(monitors, tmp_path):
    data = json.loads(json.dumps(monitor_file.to_json(monitors["probe"])))
    _refused({**data, "sample_spread": 4}, tmp_path, "sample_spread 4: a monitor that reads")


def test_a_missing_monitor_file_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError) as e:
        monitor_file.load(tmp_path / "absent.json")
    assert_one_line(e.value, "absent.json", "no such monitor file")
