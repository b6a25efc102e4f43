"""Detection over time: an episode's score at N source frames sees only its first N frames, and the figures come
out in the shape `stats --format json` prints under `outcomes.detection`."""

from __future__ import annotations

import numpy as np
import pytest
from monitor_support import episodes
from one_line import assert_one_line

from openpi_cam.auroc import bootstrap_auc, roc_auc
from openpi_cam.monitor.detection import WHOLE, ScoredEpisode, detection, score_within
from openpi_cam.monitor.fit import FitOptions, fit_monitor


def _late_signal_episodes() -> list[ScoredEpisode]:
    """Explained every 3rd source frame (0, 3, ..., 39). Every episode scores 0 until frame 10; from then on a
    failure scores 1 + its index and a success 0.5."""
    frames = np.arange(0, 40, 3)
    out = []
    for i in range(12):
        failed = i % 3 == 0
        late = 1.0 + i if failed else 0.5
        out.append(ScoredEpisode(frames, {"monitor": np.where(frames >= 10, late, 0.0)}, failed))
    return out


def test_a_failure_signal_from_frame_10_is_invisible_at_8_frames_and_visible_at_16():
    figures = {row["frames"]: row["figures"]["monitor"] for row in detection(_late_signal_episodes(), resamples=200)}
    assert list(figures) == [1, 4, 8, 16, 32, WHOLE]
    for n in (1, 4, 8):
        assert figures[n]["auroc"] == 0.5  # all tied at 0: the steps at frames 0, 3, 6 (and 9 for N = 10) say nothing
    for n in (16, 32, WHOLE):
        assert figures[n]["auroc"] == 1.0  # the step at frame 12 counts from N = 13 on
        assert figures[n]["auroc_ci95"] == [1.0, 1.0]
    assert figures[8]["episodes"] == 12 and figures[8]["failures"] == 4
    # the boundary: a step at frame f counts at N iff f < N
    frames = np.arange(0, 40, 3)
    scores = np.where(frames >= 10, 1.0, 0.0)
    assert score_within(frames, scores, 12) == 0.0 and score_within(frames, scores, 13) == 1.0


def test_the_figures_are_the_auroc_and_interval_of_the_maxima_so_far():
    rng = np.random.default_rng(0)
    scored = []
    for i in range(30):
        length = int(rng.integers(3, 40))
        frames = np.arange(length)
        scored.append(ScoredEpisode(frames, {"a": rng.normal(size=length), "b": rng.normal(size=length)}, i % 2 == 0))
    rows = detection(scored, (4, 16), resamples=300, seed=3)
    failed = [e.failed for e in scored]
    for row, n in zip(rows, (4, 16, None), strict=True):
        expected = [e.scores["b"][: n if n else None].max() for e in scored]  # frames are 0..T-1
        figure = row["figures"]["b"]
        assert figure["auroc"] == pytest.approx(roc_auc(failed, expected))
        assert figure["auroc_ci95"] == pytest.approx(list(bootstrap_auc(failed, expected, resamples=300, seed=3)))
        assert figure["episodes"] == 30 and figure["failures"] == 15
    assert sorted(rows[0]["figures"]) == ["a", "b"]


def test_an_episode_without_a_score_by_n_takes_no_part():
    frames = np.arange(6)
    stac = np.array([np.nan, 0.1, 0.2, 0.3, 0.4, 0.5])  # no previous chunk at the first call
    scored = [ScoredEpisode(frames, {"stac": stac + i}, i >= 2) for i in range(4)]
    rows = {row["frames"]: row["figures"]["stac"] for row in detection(scored, (1, 4), resamples=50)}
    assert rows[1] == {"auroc": None, "auroc_ci95": [None, None], "episodes": 0, "failures": 0}
    assert rows[4]["auroc"] == 1.0 and rows[4]["episodes"] == 4


def test_a_monitor_fitted_on_some_episodes_finds_failures_early_on_others():
    """The monitor's figures over time on fresh episodes: failures drift from step 5 on (source frame 10, two
    frames per step), so the monitor is at chance from the first 4 frames and finds them once frame 10 is in."""
    options = FitOptions(kind="mahalanobis", inputs=("features/base_0_rgb",))
    monitor = fit_monitor(episodes(0, 40, 40, drift=3.0), options)
    fresh = episodes(1, 40, 40, drift=3.0)
    scored = [
        ScoredEpisode(2 * np.arange(16), {"monitor": monitor.score_steps(e.matrix(monitor.inputs))}, not e.success)
        for e in fresh
    ]
    figures = {row["frames"]: row["figures"]["monitor"] for row in detection(scored, (4, 16), resamples=500)}
    low, high = figures[4]["auroc_ci95"]
    assert low < 0.5 < high
    assert figures[16]["auroc"] > 0.9 and figures[WHOLE]["auroc"] > 0.9


def test_scores_and_frames_of_different_lengths_are_refused_in_one_line():
    bad = ScoredEpisode(np.arange(5), {"monitor": np.zeros(4)}, True)
    with pytest.raises(ValueError) as e:
        detection([ScoredEpisode(np.arange(3), {"monitor": np.zeros(3)}, False), bad])
    assert_one_line(e.value, "episode 1", "'monitor'", "4 scores", "5 frames")
