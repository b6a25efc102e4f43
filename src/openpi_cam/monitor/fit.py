"""Fitting a failure monitor from labelled episodes (pure NumPy, deterministic given a seed).

The successful episodes are split once, by the seed, into a training share and a calibration share; the failed
episodes all train (only the probe uses them). The scorer (the Mahalanobis distance to the training successes' steps,
or a logistic probe on every training step; a union's probe and its scales) is fitted on the training episodes alone,
and the threshold on the calibration episodes alone, which the scorer never saw: that is what the conformal guarantee
needs.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from openpi_cam.monitor.monitor_file import KINDS, STANDARDISED_KINDS, Monitor, MonitorInput, Standardised, instruction
from openpi_cam.monitor.scores import Basis, MahalanobisScorer, ProbeScorer, with_running_mean
from openpi_cam.monitor.signals import SAMPLE_SPREAD, STAC


@dataclasses.dataclass(frozen=True)
class Episode:
    """One labelled rollout. columns: input name -> [T] (a scalar signal per step) or [T, D] (a feature per step),
    every column with the episode's T steps; success: whether the episode succeeded; frames: [T] each step's source
    frame index within the episode (LeRobot's `frame_index`), where known: what the detection figures count time in;
    prompts: each step's prompt, where known (empty: unknown): the instructions a monitor is fitted on."""

    columns: Mapping[str, np.ndarray]
    success: bool
    frames: np.ndarray | None = None
    prompts: tuple[str, ...] = ()

    def matrix(self, inputs: Sequence[MonitorInput]) -> np.ndarray:
        """The named inputs of every step, concatenated in order: [T, F]."""
        parts = []
        for item in inputs:
            if item.name not in self.columns:
                raise ValueError(f"the episode has no column {item.name!r} (it has {sorted(self.columns)})")
            column = np.asarray(self.columns[item.name], np.float64)
            parts.append(column.reshape(column.shape[0], -1))
            if parts[-1].shape[1] != item.dim:
                raise ValueError(f"column {item.name!r} has {parts[-1].shape[1]} values per step, expected {item.dim}")
        if len({p.shape[0] for p in parts}) > 1:
            raise ValueError(f"the columns {[i.name for i in inputs]} have different step counts")
        return np.concatenate(parts, axis=1)


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How `fit_monitor` fits. Defaults are fixed before any evaluation, not chosen on reported episodes."""

    kind: str = "probe"  # what the monitor scores: one of monitor_file.KINDS
    inputs: tuple[str, ...] = ()  # the columns the monitor reads, in order (empty: every column, sorted by name)
    alpha: float = 0.1  # the false-alarm rate on successful episodes the threshold is calibrated for
    calibration_share: float = 0.5  # of the successful episodes, held out for the threshold
    seed: int = 0  # the episode split
    max_dims: int = 32  # each input wider than this is projected onto its leading principal directions
    shrinkage: float | None = None  # Mahalanobis: None is Ledoit-Wolf's weight, a number in [0, 1] a fixed one
    l2: float = 1e-2  # the probe's penalty on its weights, in standardised units, per episode-averaged loss
    temporal: bool = False  # score each step with the running mean of its episode's inputs beside it
    execution_horizon: int | None = None  # recorded with the monitor: the actions per call that `stac` assumed
    sample_spread: int | None = None  # recorded with the monitor: the samples per call `sample_spread` compared
    trained_on: tuple[str, ...] = ()  # gated: the instructions the policy was trained on (empty: not known)


def split_episodes(success: Sequence[bool], calibration_share: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(training indices, calibration indices), sorted: a seeded share of the successful episodes (at least one,
    and at least one left to train) calibrates, everything else trains."""
    ok = np.flatnonzero(np.asarray(success, bool))
    if ok.size < 2:
        raise ValueError(f"{ok.size} successful episodes: a monitor needs at least 2 (to train and to calibrate)")
    n_cal = min(max(round(calibration_share * ok.size), 1), ok.size - 1)
    calibration = np.sort(np.random.default_rng(seed).permutation(ok)[:n_cal])
    training = np.setdiff1d(np.arange(len(success)), calibration)
    return training, calibration


def fit_basis(x: np.ndarray, max_dims: int, widths: Sequence[int] | None = None) -> Basis:
    """Standardise each column over the rows of x [N, F] (mean, standard deviation with ddof 0; a constant column
    keeps scale 1), imputing non-finite entries by the mean; then project each input wider than max_dims onto its
    own leading min(max_dims, N - 1) principal directions, keeping narrower inputs as they are. `widths` splits the
    F columns into the inputs, in order (None: one input). Per input, because a covariance in F > N dimensions is
    singular and a probe in thousands of dimensions over a few hundred steps only memorises, while a scalar signal
    projected together with a feature hundreds wide is lost among its directions. The projection is one
    block-diagonal matrix with orthonormal rows; each direction's sign is fixed (its largest entry positive) so the
    basis does not depend on the linear-algebra library."""
    x = np.asarray(x, np.float64)
    widths = [x.shape[1]] if widths is None else list(widths)
    if sum(widths) != x.shape[1]:
        raise ValueError(f"input widths {widths} do not add up to the {x.shape[1]} columns")
    finite = np.isfinite(x)
    counts = np.maximum(finite.sum(axis=0), 1)
    mean = np.where(finite, x, 0.0).sum(axis=0) / counts
    centred = np.where(finite, x - mean, 0.0)
    std = np.sqrt((centred**2).sum(axis=0) / counts)
    scale = np.where(std > 0, std, 1.0)
    if all(w <= max_dims for w in widths):
        return Basis(mean, scale)
    blocks, start = [], 0
    for width in widths:
        columns = slice(start, start + width)
        if width <= max_dims:
            block = np.eye(width)
        else:
            z = centred[:, columns] / scale[columns]
            block = leading_directions(z, max(1, min(max_dims, x.shape[0] - 1)))
            # an input of lower rank than the directions asked for (a prompt's feature over a few prompts) leaves
            # directions the steps do not vary along: kept, they would make the covariance singular
            spread = (z @ block.T).var(axis=0)
            block = block[(spread > 1e-9 * spread.max()) | (np.arange(len(spread)) == 0)]
            k = block.shape[0]
            block = block * np.sign(block[np.arange(k), np.abs(block).argmax(axis=1)])[:, None]
        rows = np.zeros((block.shape[0], x.shape[1]))
        rows[:, columns] = block
        blocks.append(rows)
        start += width
    return Basis(mean, scale, np.concatenate(blocks))


def leading_directions(a: np.ndarray, k: int, *, oversample: int = 10, iterations: int = 4) -> np.ndarray:
    """The k leading right singular vectors of a [N, F] (its principal directions when centred): [k, F], orthonormal
    rows. By randomised subspace iteration (Halko, Martinsson and Tropp 2011): a seeded random subspace of k +
    oversample dimensions, refined by `iterations` passes of a a^T, then an exact SVD inside it. Its cost grows as
    N x F x k, where a full SVD's grows as N x F x min(N, F): thousands of steps of pooled features several
    thousand wide are fitted in seconds, not minutes. The fixed seed keeps the result reproducible."""
    n, f = a.shape
    width = min(k + oversample, n, f)
    y = a @ np.random.default_rng(0).normal(size=(f, width))
    q = np.linalg.qr(y)[0]
    for _ in range(iterations):
        q = np.linalg.qr(a.T @ q)[0]  # re-orthonormalised each pass, or the columns collapse onto the first
        q = np.linalg.qr(a @ q)[0]
    _, _, vt = np.linalg.svd(q.T @ a, full_matrices=False)
    return vt[:k]


def ledoit_wolf(z: np.ndarray) -> tuple[np.ndarray, float]:
    """Ledoit and Wolf's (2004) shrunk covariance of the rows of z [N, k]: (1 - rho) S + rho mu I, with S the
    sample covariance (ddof 0), mu its mean variance and rho the weight their lemma estimates from the data (the
    rows' own scatter around S against S's distance to mu I), in [0, 1]. In standardised coordinates mu I is S's
    diagonal; in principal coordinates S is diagonal and shrinking pulls its small variances up toward the mean.
    Returns (covariance [k, k], rho)."""
    x = np.asarray(z, np.float64)
    x = x - x.mean(axis=0)
    n, p = x.shape
    s = x.T @ x / n
    mu = float(np.trace(s)) / p
    distance = float(((s - mu * np.eye(p)) ** 2).sum())
    scatter = float(((x**2).sum(axis=1) ** 2).sum() - n * (s**2).sum()) / n**2
    rho = 1.0 if distance == 0 else min(scatter, distance) / distance
    return (1 - rho) * s + rho * mu * np.eye(p), rho


def fit_mahalanobis(basis: Basis, x: np.ndarray, shrinkage: float | None = None) -> tuple[MahalanobisScorer, float]:
    """The distance to the rows of x [N, F] (the training successes' steps) in the basis: their coordinates' mean
    and the inverse of their covariance shrunk toward mu I with Ledoit-Wolf's weight (None) or a fixed one, and,
    when the basis projects, the mean variance of the directions it leaves out (probabilistic PCA's isotropic
    remainder: `scores.MahalanobisScorer`). Returns (scorer, the shrinkage weight used)."""
    z = basis.apply(x)
    if shrinkage is None:
        cov, rho = ledoit_wolf(z)
    else:
        if not 0 <= shrinkage <= 1:
            raise ValueError(f"shrinkage must be in [0, 1], got {shrinkage}")
        centred = z - z.mean(axis=0)
        s = centred.T @ centred / z.shape[0]
        cov, rho = (1 - shrinkage) * s + shrinkage * np.trace(s) / s.shape[0] * np.eye(s.shape[0]), shrinkage
    # a pseudo-inverse: with fewer steps than directions (several inputs each projected) the covariance can be
    # singular even shrunk, and a direction no training step varies along then adds nothing to the distance
    precision = np.linalg.pinv(cov, hermitian=True)
    left_out = basis.mean.shape[0] - basis.dims
    residual = float(basis.residual_sq(x).mean()) / left_out if left_out else 0.0
    return MahalanobisScorer(z.mean(axis=0), (precision + precision.T) / 2, residual), float(rho)


def _log_loss(margins: np.ndarray, y: np.ndarray, weights: np.ndarray) -> float:
    return float((weights * (np.logaddexp(0.0, margins) - y * margins)).sum())


def fit_logistic(
    z: np.ndarray, failed: np.ndarray, weights: np.ndarray | None = None, *, l2: float = 1e-2, tol: float = 1e-12
) -> ProbeScorer:
    """L2-regularised logistic regression by Newton's method with a backtracking line search (deterministic).

    Minimises sum_i w_i [log(1 + exp(m_i)) - y_i m_i] + l2 / 2 ||weights||^2 over m_i = z_i . weights + bias, with
    the row weights w normalised to sum to 1 and the bias unpenalised. z: [N, k] (standardised inputs); failed:
    bool [N]; weights: [N] (None: equal). Stops when half the squared Newton decrement is below tol."""
    x = np.hstack([np.asarray(z, np.float64), np.ones((len(z), 1))])
    y = np.asarray(failed, np.float64).reshape(-1)
    if not 0 < y.sum() < y.size:
        raise ValueError("a probe needs both failed and successful steps to train on")
    w = np.ones(y.size) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    penalty = np.full(x.shape[1], float(l2))
    penalty[-1] = 0.0

    def objective(theta: np.ndarray) -> float:
        return _log_loss(x @ theta, y, w) + 0.5 * float((penalty * theta**2).sum())

    theta = np.zeros(x.shape[1])
    for _ in range(200):
        p = 0.5 * (1.0 + np.tanh(0.5 * (x @ theta)))  # the logistic function without overflow
        grad = x.T @ (w * (p - y)) + penalty * theta
        hess = (x * (w * p * (1 - p))[:, None]).T @ x + np.diag(penalty)
        step = np.linalg.lstsq(hess, grad, rcond=None)[0]
        decrement = float(grad @ step)
        if decrement / 2 < tol:
            break
        t, before = 1.0, objective(theta)
        while objective(theta - t * step) > before - 0.25 * t * decrement and t > 1e-12:
            t /= 2
        theta = theta - t * step
    return ProbeScorer(theta[:-1].copy(), float(theta[-1]))


def episode_max(scores: np.ndarray) -> float:
    """An episode's score: the maximum of its finite step scores (-inf when it has none: it never flags)."""
    s = np.asarray(scores, np.float64)
    s = s[np.isfinite(s)]
    return float(s.max()) if s.size else -math.inf


def conformal_threshold(calibration_maxima: Sequence[float], alpha: float) -> float:
    """Split conformal threshold over n successful calibration episodes' maximum step scores M_1..M_n: the k-th
    smallest, k = ceil((n + 1)(1 - alpha)), i.e. their ceil((n + 1)(1 - alpha)) / n empirical quantile; inf when
    k > n (too few episodes for alpha: never flag). An episode is flagged once a step's score exceeds it.

    Guarantee: if a new successful episode's maximum M is exchangeable with M_1..M_n (same policy, task and
    perturbation distribution; the scorer fitted on other episodes), then P(M > threshold) <= alpha, so the
    probability that the monitor ever flags it, at any step, is at most alpha. The probability is over the
    calibration episodes and the new one together (marginal), not conditional on one calibration set: for
    continuous maxima a fixed calibration set's false-alarm rate is Beta(n + 1 - k, k) distributed, with mean
    1 - k / (n + 1) in [alpha - 1 / (n + 1), alpha]. Nothing is promised for failed episodes (that is the AUROC's
    job) nor for successes from another distribution."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    maxima = np.asarray(calibration_maxima, np.float64)
    maxima = np.sort(np.where(np.isfinite(maxima), maxima, -np.inf))
    n = maxima.size
    # (n + 1)(1 - alpha) rounded first: 20 x 0.9 is 18.000000000000004 in binary, whose ceiling would be 19
    k = math.ceil(round((n + 1) * (1 - alpha), 9))
    return math.inf if k > n else float(maxima[k - 1])


def _inputs(episodes: Sequence[Episode], names: Sequence[str]) -> tuple[MonitorInput, ...]:
    first = episodes[0].columns
    names = list(names) or sorted(first)
    missing = [n for n in names if n not in first]
    if missing:
        raise ValueError(f"the episodes have no column {missing[0]!r} (they have {sorted(first)})")
    return tuple(MonitorInput(n, int(np.prod(np.shape(first[n])[1:], dtype=int))) for n in names)


def _matrix(index: int, episode: Episode, inputs: tuple[MonitorInput, ...]) -> np.ndarray:
    try:
        return episode.matrix(inputs)
    except ValueError as e:
        raise ValueError(f"episode {index}: {e}") from None


def _scorer(
    options: FitOptions, x: list[np.ndarray], widths: list[int], success: np.ndarray, training: np.ndarray
) -> tuple[Basis | None, MahalanobisScorer | ProbeScorer | None, dict]:
    if options.kind == "stac":
        return None, None, {}
    if options.kind == "mahalanobis":
        rows = np.concatenate([x[i] for i in training if success[i]])
        basis = fit_basis(rows, options.max_dims, widths)
        scorer, rho = fit_mahalanobis(basis, rows, options.shrinkage)
        return basis, scorer, {"shrinkage": rho, "steps": int(rows.shape[0])}
    rows = np.concatenate([x[i] for i in training])
    basis = fit_basis(rows, options.max_dims, widths)
    failed = np.concatenate([np.full(len(x[i]), not success[i]) for i in training])
    # every episode weighs alike: failed episodes run to the time limit, and per-step weights would let their
    # late steps (and so episode length) decide the fit
    weights = np.concatenate([np.full(len(x[i]), 1.0 / len(x[i])) for i in training])
    scorer = fit_logistic(basis.apply(rows), failed, weights, l2=options.l2)
    return basis, scorer, {"l2": options.l2, "steps": int(rows.shape[0])}


def _spread(scores: np.ndarray, what: str, kind: str) -> tuple[float, float]:
    s = np.asarray(scores, np.float64)
    s = s[np.isfinite(s)]
    if s.size < 2 or not s.std() > 0:
        raise ValueError(f"a {kind} monitor needs the training successes' {what} scores to vary ({s.size} finite)")
    return float(s.mean()), float(s.std())


def standardise_union(probe: Monitor, x: Sequence[np.ndarray], kind: str = "union") -> Standardised:
    """A union's (or gated monitor's) scales (`monitor_file.Standardised`): the mean and standard deviation of the
    probe's step scores and of the `stac` input over the steps x (each episode's [T, F] inputs; the training
    successes')."""
    scores = np.concatenate([probe.score_steps(m) for m in x])
    stac = np.concatenate([m[:, probe.stac_column] for m in x])
    return Standardised(_spread(scores, "probe", kind), _spread(stac, STAC, kind))


def _instructions(episodes: Sequence[Episode], kind: str) -> tuple[str, ...]:
    """The instructions the episodes were served under (`instruction` form, sorted); a gated monitor needs every
    step's."""
    for index, episode in enumerate(episodes):
        steps = len(next(iter(episode.columns.values()), ()))
        if episode.prompts and len(episode.prompts) != steps:
            raise ValueError(f"episode {index}: {len(episode.prompts)} prompts for {steps} steps")
        if kind == "gated" and not episode.prompts:
            raise ValueError(f"episode {index}: a gated monitor is fitted on episodes whose prompts are known")
        if kind == "gated" and not all(instruction(p) for p in episode.prompts):
            raise ValueError(f"episode {index}: an empty instruction, and a gated monitor tells tasks by theirs")
    return tuple(sorted({instruction(p) for e in episodes for p in e.prompts}))


def fit_monitor(episodes: Sequence[Episode], options: FitOptions = FitOptions()) -> Monitor:
    """Fit a monitor on labelled episodes: the scorer on the training split, the threshold on the calibration split
    (`split_episodes`, `conformal_threshold`). The same episodes and options give the same monitor."""
    if options.kind not in KINDS:
        raise ValueError(f"kind {options.kind!r} is not one of {KINDS}")
    if not episodes:
        raise ValueError("no episodes to fit a monitor on")
    inputs = _inputs(episodes, (STAC,) if options.kind == "stac" and not options.inputs else options.inputs)
    if options.kind == "stac" and (inputs != (MonitorInput(STAC, 1),) or options.temporal):
        raise ValueError(f"a stac monitor reads the one input {STAC!r} as it is, not {[i.name for i in inputs]}")
    if options.kind in STANDARDISED_KINDS and MonitorInput(STAC, 1) not in inputs:
        kind = options.kind
        raise ValueError(f"a {kind} monitor reads {STAC!r} among its inputs, not only {[i.name for i in inputs]}")
    prompts = _instructions(episodes, options.kind)
    if options.trained_on and options.kind != "gated":
        raise ValueError(f"the policy's instructions are read by a gated monitor, not a {options.kind} one")
    trained_on = {instruction(p) for p in options.trained_on}
    if "" in trained_on:
        raise ValueError("an empty instruction among the policy's: a gated monitor tells instructions by their text")
    strangers = sorted(set(prompts) - trained_on) if trained_on else []
    if strangers:  # most likely another policy's training data: every served call would be flagged
        raise ValueError(
            f"the episodes were served under {strangers[0]!r}, which is not among the {len(trained_on)} instructions "
            "the policy was trained on: name this policy's training data"
        )
    reads_spread = any(i.name == SAMPLE_SPREAD for i in inputs)
    if reads_spread and options.sample_spread is None:
        raise ValueError(f"the {SAMPLE_SPREAD!r} input needs its samples per call (FitOptions.sample_spread)")
    success = np.array([bool(e.success) for e in episodes])
    training, calibration = split_episodes(success, options.calibration_share, options.seed)
    x = [_matrix(i, e, inputs) for i, e in enumerate(episodes)]
    prepared = [with_running_mean(m) for m in x] if options.temporal else x
    widths = [i.dim for i in inputs] * (2 if options.temporal else 1)
    basis, scorer, record = _scorer(options, prepared, widths, success, training)
    monitor = Monitor(
        kind="probe" if options.kind in STANDARDISED_KINDS else options.kind,
        inputs=inputs,
        threshold=math.inf,
        alpha=options.alpha,
        basis=basis,
        scorer=scorer,
        temporal=options.temporal,
        execution_horizon=options.execution_horizon,
        sample_spread=options.sample_spread if reads_spread else None,
        prompts=prompts,
    )
    if options.kind in STANDARDISED_KINDS:
        scales = standardise_union(monitor, [x[i] for i in training if success[i]], options.kind)
        known = tuple(sorted(trained_on))
        monitor = dataclasses.replace(monitor, kind=options.kind, standardised=scales, trained_on=known)
    maxima = [episode_max(monitor.score_steps(x[i], episodes[i].prompts)) for i in calibration]
    record |= {
        "seed": options.seed,
        "calibration_share": options.calibration_share,
        "max_dims": options.max_dims,
        "training_episodes": int(training.size),
        "training_failures": int((~success[training]).sum()),
        "calibration_episodes": int(calibration.size),
    }
    return dataclasses.replace(monitor, threshold=conformal_threshold(maxima, options.alpha), fit=record)
