"""A stream of served calls through a monitor (`monitor.stream`): each call's signals become its named inputs,
STAC-single against the call before it (only where that call lies one execution horizon earlier), and its score
equals the monitor's offline score of the whole stream."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest
from monitor_support import FEATURE, episodes

from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.monitor.fit import FitOptions, fit_monitor
from openpi_cam.monitor.signals import STAC, TOKEN_ENTROPY, stac_single
from openpi_cam.monitor.stream import DEFAULT_EXECUTION_HORIZON, FLAG, SCORE, Stream, execution_horizon, step_inputs
from openpi_cam.vocabulary import ACTION_TOKENS, NORMALIZED_CHUNK, TOKEN_ENTROPIES


def _calls(rng: np.random.Generator, n: int, drift_from: int | None = None) -> list[dict[str, np.ndarray]]:
    """n calls' signals: a feature, a generation's entropies with its action tokens, and a chunk [10, 2] that follows
    the previous one shifted by the default horizon, plus noise (more of it from `drift_from` on)."""
    calls, path = [], np.cumsum(rng.normal(size=(10 + 5 * n, 2)), axis=0)
    for t in range(n):
        noise = 0.05 if drift_from is None or t < drift_from else 1.5
        flags = np.zeros(12, bool)
        flags[2:9] = True
        calls.append(
            {
                FEATURE: rng.normal(size=6).astype(np.float32) + (0.0 if noise < 1 else 3.0),
                TOKEN_ENTROPIES: rng.random(12).astype(np.float32),
                ACTION_TOKENS: flags,
                NORMALIZED_CHUNK: path[5 * t : 5 * t + 10] + rng.normal(scale=noise, size=(10, 2)),
            }
        )
    return calls


def test_step_inputs_reduce_the_token_entropies_over_the_action_tokens_and_keep_the_features():
    call = _calls(np.random.default_rng(0), 1)[0]
    inputs = step_inputs(call)
    assert set(inputs) == {FEATURE, TOKEN_ENTROPY}
    np.testing.assert_array_equal(inputs[FEATURE], call[FEATURE])
    expected = call[TOKEN_ENTROPIES][2:9].astype(np.float64).mean()
    assert inputs[TOKEN_ENTROPY] == pytest.approx(expected, rel=1e-12)
    # a flow family's call: no entropies, no token_entropy input
    assert set(step_inputs({FEATURE: call[FEATURE], NORMALIZED_CHUNK: call[NORMALIZED_CHUNK]})) == {FEATURE}


def test_stac_compares_each_call_with_the_previous_over_their_overlap_and_only_when_it_follows():
    calls = _calls(np.random.default_rng(1), 4)
    stream = Stream(None, DEFAULT_EXECUTION_HORIZON)
    first, second = stream.step(calls[0]), stream.step(calls[1])
    assert math.isnan(first.inputs[STAC]) and first.score is None and first.flag is None
    assert second.inputs[STAC] == stac_single(calls[0][NORMALIZED_CHUNK], calls[1][NORMALIZED_CHUNK], 5)
    assert 0 < second.inputs[STAC] < 0.5  # the chunks agree where they overlap, up to their noise
    # a call that does not follow the previous one by the horizon (offline: another frame spacing) has no STAC
    assert math.isnan(stream.step(calls[2], follows=False).inputs[STAC])
    assert not math.isnan(stream.step(calls[3]).inputs[STAC])
    assert set(second.arrays()) == {FEATURE, TOKEN_ENTROPY, STAC}  # no score or flag without a monitor


def test_a_monitored_stream_scores_each_call_as_the_monitor_scores_the_whole_episode():
    """One call at a time, as the side channel scores a connection, gives the very numbers the monitor gives the
    whole stream's inputs at once (a maps dataset's fit and detection figures)."""
    rng = np.random.default_rng(2)
    monitor = fit_monitor(episodes(3, 12, 12), FitOptions(kind="mahalanobis", inputs=(FEATURE, STAC), alpha=0.2))
    calls = _calls(rng, 8, drift_from=4)
    stream = Stream(monitor, execution_horizon(monitor))
    scored = [stream.step(call) for call in calls]
    inputs = np.array([[*s.inputs[FEATURE], s.inputs[STAC]] for s in scored])
    np.testing.assert_array_equal([s.score for s in scored], monitor.score_steps(inputs))
    flags = [s.flag for s in scored]
    crossed = np.flatnonzero(monitor.score_steps(inputs) > monitor.threshold)
    assert crossed.size and crossed[0] >= 4  # the drifting calls are what crosses
    assert flags == [t >= crossed[0] for t in range(len(calls))]  # flagged from the first crossing on, for good
    assert scored[-1].arrays()[SCORE] == scored[-1].score and scored[-1].arrays()[FLAG]


def test_a_monitor_reading_an_input_the_call_lacks_is_refused_naming_it():
    monitor = fit_monitor(episodes(4, 6, 2), FitOptions(kind="mahalanobis", inputs=(FEATURE,)))
    call = _calls(np.random.default_rng(5), 1)[0]
    del call[FEATURE]
    with pytest.raises(ValueError, match=f"no monitor input {FEATURE!r}"):
        Stream(monitor, 5).step(call)
    with pytest.raises(ValueError, match="served without signals"):
        Stream(monitor, 5).step({FEATURE: np.zeros(6)})
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        Stream(monitor, 0)


def test_a_live_connection_under_an_instruction_the_policy_never_learnt_is_flagged_at_once_and_counted(caplog):
    """`serve --monitor` with a gated monitor told the policy's instructions: a connection served under another one
    is flagged at its first call (no STAC yet), counted once in `/stats` however many calls it makes, and logged
    once with its instruction; a connection under a trained instruction it was not fitted on is scored by STAC and
    not counted. A closed connection leaves the open set, not the count."""
    prompted = [
        dataclasses.replace(e, prompts=("press the button",) * len(e.columns[STAC])) for e in episodes(3, 20, 10)
    ]
    options = FitOptions(kind="gated", inputs=(FEATURE, STAC), trained_on=("press the button", "open the door"))
    live = LiveMonitor(fit_monitor(prompted, options), "m.json")
    assert math.isfinite(live.monitor.threshold)
    rng = np.random.default_rng(4)
    with caplog.at_level(logging.WARNING, logger="openpi_cam.cam.monitoring"):
        for connection, prompt in [("a", "Open the drawer"), ("b", "open the door"), ("a", "Open the drawer")]:
            for call in _calls(rng, 3):
                scored = live.score(connection, call, prompt)
                if connection == "a":
                    assert scored.flag and scored.score >= live.monitor.threshold + 1
                else:
                    assert math.isnan(scored.score) or scored.score < live.monitor.threshold + 1
        live.closed("a")
    stats = live.stats()
    assert stats["connections_untrained"] == 1 and stats["connections_open"] == 1
    (line,) = [r.getMessage() for r in caplog.records]
    assert "connection a" in line and "'Open the drawer'" in line and line.endswith("(flagged)")
