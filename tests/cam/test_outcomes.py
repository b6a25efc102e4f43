"""Outcome statistics on labelled data whose answers are counted by hand: success intervals, and how well a figure
finds failed episodes (ROC AUC, precision at the number of failures)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from openpi_cam.cam.outcomes import bootstrap_auc, finding, precision_at_failures, roc_auc, wilson_interval


def test_wilson_interval_matches_its_closed_form_at_hand_checked_points():
    # 0 of 10: the upper end is z^2 / (n + z^2) = 3.8415 / 13.8415; 5 of 10: 0.5 -+ 0.2634 (Wilson 1927, eq. by hand)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.27753), abs=1e-5)
    assert wilson_interval(5, 10) == pytest.approx((0.23659, 0.76341), abs=1e-5)
    assert wilson_interval(10, 10) == pytest.approx((0.72247, 1.0), abs=1e-5)
    assert all(math.isnan(x) for x in wilson_interval(0, 0))


def test_auroc_and_precision_count_pairs_and_ties_by_hand():
    failed = [True, True, False, False, False]
    scores = [0.9, 0.3, 0.5, 0.1, 0.3]
    # failure/success pairs: 0.9 beats all three (3), 0.3 beats 0.1 (1) and ties 0.3 (0.5), loses to 0.5: 4.5 of 6
    assert roc_auc(failed, scores) == pytest.approx(4.5 / 6)
    # the two highest scores are 0.9 (failed) and 0.5 (succeeded): 1 of 2
    assert precision_at_failures(failed, scores) == pytest.approx(0.5)
    # the second place is shared by a failure and a success tied at 0.3: half a hit
    assert precision_at_failures([True, True, False, False], [0.9, 0.3, 0.3, 0.1]) == pytest.approx(0.75)
    assert roc_auc([True, False], [1.0, 0.0]) == 1.0 and roc_auc([True, False], [0.0, 1.0]) == 0.0
    # an episode without the figure (NaN) takes no part; one class alone has no AUC
    assert roc_auc([True, False, False], [1.0, math.nan, 0.0]) == 1.0
    assert math.isnan(roc_auc([True, True], [0.0, 1.0]))


def test_auroc_is_mann_whitneys_u_and_its_interval_holds_it():
    rng = np.random.default_rng(0)
    failed = rng.random(60) < 0.4
    scores = rng.normal(size=60) + failed * 0.8
    scores[::7] = np.round(scores[::7], 1)  # some ties
    u = stats.mannwhitneyu(scores[failed], scores[~failed]).statistic
    assert roc_auc(failed, scores) == pytest.approx(u / (failed.sum() * (~failed).sum()), rel=1e-12)
    low, high = bootstrap_auc(failed, scores)
    assert low < roc_auc(failed, scores) < high
    report = finding(failed, scores)
    assert report["failures"] == failed.sum() and report["chance_precision"] == pytest.approx(failed.mean())
