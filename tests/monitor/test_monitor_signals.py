"""The per-call signals of the failure monitor, on hand-made arrays whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest
from one_line import assert_one_line
from scipy import special, stats

from openpi_cam.monitor.signals import (
    entropies_from_logits,
    pool_spans,
    sample_spread,
    stac_aligned,
    stac_single,
    token_entropy,
)


def test_stac_is_zero_where_consecutive_chunks_agree_over_their_overlap():
    rng = np.random.default_rng(0)
    previous = rng.normal(size=(10, 3))
    # the robot executed 3 actions; the new chunk continues the old one exactly, then adds 3 steps of its own
    current = np.concatenate([previous[3:], rng.normal(size=(3, 3))])
    assert stac_single(previous, current, 3) == 0.0
    # the same chunks read with the wrong execution count disagree
    assert stac_single(previous, current, 2) > 0.5


def test_stac_is_the_mean_per_step_euclidean_distance_over_the_overlap():
    previous = np.zeros((6, 3))
    current = np.zeros((6, 3))
    current[0] = [3.0, 4.0, 0.0]  # 5 away from previous[2]
    current[1] = [0.0, 0.0, 1.0]  # 1 away from previous[3]
    # executed 2: the overlap is previous[2:6] against current[0:4], 4 steps with distances 5, 1, 0, 0
    assert stac_single(previous, current, 2) == pytest.approx(6.0 / 4)
    # a constant offset c over every overlapping step gives ||c||
    offset = np.array([0.3, -0.4, 1.2])
    assert stac_single(previous, previous[1:] + offset, 1) == pytest.approx(float(np.linalg.norm(offset)))
    # a shorter current chunk: the overlap is its own length (2 steps, distances 5 and 1)
    assert stac_single(previous, current[:2], 2) == pytest.approx(3.0)
    # no overlap: no figure
    assert math.isnan(stac_single(previous, current, 6))


def test_stac_refuses_chunks_of_different_action_sizes_in_one_line():
    with pytest.raises(ValueError) as e:
        stac_single(np.zeros((4, 3)), np.zeros((4, 2)), 1)
    assert_one_line(e.value, "3", "2")


def test_stac_aligned_finds_the_true_execution_count():
    # a smooth random trajectory: any wrong shift compares points of the path that lie apart
    rng = np.random.default_rng(1)
    path = np.cumsum(rng.normal(size=(40, 4)), axis=0)
    for executed in (1, 4, 7):
        previous = path[10:20]
        current = path[10 + executed : 20 + executed] + rng.normal(scale=1e-3, size=(10, 4))
        value, shift = stac_aligned(previous, current)
        assert shift == executed
        assert value == pytest.approx(stac_single(previous, current, executed))
    # the true shift 8 overlaps by 2 steps: found with any overlap allowed, left out when 3 are required
    assert stac_aligned(path[:10], path[8:18]) == (0.0, 8)
    value, shift = stac_aligned(path[:10], path[8:18], min_overlap=3)
    assert shift <= 7 and value > 0.5
    assert math.isnan(stac_aligned(path[:1], path[:5])[0])


def test_token_entropy_is_the_mean_entropy_over_the_action_tokens():
    rng = np.random.default_rng(2)
    logits = rng.normal(scale=3.0, size=(6, 11))
    expected = stats.entropy(special.softmax(logits, axis=-1), axis=-1)
    assert entropies_from_logits(logits) == pytest.approx(expected, rel=1e-12)
    # a uniform distribution over V tokens has entropy log V, even from huge equal logits
    assert entropies_from_logits(np.full((1, 7), 1e4)) == pytest.approx([math.log(7)])
    entropies = np.array([9.0, 1.0, 2.0, 3.0, 9.0])
    action = np.array([False, True, True, True, False])  # the prefix and the end token are left out
    assert token_entropy(entropies, action) == pytest.approx(2.0)
    assert token_entropy(entropies) == pytest.approx(4.8)
    assert math.isnan(token_entropy(entropies, np.zeros(5, bool)))


def test_pooling_is_the_mean_over_each_spans_valid_tokens():
    features = np.arange(12.0).reshape(6, 2)  # token t has features (2t, 2t + 1)
    valid = np.array([True, True, True, True, True, False])  # the last prompt token is padding
    pooled = pool_spans(features, {"base_0_rgb": (0, 3), "prompt": (3, 6)}, valid)
    assert pooled["base_0_rgb"] == pytest.approx([2.0, 3.0])  # tokens 0..2
    assert pooled["prompt"] == pytest.approx([7.0, 8.0])  # tokens 3, 4 (5 is padding)
    assert np.isnan(pool_spans(features, {"empty": (5, 6)}, valid)["empty"]).all()
    with pytest.raises(ValueError) as e:
        pool_spans(features, {"wrist": (4, 9)})
    assert_one_line(e.value, "wrist", "6 tokens")


def test_sample_spread_is_the_mean_per_step_rms_spread():
    rng = np.random.default_rng(3)
    mean = rng.normal(size=(5, 3))
    d = rng.normal(size=(5, 3))
    # two samples mean -+ d / 2: each dimension's variance (ddof 1) is d_j^2 / 2, so a step's spread is ||d|| / sqrt 2
    chunks = np.stack([mean - d / 2, mean + d / 2])
    assert sample_spread(chunks) == pytest.approx(float(np.linalg.norm(d, axis=1).mean() / math.sqrt(2)))
    assert sample_spread(np.stack([mean] * 4)) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError) as e:
        sample_spread(mean[None])
    assert_one_line(e.value, "N >= 2")
