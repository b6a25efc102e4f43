"""Faithfulness metrics: each definition checked on inputs whose answer is known by hand."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from openpi_cam.cam import faithfulness as fm

GRID = (2, 3)


class RecordingScore:
    """A re-scoring callback over a 2 x 3 grid that records every mask stack it is given.

    score(masks) = 10 - sum of painted patch effects - 5 if both patches 1 and 3 are painted: the interaction makes
    the drop of a set differ from the sum of its patches' drops, so painting any other set than the claimed one
    gives other numbers."""

    effects = np.array([0.5, 4.0, -1.0, 2.0, 1.5, 0.0])

    def __init__(self):
        self.calls: list[np.ndarray] = []

    def __call__(self, masks: np.ndarray) -> np.ndarray:
        masks = np.asarray(masks, bool)
        self.calls.append(masks.copy())
        flat = masks.reshape(masks.shape[0], -1)
        return 10.0 - flat @ self.effects - 5.0 * (flat[:, 1] & flat[:, 3])


def test_patch_order_is_signed_descending_with_ties_by_index():
    m = np.array([[0.1, 5.0, -1.0], [3.0, 3.0, 0.0]])
    assert fm.patch_order(m).tolist() == [1, 3, 4, 0, 5, 2]
    # A per-token stack is reduced by its mean over tokens, keeping signs.
    stack = np.stack([m, -m, 3 * m])
    np.testing.assert_allclose(fm.reduce_map(stack), m)
    masks = fm.top_k_masks(fm.patch_order(m), GRID)
    assert masks.shape == (7, 2, 3) and not masks[0].any() and masks[6].all()
    assert masks[2].ravel().tolist() == [False, True, False, True, False, False]


def deletion_of(orders: dict[str, np.ndarray], score: RecordingScore, **kw) -> tuple[fm.Deletion, fm.DeletionMasks]:
    """What `evaluate_run` does for one camera: the masks, one re-scoring call, the curves."""
    masks = fm.deletion_masks(orders, GRID, **kw)
    return fm.deletion(masks, score(masks.masks)), masks


def test_deletion_paints_the_claimed_patches_and_reports_their_drops():
    score = RecordingScore()
    m = np.array([[0.1, 5.0, -1.0], [3.0, 3.0, 0.0]])  # order 1, 3, 4, 0, 5, 2
    result, masks = deletion_of({"m": fm.patch_order(m)}, score, random_orders=2)
    (sent,) = score.calls  # one call for the reference, every patch alone, the map's order and the random orders
    assert sent.shape == (1 + 6 + 6 + 2 * 6, 2, 3)
    expected_sets = [[1], [1, 3], [1, 3, 4], [0, 1, 3, 4], [0, 1, 3, 4, 5], [0, 1, 2, 3, 4, 5]]
    assert [np.flatnonzero(k).tolist() for k in sent[masks.blocks["m"]].reshape(6, -1)] == expected_sets
    # Drops by hand: patch effects plus the interaction once 1 and 3 are both painted.
    np.testing.assert_allclose(result.drops["m"], [4.0, 11.0, 12.5, 13.0, 13.0, 12.0])
    # Each patch alone, row-major, after the unpainted reference: the single-patch occlusion map.
    assert not sent[0].any() and sent[1:7].reshape(6, -1).tolist() == np.eye(6).tolist()
    np.testing.assert_allclose(result.single, RecordingScore.effects.reshape(GRID))


def test_deletion_is_normalised_by_the_single_patch_optimum():
    occlusion = RecordingScore.effects.reshape(GRID)  # the single-patch drops, as a map
    orders = {"own": fm.patch_order(occlusion), "wrong": fm.patch_order(-occlusion)}
    result, _ = deletion_of(orders, RecordingScore(), random_orders=4, seed=0)
    assert result.optimum == 4.0
    assert result.at_k("own", [1])[0] == 1.0  # occlusion's own order: its top patch is the optimum, by definition
    np.testing.assert_allclose(result.at_k("own", (1, 2, 4)), np.array([4.0, 11.0, 13.0]) / 4.0)
    np.testing.assert_allclose(result.auc("own"), np.mean([4.0, 11.0, 12.5, 13.0, 13.0, 12.0]) / 4.0)
    # The reversed order is worse at every k short of painting everything, and random lies in between at k = 1.
    assert np.all(result.curves["wrong"][:-1] < result.curves["own"][:-1]) and result.auc("wrong") < result.auc("own")
    assert result.curves["wrong"][-1] == result.curves["own"][-1]
    assert result.curves["wrong"][0] < result.curves[fm.RANDOM][0] < result.curves["own"][0]
    # The random reference is the mean over the seeded orders' curves.
    rng = np.random.default_rng(0)
    painted = [fm.top_k_masks(rng.permutation(6), GRID)[1:] for _ in range(4)]
    expected = np.mean([10.0 - RecordingScore()(p) for p in painted], axis=0)
    np.testing.assert_allclose(result.drops[fm.RANDOM], expected)
    # `k_max` cuts every curve (and the AUC) at that depth.
    short, _ = deletion_of(orders, RecordingScore(), k_max=2, random_orders=4, seed=0)
    np.testing.assert_allclose(short.curves["own"], [1.0, 11.0 / 4.0])
    np.testing.assert_allclose(short.curves[fm.RANDOM], result.curves[fm.RANDOM][:2])


def test_deletion_without_a_lowering_patch_is_nan():
    """No patch lowers the score: nothing to normalise by, so every fraction is NaN (the report writes null)."""
    masks = fm.deletion_masks({"m": np.arange(6)}, GRID, random_orders=1)
    result = fm.deletion(masks, np.full(len(masks.masks), 3.0))
    assert result.optimum == 0.0 and all(np.isnan(c).all() for c in result.curves.values())
    assert np.isnan(result.auc("m")) and np.isnan(result.at_k(fm.RANDOM, [1])[0])
    with pytest.raises(ValueError, match="scores for"):
        fm.deletion(masks, np.zeros(3))


def test_top1_and_spearman():
    ref = np.arange(6.0).reshape(GRID)
    assert fm.top1_agreement(ref * 2 + 1, ref) and not fm.top1_agreement(-ref, ref)
    assert fm.spearman(ref, ref**3) == pytest.approx(1.0)
    assert fm.spearman(ref, -ref) == pytest.approx(-1.0)
    assert np.isnan(fm.spearman(ref, np.zeros(GRID)))
    rng = np.random.default_rng(1)
    a, b = rng.integers(0, 3, (4, 4)).astype(float), rng.normal(size=(4, 4))
    assert fm.spearman(a, b) == pytest.approx(stats.spearmanr(a.ravel(), b.ravel()).statistic)  # ties: average ranks


def test_bootstrap_interval():
    assert fm.bootstrap_mean_ci([2.0] * 10) == (2.0, 2.0, 2.0)
    x = np.random.default_rng(0).normal(1.0, 1.0, size=400)
    mean, lo, hi = fm.bootstrap_mean_ci(x, resamples=4000, seed=3)
    assert mean == pytest.approx(x.mean()) and lo < mean < hi
    # Normal theory: half-width 1.96 * sd / sqrt(n).
    assert (hi - lo) / 2 == pytest.approx(1.96 * x.std() / np.sqrt(x.size), rel=0.15)
    assert fm.bootstrap_mean_ci(x, resamples=4000, seed=3) == (mean, lo, hi)  # seeded
    assert fm.bootstrap_mean_ci([np.nan, 1.0, 3.0], resamples=100)[0] == 2.0  # non-finite dropped


def test_randomisation_and_null():
    rng = np.random.default_rng(2)
    maps = [rng.normal(size=GRID) for _ in range(5)]
    np.testing.assert_allclose(fm.randomisation_abs_spearman(maps, [-2 * m for m in maps]), 1.0)
    null = fm.null_abs_spearman(maps)
    expected = [abs(stats.spearmanr(maps[i].ravel(), maps[(i + 1) % 5].ravel()).statistic) for i in range(5)]
    np.testing.assert_allclose(null, expected)


def test_box_cells_pointing_and_mass():
    # 64 px image, 4 x 4 grid of 16 px patches; box x in [20, 32), y in [0, 17): columns 1, rows 0 and 1.
    cells = fm.box_cells((20, 0, 32, 17), (4, 4), 64)
    assert np.argwhere(cells).tolist() == [[0, 1], [1, 1]]
    assert fm.pointing_chance(cells) == 2 / 16
    m = np.zeros((4, 4))
    m[1, 1], m[3, 3], m[0, 0] = 3.0, 1.0, -5.0
    assert fm.pointing_hit(m, cells)
    assert fm.mass_on_target(m, cells) == 0.75  # the negative patch carries no mass
    assert fm.nuisance_mass_ratio(m, cells) == 0.25
    assert not fm.pointing_hit(-np.abs(m), cells)  # no positive peak: a miss
    assert np.isnan(fm.mass_on_target(-np.abs(m), cells))
    m[3, 3] = 4.0
    assert not fm.pointing_hit(m, cells)
    # A stack is averaged over tokens before pointing.
    stack = np.stack([m, np.where(cells, 10.0, 0.0)])
    assert fm.pointing_hit(stack, cells)


def test_a_hidden_target_is_not_scored():
    """Simulators send an empty box (zeros) for a target out of view or fully occluded: no patch can hold it, so the
    step gives no pointing figure rather than a miss at chance 0."""
    assert fm.client_box_cells((0, 0, 0, 0), None, (4, 4), (64, 64)) is None
    assert fm.client_box_cells((10, 10, 10, 30), None, (4, 4), (64, 64)) is None  # zero width
    visible = fm.client_box_cells((20, 0, 32, 17), None, (4, 4), (64, 64))
    assert visible is not None and visible.sum() == 2
    assert not fm.box_visible((5, 5, 5, 5)) and fm.box_visible((5, 5, 6, 6))
