"""Fitting a failure monitor: each estimator against an independent computation (SciPy, the paper's formula, a
general-purpose optimiser), the conformal threshold against its guarantee in seeded simulations, and the whole fit
against fresh episodes from the same synthetic distribution."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from monitor_support import FEATURE, episode, episodes
from one_line import assert_one_line
from scipy import optimize
from scipy.spatial import distance

from openpi_cam.auroc import roc_auc
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.fit import (
    Episode,
    FitOptions,
    conformal_threshold,
    episode_max,
    fit_basis,
    fit_logistic,
    fit_mahalanobis,
    fit_monitor,
    leading_directions,
    ledoit_wolf,
    split_episodes,
)


def test_mahalanobis_without_shrinkage_equals_scipys():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 4)) @ rng.normal(size=(4, 4)) + [1.0, -2.0, 0.5, 3.0]
    basis = fit_basis(x, max_dims=8)  # 4 inputs: standardised, not projected
    scorer, rho = fit_mahalanobis(basis, x, shrinkage=0.0)
    assert basis.components is None and rho == 0.0 and scorer.residual_variance == 0.0
    # the fit's covariance is the sample covariance with ddof 0 (bias=True); the distance is invariant under the
    # standardisation, so it equals SciPy's in the raw coordinates up to round-off (a 4 x 4 well-conditioned inverse)
    inverse = np.linalg.inv(np.cov(x.T, bias=True))
    points = rng.normal(size=(5, 4)) * 3
    ours = scorer.score(basis.apply(points))
    theirs = [distance.mahalanobis(p, x.mean(axis=0), inverse) for p in points]
    assert ours == pytest.approx(theirs, rel=1e-9)


def test_ledoit_wolf_follows_its_formula_and_shrinks_when_it_should():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(30, 8)) @ rng.normal(size=(8, 8))
    cov, rho = ledoit_wolf(x)
    # Ledoit and Wolf's lemma written out term by term (the module uses an algebraic shortcut for the scatter)
    c = x - x.mean(axis=0)
    n, p = c.shape
    s = c.T @ c / n
    mu = np.trace(s) / p
    d2 = ((s - mu * np.eye(p)) ** 2).sum()
    b2 = sum(((np.outer(row, row) - s) ** 2).sum() for row in c) / n**2
    expected = min(b2, d2) / d2
    assert rho == pytest.approx(expected, rel=1e-10)
    assert cov == pytest.approx((1 - expected) * s + expected * mu * np.eye(p), rel=1e-10)
    # isotropic data seen through few rows: most of S's departure from mu I is noise, so it shrinks hard; strongly
    # correlated data seen through many rows: S is trustworthy, so it barely shrinks
    assert ledoit_wolf(rng.normal(size=(10, 8)))[1] > 0.5
    assert ledoit_wolf(rng.normal(size=(5000, 3)) @ np.array([[1, 0.9, 0.9], [0, 0.4, 0], [0, 0, 0.4]]))[1] < 0.01


def test_the_basis_projects_onto_the_leading_principal_directions():
    rng = np.random.default_rng(2)
    latent = rng.normal(size=(400, 3)) * [3.0, 2.0, 1.0]  # three directions of distinct variance, then noise
    x = latent @ rng.normal(size=(3, 20)) + rng.normal(scale=0.01, size=(400, 20))
    basis = fit_basis(x, max_dims=3)
    z = (x - x.mean(axis=0)) / x.std(axis=0)
    _, eigenvectors = np.linalg.eigh(np.cov(z.T, bias=True))
    top = eigenvectors[:, ::-1][:, :3]
    assert basis.components is not None and basis.components.shape == (3, 20)
    # the same directions up to sign, each with its largest entry positive
    assert np.abs(basis.components @ top) == pytest.approx(np.eye(3), abs=1e-6)
    rows = np.arange(3)
    assert (basis.components[rows, np.abs(basis.components).argmax(axis=1)] > 0).all()
    # a missing input is imputed by its mean: it moves nothing
    probe = x[:1].copy()
    probe[0, 4] = np.nan
    filled = x[:1].copy()
    filled[0, 4] = basis.mean[4]
    assert basis.apply(probe) == pytest.approx(basis.apply(filled))


def test_each_wide_input_is_projected_alone_and_a_scalar_beside_it_is_kept():
    """A feature 20 wide whose variance dwarfs a scalar signal's, fitted as two inputs with max_dims 3: the feature
    is projected onto its own 3 leading directions and the scalar kept as it is (projected together, the scalar's
    one column of 21 would be lost among the feature's directions)."""
    rng = np.random.default_rng(3)
    latent = rng.normal(size=(300, 3)) * [3.0, 2.0, 1.0]
    feature = latent @ rng.normal(size=(3, 20)) * 100 + rng.normal(scale=0.01, size=(300, 20))
    scalar = rng.normal(size=(300, 1))
    x = np.hstack([feature, scalar])
    basis = fit_basis(x, max_dims=3, widths=[20, 1])
    assert basis.components is not None and basis.components.shape == (4, 21)
    alone = fit_basis(feature, max_dims=3)
    np.testing.assert_allclose(basis.components[:3, :20], alone.components, atol=1e-9)
    assert (basis.components[:3, 20] == 0).all() and basis.components[3].tolist() == [0.0] * 20 + [1.0]
    # the scalar's standardised value reaches the coordinates unchanged; projected together it would not
    z = basis.apply(x)
    np.testing.assert_allclose(z[:, 3], (scalar[:, 0] - scalar.mean()) / scalar.std(), rtol=1e-12)
    together = fit_basis(x, max_dims=3).components
    assert np.abs(together[:, 20]).max() < 0.1
    with pytest.raises(ValueError, match="do not add up"):
        fit_basis(x, max_dims=3, widths=[20])


def test_the_randomised_directions_capture_what_the_exact_ones_do():
    """On a spectrum with no gap to speak of (singular values 1 / i), the k directions found capture the variance
    the exact top k capture: measured above 0.99999 of it for k = 5, 10, 32 on this matrix; asserted at 0.9999."""
    rng = np.random.default_rng(6)
    u = np.linalg.qr(rng.normal(size=(400, 300)))[0]
    v = np.linalg.qr(rng.normal(size=(600, 300)))[0]
    a = (u / np.arange(1, 301)) @ v.T
    exact = np.linalg.svd(a, full_matrices=False)[2]
    for k in (5, 10, 32):
        found = leading_directions(a, k)
        assert found @ found.T == pytest.approx(np.eye(k), abs=1e-10)
        assert ((a @ found.T) ** 2).sum() / ((a @ exact[:k].T) ** 2).sum() > 0.9999


def _toy_probe_data(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z = rng.normal(size=(200, 3))
    side = z @ np.array([1.5, -1.0, 0.5]) + 0.3
    z = z[np.abs(side) > 0.5][:120]  # separable by a plane, with a margin
    failed = side[np.abs(side) > 0.5][:120] > 0
    weights = rng.uniform(0.2, 2.0, size=len(z))
    return z, failed, weights


def test_the_probe_separates_a_separable_set():
    z, failed, weights = _toy_probe_data(np.random.default_rng(3))
    probe = fit_logistic(z, failed, weights, l2=1e-3)
    assert ((probe.score(z) > 0) == failed).all()


def test_the_probe_is_the_minimum_a_general_optimiser_finds():
    z, failed, weights = _toy_probe_data(np.random.default_rng(4))
    l2 = 0.1
    probe = fit_logistic(z, failed, weights, l2=l2)
    w = weights / weights.sum()
    x = np.hstack([z, np.ones((len(z), 1))])
    penalty = np.array([l2, l2, l2, 0.0])

    def objective(theta: np.ndarray) -> tuple[float, np.ndarray]:
        m = x @ theta
        value = (w * (np.logaddexp(0, m) - failed * m)).sum() + 0.5 * (penalty * theta**2).sum()
        return value, x.T @ (w * (_expit(m) - failed)) + penalty * theta

    result = optimize.minimize(objective, np.zeros(4), jac=True, method="BFGS", options={"gtol": 1e-11})
    # the objective is strictly convex; both solvers stop at gradients below 1e-10, so their minimisers agree far
    # inside the stated 1e-6 (the Hessian's smallest eigenvalue bounds the distance by |gradient| / eigenvalue)
    assert np.append(probe.weights, probe.bias) == pytest.approx(result.x, abs=1e-6)


def _expit(m: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-m))


def test_the_probe_refuses_one_class_in_one_line():
    with pytest.raises(ValueError) as e:
        fit_logistic(np.zeros((4, 2)), np.zeros(4, bool))
    assert_one_line(e.value, "both failed and successful")


def test_the_conformal_threshold_is_the_stated_order_statistic():
    maxima = np.arange(9.0, 0.0, -1.0)  # 9..1, unsorted on purpose
    assert conformal_threshold(maxima, 0.2) == 8.0  # k = ceil(10 x 0.8) = 8
    assert conformal_threshold(maxima, 0.05) == math.inf  # k = ceil(9.5) = 10 > 9: never flag
    # n = 19, alpha = 0.1: k = ceil(20 x 0.9) = 18, although 20 x 0.9 is 18.000000000000004 in binary
    assert conformal_threshold(np.arange(1.0, 20.0), 0.1) == 18.0
    # an episode with no score never flags: it counts as the lowest maximum
    assert conformal_threshold([math.nan, 2.0, 1.0, 3.0], 0.4) == 2.0  # k = ceil(3) = 3 of (-inf, 1, 2, 3)
    assert episode_max(np.array([np.nan, 0.5, -1.0])) == 0.5 and episode_max(np.array([np.nan])) == -math.inf


def test_the_conformal_false_alarm_rate_on_fresh_successes_is_at_most_alpha():
    """Seeded simulation of the guarantee: R calibration sets of n successful episodes (T step scores each), and m
    fresh successful episodes per set, all drawn alike; a fresh episode is a false alarm when its maximum step
    score exceeds the set's threshold."""
    rng = np.random.default_rng(5)
    alpha, n, m, steps, sets = 0.1, 30, 50, 20, 4000
    calibration = rng.normal(size=(sets, n, steps)).max(axis=2)
    fresh = rng.normal(size=(sets, m, steps)).max(axis=2)
    thresholds = np.array([conformal_threshold(c, alpha) for c in calibration])
    rate = float((fresh > thresholds[:, None]).mean())
    k = math.ceil((n + 1) * (1 - alpha) - 1e-9)
    # margin: 3 standard errors of the mean rate over the sets; a set's rate varies as Beta(n + 1 - k, k) (the
    # threshold's own draw) plus the binomial spread of m fresh episodes (at most 1 / (4m))
    a, b = n + 1 - k, k
    per_set = a * b / ((a + b) ** 2 * (a + b + 1)) + 1 / (4 * m)
    margin = 3 * math.sqrt(per_set / sets)
    assert rate <= alpha + margin
    # and not conservative beyond the theory: the expected rate is 1 - k / (n + 1) >= alpha - 1 / (n + 1), which a
    # quantile one place too high or low would miss by 1 / (n + 1)
    assert abs(rate - (1 - k / (n + 1))) <= margin


def test_a_fitted_monitor_keeps_its_false_alarm_rate_on_fresh_successes():
    """The whole fit, scorer and split and threshold, over several seeds: the mean false-alarm rate on fresh
    successful episodes from the same distribution stays within alpha plus 3 standard errors. A 30-wide input over
    15 training successes: the distance is smaller on the steps it was fitted on than on new ones, so a threshold
    calibrated on the training episodes would flag fresh successes far more often than alpha."""
    alpha, fresh_n, seeds = 0.1, 200, 20
    rates, expected = [], []
    for seed in range(seeds):
        data = episodes(seed, 30, 10, steps=12, noise_dims=24)
        monitor = fit_monitor(data, FitOptions(kind="mahalanobis", alpha=alpha, seed=seed, inputs=(FEATURE,)))
        fresh = episodes(1000 + seed, fresh_n, 0, steps=12, noise_dims=24)
        maxima = [episode_max(monitor.score_steps(e.matrix(monitor.inputs))) for e in fresh]
        rates.append(np.mean([monitor.flags(s) for s in maxima]))
        n = monitor.fit["calibration_episodes"]
        expected.append((n, math.ceil((n + 1) * (1 - alpha) - 1e-9)))
    (n, k), *_ = expected
    a, b = n + 1 - k, k
    margin = 3 * math.sqrt((a * b / ((a + b) ** 2 * (a + b + 1)) + 1 / (4 * fresh_n)) / seeds)
    assert np.mean(rates) <= alpha + margin


def test_a_fitted_probe_finds_fresh_failures():
    train = episodes(10, 40, 40)
    test = episodes(11, 40, 40)
    for kind in ("probe", "mahalanobis", "stac"):
        monitor = fit_monitor(train, FitOptions(kind=kind, inputs=(FEATURE, "stac") if kind == "probe" else ()))
        maxima = [episode_max(monitor.score_steps(e.matrix(monitor.inputs))) for e in test]
        failed = [not e.success for e in test]
        assert roc_auc(failed, maxima) > 0.9, kind
        flagged = np.array([monitor.flags(s) for s in maxima])
        assert flagged[np.array(failed)].mean() > 0.5, kind  # most failures are caught at alpha = 0.1


def _task(rng: np.random.Generator, n: int, drift: np.ndarray, stac_rise: float) -> list[Episode]:
    """n successes and n failures of one synthetic task: a failure's feature drifts by `drift` and its STAC rises by
    `stac_rise` from step 4 on."""
    out = []
    for i in range(2 * n):
        e = episode(rng, i < n, drift=0.0)
        features, stac = e.columns[FEATURE].copy(), e.columns["stac"].copy()
        if not e.success:
            features[4:] += drift
            stac[4:] += stac_rise - 0.5  # `episode` already raised it by 0.5
        out.append(Episode({FEATURE: features, "stac": stac}, e.success))
    return out


def test_a_union_finds_the_failures_its_probe_learnt_and_those_only_stac_sees():
    """Seen tasks' failures drift the feature along one direction with STAC unchanged; an unseen task's drift along
    a direction the probe was never shown, with STAC raised. The probe finds the first and not the second, STAC the
    second and not the first; the union of the two finds both, and its score is the larger standardised one."""
    rng = np.random.default_rng(40)
    seen_drift, unseen_drift = np.array([3.0, -3.0, 0, 0, 0, 0]), np.array([0, 0, 0, 0, 3.0, 3.0])
    train, seen, unseen = (_task(rng, 30, d, r) for d, r in [(seen_drift, 0), (seen_drift, 0), (unseen_drift, 1.5)])
    fitted = {k: fit_monitor(train, FitOptions(kind=k, inputs=(FEATURE, "stac"))) for k in ("probe", "union")}
    fitted["stac"] = fit_monitor(train, FitOptions(kind="stac"))

    def auroc(monitor, episodes):
        maxima = [episode_max(monitor.score_steps(e.matrix(monitor.inputs))) for e in episodes]
        return roc_auc([not e.success for e in episodes], maxima)

    found = {k: (auroc(m, seen), auroc(m, unseen)) for k, m in fitted.items()}
    assert found["probe"][0] > 0.9 and found["probe"][1] < 0.7, found
    assert found["stac"][0] < 0.7 and found["stac"][1] > 0.9, found
    assert min(found["union"]) > 0.9, found
    union, probe = fitted["union"], dataclasses.replace(fitted["union"], kind="probe", standardised=None)
    x = unseen[-1].matrix(union.inputs)
    (p_mean, p_std), (s_mean, s_std) = union.standardised.probe, union.standardised.stac
    expected = np.fmax((probe.score_steps(x) - p_mean) / p_std, (x[:, union.stac_column] - s_mean) / s_std)
    np.testing.assert_allclose(union.score_steps(x), expected, rtol=0, atol=1e-12)
    # the scales are the training successes' (those not held out to calibrate)
    training, _ = split_episodes([e.success for e in train], 0.5, 0)
    steps = np.concatenate([train[i].matrix(union.inputs) for i in training if train[i].success])
    assert s_mean == pytest.approx(np.nanmean(steps[:, union.stac_column]), rel=1e-12)


def _prompted(episodes: list[Episode], prompt: str) -> list[Episode]:
    return [dataclasses.replace(e, prompts=(prompt,) * len(e.columns["stac"])) for e in episodes]


def test_a_gated_monitor_trusts_its_probe_only_under_the_instructions_it_was_fitted_on():
    """An unseen task whose successes look like the seen tasks' failures to the probe (their feature drifts the way
    a seen failure's does) and whose failures only STAC sees: the probe and the union rank it the wrong way round;
    the gated monitor, fitted on the seen task's instruction, scores it by STAC alone and finds its failures, and
    on the seen task it is the union, score for score."""
    rng = np.random.default_rng(41)
    seen_drift, unseen_drift = np.array([3.0, -3.0, 0, 0, 0, 0]), np.array([0, 0, 0, 0, 3.0, 3.0])
    train = _prompted(_task(rng, 30, seen_drift, 0), "Press the button")
    seen = _prompted(_task(rng, 30, seen_drift, 0), "press  the button ")  # case and spacing: the same instruction
    unseen = []
    for e in _task(rng, 30, unseen_drift, 1.5):
        features = e.columns[FEATURE] + (2 * seen_drift if e.success else 0.0)
        unseen.append(dataclasses.replace(e, columns={**e.columns, FEATURE: features}))
    unseen = _prompted(unseen, "open the door")
    options = FitOptions(inputs=(FEATURE, "stac"))
    fitted = {k: fit_monitor(train, dataclasses.replace(options, kind=k)) for k in ("probe", "union", "gated")}
    gated, union = fitted["gated"], fitted["union"]
    assert gated.prompts == union.prompts == ("press the button",)

    def auroc(monitor, episodes):
        maxima = [episode_max(monitor.score_steps(e.matrix(monitor.inputs), e.prompts)) for e in episodes]
        return roc_auc([not e.success for e in episodes], maxima)

    found = {k: (auroc(m, seen), auroc(m, unseen)) for k, m in fitted.items()}
    assert found["probe"][1] < 0.5 and found["union"][1] < 0.5, found
    assert min(found["gated"]) > 0.9, found
    # the same fit as the union's: scales and threshold (its calibration episodes are all under known instructions)
    assert gated.standardised == union.standardised and gated.threshold == union.threshold
    for e in seen[::7]:
        x = e.matrix(gated.inputs)
        np.testing.assert_array_equal(gated.score_steps(x, e.prompts), union.score_steps(x))
    s_mean, s_std = gated.standardised.stac
    x = unseen[-1].matrix(gated.inputs)
    expected = (x[:, gated.stac_column] - s_mean) / s_std
    np.testing.assert_allclose(gated.score_steps(x, "Open the door"), expected, rtol=0, atol=1e-12)
    # live, step by step, the same numbers
    running = gated.episode()
    steps = [{FEATURE: row[:-1], "stac": row[-1]} for row in x]
    live = [running.update(step, "open the door") for step in steps]
    np.testing.assert_array_equal(live, gated.score_steps(x, "open the door"))
    with pytest.raises(ValueError) as e:
        gated.episode().update(steps[0])
    assert_one_line(e.value, "gated", "prompt")
    with pytest.raises(ValueError) as e:
        fit_monitor(
            [*train[:-1], dataclasses.replace(train[-1], prompts=())], dataclasses.replace(options, kind="gated")
        )
    assert_one_line(e.value, f"episode {len(train) - 1}", "prompts")
    with pytest.raises(ValueError) as e:  # a recording without instructions: nothing to tell tasks apart by
        fit_monitor(_prompted(train[:3], " ") + train[3:], dataclasses.replace(options, kind="gated"))
    assert_one_line(e.value, "episode 0", "empty instruction")


def test_a_gated_monitor_told_the_policys_instructions_flags_any_other_from_the_first_call():
    """Told the instructions the policy was trained on, a gated monitor scores a step under one it was fitted on by
    the union and under another trained one by STAC alone, exactly as without being told; under an instruction the
    policy never learnt it scores one standard deviation above the threshold at least (STAC's score where that is
    higher), so the episode is flagged at its first call, where STAC has no value yet. Those episodes then rank
    above every success whatever their features, which is what ranks a new task's failures without a probe."""
    rng = np.random.default_rng(42)
    drift = np.array([3.0, -3.0, 0, 0, 0, 0])
    train = _prompted(_task(rng, 30, drift, 0), "Press the button")
    options = FitOptions(kind="gated", inputs=(FEATURE, "stac"))
    plain = fit_monitor(train, options)
    told = fit_monitor(train, dataclasses.replace(options, trained_on=("press the button", "Open  the DOOR")))
    assert told.trained_on == ("open the door", "press the button") and math.isfinite(told.threshold)
    assert (told.standardised, told.threshold, told.prompts) == (plain.standardised, plain.threshold, plain.prompts)
    episodes = _task(rng, 30, drift, 1.5)
    for prompt in ("press the button", "open the door"):  # fitted, then trained but not fitted on
        for e in episodes[::5]:
            x = e.matrix(told.inputs)
            np.testing.assert_array_equal(told.score_steps(x, prompt), plain.score_steps(x, prompt))
    assert told.trust("Press the button") == monitor_file.FITTED and told.trust("open the door") == "trained"
    floor = told.threshold + monitor_file.UNTRAINED_MARGIN
    for e in episodes:
        x = e.matrix(told.inputs)
        stac = plain.score_steps(x, "open the door")  # its standardised STAC, NaN on the first call
        scores = told.score_steps(x, "open the drawer")
        assert np.isnan(stac[0]) and scores[0] == floor
        np.testing.assert_array_equal(scores[1:], np.fmax(stac[1:], floor))
        running = told.episode()
        live = [running.update({FEATURE: row[:-1], "stac": row[-1]}, "open the drawer") for row in x]
        np.testing.assert_array_equal(live, scores)
        assert running.flagged_at == 0
    # untold, the same instruction is a trained one: STAC alone, nothing on the first call
    assert np.isnan(plain.score_steps(episodes[0].matrix(plain.inputs), "open the drawer")[0])
    # a monitor that never flags (no finite threshold) keeps STAC's score there: no floor to raise it to
    never = dataclasses.replace(told, threshold=math.inf)
    x = episodes[0].matrix(told.inputs)
    np.testing.assert_array_equal(never.score_steps(x, "open the drawer"), plain.score_steps(x, "open the drawer"))
    for kind in ("probe", "union"):
        with pytest.raises(ValueError) as e:
            fit_monitor(train, dataclasses.replace(options, kind=kind, trained_on=("press the button",)))
        assert_one_line(e.value, "gated", kind)
    with pytest.raises(ValueError) as e:
        dataclasses.replace(fit_monitor(train, dataclasses.replace(options, kind="union")), trained_on=("x",))
    assert_one_line(e.value, "union", "gated")
    with pytest.raises(ValueError) as e:  # rollouts under an instruction the named training data lacks
        fit_monitor(train, dataclasses.replace(options, trained_on=("open the door", "close the door")))
    assert_one_line(e.value, "'press the button'", "2 instructions")


def test_the_fit_is_reproducible_from_its_seed():
    data = episodes(20, 30, 10)
    options = FitOptions(kind="probe", inputs=(FEATURE, "stac"), temporal=True, seed=7)
    first, again = fit_monitor(data, options), fit_monitor(data, options)
    assert monitor_file.to_json(first) == monitor_file.to_json(again)
    other = fit_monitor(data, dataclasses.replace(options, seed=8))
    assert monitor_file.to_json(other) != monitor_file.to_json(first)
    training, calibration = split_episodes([e.success for e in data], 0.5, 7)
    assert calibration.size == 15 and not set(training) & set(calibration)
    assert all(data[i].success for i in calibration) and {30, 39} <= set(training)  # failures all train


def test_fit_refuses_what_it_cannot_fit_in_one_line():
    data = episodes(30, 5, 5)
    with pytest.raises(ValueError) as e:
        fit_monitor(data, FitOptions(inputs=("features/wrist",)))
    assert_one_line(e.value, "features/wrist")
    ragged = [*data[:-1], Episode({**data[-1].columns, "stac": data[-1].columns["stac"][:-2]}, False)]
    with pytest.raises(ValueError) as e:
        fit_monitor(ragged, FitOptions(inputs=(FEATURE, "stac")))
    assert_one_line(e.value, f"episode {len(data) - 1}", "different step counts")
    with pytest.raises(ValueError) as e:
        fit_monitor(data[4:], FitOptions())
    assert_one_line(e.value, "1 successful episodes")
    with pytest.raises(ValueError) as e:
        fit_monitor(data, FitOptions(kind="stac", inputs=(FEATURE,)))
    assert_one_line(e.value, "stac", FEATURE)
    with pytest.raises(ValueError) as e:
        fit_monitor(data, FitOptions(kind="union", inputs=(FEATURE,)))
    assert_one_line(e.value, "union", "'stac'", FEATURE)
