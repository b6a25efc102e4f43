"""A fitted failure monitor, its file, and its running score over an episode.

A `Monitor` reads named inputs of each step (pooled features [D], scalar signals such as `stac`), scores the step,
and flags an episode once the maximum of its step scores so far exceeds the conformal threshold. It is saved as one
JSON file (arrays as lists of floats, which round-trip float64 exactly), versioned by `format_version`; `load`
refuses a file it cannot trust in one line naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.monitor.scores import Basis, MahalanobisScorer, ProbeScorer, with_running_mean
from openpi_cam.monitor.signals import SAMPLE_SPREAD, STAC

FORMAT = "openpi-cam monitor"
# 2: the `gated` kind and the `prompts` a monitor was fitted on; 3: `trained_on`, the instructions the policy was
# trained on
FORMAT_VERSION = 3
# What a monitor scores (its kind): a logistic probe's log-odds of failure over its inputs; the Mahalanobis distance
# of its inputs to successful steps; the consecutive-chunk disagreement itself (training-free, one input: `stac`);
# the union of a probe and `stac`, the larger of their standardised scores (`Standardised`); or a gated union, the
# union on the instructions it was fitted on and the standardised `stac` alone on any other (`Monitor.knows`).
KINDS = ("probe", "mahalanobis", "stac", "union", "gated")
# The kinds that put a probe and `stac` on one scale (`Standardised`).
STANDARDISED_KINDS = ("union", "gated")
# How a gated monitor scores a step, by the instruction it was served under: the union of its probe and `stac` (an
# instruction it was fitted on); the standardised `stac` alone (one the policy was trained on, or any other where the
# policy's are not known); that, raised to `UNTRAINED_MARGIN` above the threshold (one the policy was never trained
# on: the episode is flagged from its first call). Any other kind scores every step as FITTED.
FITTED, TRAINED, UNTRAINED = "fitted", "trained", "untrained"
# One standard deviation of the training successes' scores, on a gated monitor's standardised scale.
UNTRAINED_MARGIN = 1.0


def instruction(prompt: str) -> str:
    """A prompt as a monitor compares instructions: case and runs of whitespace do not make another one."""
    return " ".join(prompt.split()).casefold()


@dataclasses.dataclass(frozen=True)
class Standardised:
    """How a union monitor puts its two detectors on one scale: each score's mean and standard deviation over the
    training successes' steps, so that a step scores (s - mean) / std on each and the larger counts.

    Why a union: a probe learns what failure looked like on the tasks it was fitted on, which need not be what it
    looks like on a task it never saw, while the training-free `stac` (a policy contradicting itself) reads the
    same on any task; the larger of the two standardised scores alerts on either, and the conformal threshold over
    the union's own calibration maxima keeps the false-alarm rate of the pair, not of each."""

    probe: tuple[float, float]
    stac: tuple[float, float]

    def combine(self, probe: np.ndarray, stac: np.ndarray, trusted: bool = True) -> np.ndarray:
        """[T], [T] -> [T]: the larger standardised score; the probe's alone where `stac` is NaN (a first call).
        Untrusted steps (a gated monitor's, under an instruction it was not fitted on): the standardised `stac`
        alone."""
        b = (np.asarray(stac, np.float64) - self.stac[0]) / self.stac[1]
        if not trusted:
            return b
        return np.fmax((np.asarray(probe, np.float64) - self.probe[0]) / self.probe[1], b)


@dataclasses.dataclass(frozen=True)
class MonitorInput:
    """One named input of a step: a vector of `dim` values (a pooled feature), or a scalar signal (dim 1)."""

    name: str
    dim: int = 1


@dataclasses.dataclass(frozen=True)
class Monitor:
    """What a fitted monitor scores and how it decides.

    kind: one of KINDS. inputs: the step's inputs in the order they are concatenated (F values in all; a union's
    include `stac`).
    temporal: each step is scored on its inputs beside their running mean over the episode so far
    (`scores.with_running_mean`: 2F values into the basis). basis / scorer: the fitted arrays (None for `stac`).
    threshold: a step whose score exceeds it flags the episode (inf: never). alpha: the false-alarm rate on
    successful episodes the threshold was calibrated for (`fit.conformal_threshold`). execution_horizon: the number
    of actions executed per call that the `stac` input assumes (None: unknown, the aligned variant). sample_spread:
    the action samples per call its `sample_spread` input compares (None: it reads none); whoever scores with it
    draws as many. standardised: a union's or gated monitor's scales (None for the other kinds). prompts: the
    instructions of the episodes it was fitted on (`instruction` form, sorted; empty where they were not known): a
    gated monitor trusts its probe on these alone. trained_on: the instructions the policy was trained on
    (`instruction` form, sorted; empty where they are not known), read by a gated monitor alone: a step under any
    other is UNTRAINED. fit: how it was fitted (seed, episode counts, options), for the record.

    Why gated: a probe learns what failure looked like on the tasks it was fitted on and can rank a task it never
    saw backwards, while `stac` reads alike on any task; which tasks it saw is known exactly, by their instructions,
    so a step under another instruction is scored by `stac` alone rather than by a probe outside what it learnt. And
    a policy fails a task it was never trained on whatever its features or `stac` say on the first calls (the
    multi-task demo models: every held-out task's episode), so where the policy's instructions are known a step
    under none of them flags the episode at once, with its reason in the instruction rather than in a score."""

    kind: str
    inputs: tuple[MonitorInput, ...]
    threshold: float
    alpha: float
    basis: Basis | None = None
    scorer: MahalanobisScorer | ProbeScorer | None = None
    temporal: bool = False
    execution_horizon: int | None = None
    standardised: Standardised | None = None
    fit: dict[str, Any] = dataclasses.field(default_factory=dict)
    sample_spread: int | None = None
    prompts: tuple[str, ...] = ()
    trained_on: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind == "gated" and not self.prompts:
            raise ValueError("a gated monitor names the instructions it was fitted on (prompts is empty)")
        if self.trained_on and self.kind != "gated":
            raise ValueError(f"a {self.kind} monitor reads no instruction: only a gated one is told the policy's")
        reads = any(i.name == SAMPLE_SPREAD for i in self.inputs)
        if reads != (self.sample_spread is not None) or (reads and self.sample_spread < 2):
            raise ValueError(
                f"sample_spread {self.sample_spread!r}: a monitor that reads {SAMPLE_SPREAD!r} names its samples per "
                "call (>= 2), one that does not names none"
            )

    @property
    def input_dim(self) -> int:
        return sum(i.dim for i in self.inputs)

    def step_inputs(self, step: Mapping[str, Any]) -> np.ndarray:
        """One step's named inputs concatenated in the monitor's order: [F]."""
        parts = []
        for item in self.inputs:
            if item.name not in step:
                raise ValueError(f"the step has no monitor input {item.name!r} (it has {sorted(step)})")
            value = np.asarray(step[item.name], np.float64).reshape(-1)
            if value.size != item.dim:
                raise ValueError(f"monitor input {item.name!r} has {value.size} values, the monitor expects {item.dim}")
            parts.append(value)
        return np.concatenate(parts)

    def trust(self, prompt: str | None) -> str:
        """How a step under this prompt is scored: FITTED, TRAINED or UNTRAINED (above). A gated monitor refuses a
        step whose prompt it is not told."""
        if self.kind != "gated":
            return FITTED
        if prompt is None:
            raise ValueError("a gated monitor scores a step with the prompt it was served under, and none was given")
        text = instruction(prompt)
        if text in self.prompts:
            return FITTED
        return UNTRAINED if self.trained_on and text not in self.trained_on else TRAINED

    def knows(self, prompt: str | None) -> bool:
        """Whether a step under this prompt is one a monitor trusts its probe on (a gated one: one of `prompts`)."""
        return self.trust(prompt) == FITTED

    def score(self, step: Mapping[str, Any], prompt: str | None = None) -> float:
        """One step's score from its named inputs (and its prompt, for a gated monitor), on its own; a temporal
        monitor scores a step with its episode's history, through `episode()`."""
        if self.temporal:
            raise ValueError("a temporal monitor scores a step with its episode's history: use Monitor.episode()")
        return float(self.score_prepared(self.step_inputs(step)[None, :], self.trust(prompt))[0])

    def score_steps(self, x: np.ndarray, prompts: Sequence[str] | str | None = None) -> np.ndarray:
        """The step scores of one episode, in order: x [T, F] (`step_inputs` of each step, or `Episode.matrix`) ->
        [T]. NaN where a step has no score (`stac` on an episode's first call). prompts: each step's prompt, or one
        for them all (read by a gated monitor alone; None or empty: unknown)."""
        x = np.asarray(x, np.float64).reshape(-1, self.input_dim)
        prepared = with_running_mean(x) if self.temporal else x
        single = prompts is None or isinstance(prompts, str)
        each = [prompts] * len(x) if single else list(prompts) or [None] * len(x)
        if len(each) != len(x):
            raise ValueError(f"{len(each)} prompts for {len(x)} steps")
        # one step at a time, as `EpisodeScore` scores: a matrix product over many rows may sum in another order
        # than over one, and the live and offline scores must be the same numbers, not merely close ones
        rows = zip(prepared, each, strict=True)
        return np.array([self.score_prepared(row[None, :], self.trust(p))[0] for row, p in rows])

    def score_prepared(self, x: np.ndarray, trust: str = FITTED) -> np.ndarray:
        """Scores of inputs as the basis reads them: x [T, F], or [T, 2F] for a temporal monitor (each step's inputs
        beside their running mean) -> [T]. trust: how a gated monitor scores these steps (`Monitor.trust`)."""
        if self.kind == "stac":
            return x[:, 0].copy()
        assert self.basis is not None and self.scorer is not None
        if isinstance(self.scorer, MahalanobisScorer):
            return self.scorer.score(self.basis.apply(x), self.basis.residual_sq(x))
        probe = self.scorer.score(self.basis.apply(x))
        if self.kind not in STANDARDISED_KINDS:
            return probe
        assert self.standardised is not None
        out = self.standardised.combine(probe, x[:, self.stac_column], trust == FITTED)
        if trust == UNTRAINED and math.isfinite(self.threshold):
            out = np.fmax(out, self.threshold + UNTRAINED_MARGIN)
        return out

    @property
    def stac_column(self) -> int:
        """Where `stac` sits among the concatenated inputs (a union reads it beside its probe)."""
        start = 0
        for item in self.inputs:
            if item.name == STAC:
                return start
            start += item.dim
        raise ValueError(f"the monitor has no {STAC!r} input")

    def flags(self, score: float) -> bool:
        return bool(score > self.threshold)

    def episode(self) -> EpisodeScore:
        """A running score for a new episode."""
        return EpisodeScore(self)


@dataclasses.dataclass
class EpisodeScore:
    """An episode's score as it runs: the maximum of its step scores so far, and the step at which it first
    exceeded the threshold. `update` scores each step as `Monitor.score_steps` scores the whole episode."""

    monitor: Monitor
    steps: int = 0
    score: float = -math.inf
    flagged_at: int | None = None
    _sums: np.ndarray | None = None
    _counts: np.ndarray | None = None

    @property
    def flagged(self) -> bool:
        return self.flagged_at is not None

    def update(self, step: Mapping[str, Any], prompt: str | None = None) -> float:
        """Score the next step (its named inputs, and the prompt it was served under) and return its score."""
        trust = self.monitor.trust(prompt)
        x = self.monitor.step_inputs(step)
        if self.monitor.temporal:
            finite = np.isfinite(x)
            self._sums = (0.0 if self._sums is None else self._sums) + np.where(finite, x, 0.0)
            self._counts = (0 if self._counts is None else self._counts) + finite
            with np.errstate(invalid="ignore", divide="ignore"):
                means = np.where(self._counts > 0, self._sums / np.maximum(self._counts, 1), np.nan)
            x = np.concatenate([x, means])
        value = float(self.monitor.score_prepared(x[None, :], trust)[0])
        if math.isfinite(value) and value > self.score:
            self.score = value
        if self.flagged_at is None and self.monitor.flags(value):
            self.flagged_at = self.steps
        self.steps += 1
        return value


def _floats(a: np.ndarray | None) -> Any:
    return None if a is None else np.asarray(a, np.float64).tolist()


def to_json(monitor: Monitor) -> dict[str, Any]:
    data: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": monitor.kind,
        "inputs": [{"name": i.name, "dim": i.dim} for i in monitor.inputs],
        "temporal": monitor.temporal,
        "execution_horizon": monitor.execution_horizon,
        "sample_spread": monitor.sample_spread,
        "alpha": monitor.alpha,
        "threshold": monitor.threshold if math.isfinite(monitor.threshold) else None,
        "prompts": list(monitor.prompts),
        "trained_on": list(monitor.trained_on),
        "fit": monitor.fit,
    }
    if monitor.basis is not None:
        b = monitor.basis
        data["basis"] = {"mean": _floats(b.mean), "scale": _floats(b.scale), "components": _floats(b.components)}
    if isinstance(monitor.scorer, MahalanobisScorer):
        m = monitor.scorer
        data["mahalanobis"] = {
            "center": _floats(m.center),
            "precision": _floats(m.precision),
            "residual_variance": m.residual_variance,
        }
    elif isinstance(monitor.scorer, ProbeScorer):
        data["probe"] = {"weights": _floats(monitor.scorer.weights), "bias": float(monitor.scorer.bias)}
    if monitor.standardised is not None:
        data[monitor.kind] = {"probe": list(monitor.standardised.probe), "stac": list(monitor.standardised.stac)}
    return data


def _encode(value: Any, depth: int = 0) -> str:
    """JSON with objects and lists of lists indented and each list of numbers on one line (a matrix: a line per row),
    so that a file, and the diff of a refitted one, grow with its rows rather than its numbers."""
    pad, inner = " " * depth, " " * (depth + 1)
    if isinstance(value, Mapping) and value:
        items = (f"{inner}{json.dumps(k)}: {_encode(v, depth + 1)}" for k, v in value.items())
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(value, list) and any(isinstance(v, Mapping | list) for v in value):
        return "[\n" + ",\n".join(inner + _encode(v, depth + 1) for v in value) + f"\n{pad}]"
    return json.dumps(value, allow_nan=False)


def save(monitor: Monitor, path: str | os.PathLike[str]) -> pathlib.Path:
    """Write the monitor as one JSON file (atomically: a reader never sees half a file)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    staged = path.with_name(path.name + ".tmp")
    staged.write_text(_encode(to_json(monitor)) + "\n")
    os.replace(staged, path)
    return path


def load(path: str | os.PathLike[str]) -> Monitor:
    """Read and validate a monitor file; a bad file raises ValueError in one line naming the file and the problem."""
    path = pathlib.Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such monitor file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a JSON monitor file ({str(e).splitlines()[0]})") from None
    try:
        return from_json(data)
    except (ValueError, KeyError, TypeError) as e:
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{path}: {message}") from None


def _array(section: Mapping[str, Any], where: str, key: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """section[key] as a finite float64 array of `shape` (None: any length), else ValueError naming `where.key`."""
    if key not in section:
        raise ValueError(f"{where}.{key} is missing")
    try:
        a = np.asarray(section[key], np.float64)
    except (ValueError, TypeError):
        raise ValueError(f"{where}.{key} is not a numeric array") from None
    if a.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, a.shape, strict=True)):
        wanted = "x".join("?" if n is None else str(n) for n in shape) or "a number"
        raise ValueError(f"{where}.{key} has shape {list(a.shape)}, expected {wanted}")
    if not np.isfinite(a).all():
        raise ValueError(f"{where}.{key} has non-finite values")
    return a


def _section(data: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    section = data.get(key)
    if not isinstance(section, dict):
        raise ValueError(f"{key} is missing or not an object")
    return section


def _inputs(data: Mapping[str, Any]) -> tuple[MonitorInput, ...]:
    items = data.get("inputs")
    if not isinstance(items, list) or not items:
        raise ValueError("inputs must be a non-empty list")
    inputs = []
    for item in items:
        ok = isinstance(item, dict) and isinstance(item.get("name"), str) and isinstance(item.get("dim"), int)
        if not ok or item["dim"] < 1:
            raise ValueError(f"input {item!r} is not a {{name, dim >= 1}} object")
        inputs.append(MonitorInput(item["name"], item["dim"]))
    names = [i.name for i in inputs]
    if len(set(names)) != len(names):
        raise ValueError(f"inputs name one input twice: {names}")
    return tuple(inputs)


def _scorer(data: Mapping[str, Any], kind: str, width: int) -> tuple[Basis, MahalanobisScorer | ProbeScorer]:
    b = _section(data, "basis")
    mean = _array(b, "basis", "mean", (width,))
    scale = _array(b, "basis", "scale", (width,))
    if (scale <= 0).any():
        raise ValueError("basis.scale has values <= 0")
    components = None if b.get("components") is None else _array(b, "basis", "components", (None, width))
    basis = Basis(mean, scale, components)
    k = basis.dims
    if kind == "mahalanobis":
        m = _section(data, "mahalanobis")
        residual = float(_array(m, "mahalanobis", "residual_variance", ()))
        if residual < 0:
            raise ValueError(f"mahalanobis.residual_variance {residual} is negative")
        center, precision = _array(m, "mahalanobis", "center", (k,)), _array(m, "mahalanobis", "precision", (k, k))
        return basis, MahalanobisScorer(center, precision, residual)
    p = _section(data, "probe")
    return basis, ProbeScorer(_array(p, "probe", "weights", (k,)), float(_array(p, "probe", "bias", ())))


def from_json(data: Any) -> Monitor:
    """A monitor from its JSON object, validated (ValueError naming the first problem)."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"not a monitor file (format {found!r}, expected {FORMAT!r})")
    version = data.get("format_version")
    if not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise ValueError(f"format_version {version!r} is not one this openpi-cam reads (1 to {FORMAT_VERSION})")
    kind = data.get("kind")
    if kind not in KINDS:
        raise ValueError(f"kind {kind!r} is not one of {KINDS}")
    inputs = _inputs(data)
    alpha, threshold, horizon = data.get("alpha"), data.get("threshold"), data.get("execution_horizon")
    if not isinstance(alpha, int | float) or not 0 < alpha < 1:
        raise ValueError(f"alpha {alpha!r} is not a rate in (0, 1)")
    if threshold is not None and (not isinstance(threshold, int | float) or not math.isfinite(threshold)):
        raise ValueError(f"threshold {threshold!r} is not a number (null: never flags)")
    if horizon is not None and (not isinstance(horizon, int) or horizon < 1):
        raise ValueError(f"execution_horizon {horizon!r} is not a positive integer (null: unknown)")
    temporal = data.get("temporal", False)
    if not isinstance(temporal, bool):
        raise ValueError(f"temporal {temporal!r} is not true or false")
    samples = data.get("sample_spread")
    if samples is not None and (not isinstance(samples, int) or isinstance(samples, bool)):
        raise ValueError(f"sample_spread {samples!r} is not an integer (null: the monitor reads no sample spread)")
    prompts, trained_on = (_instructions(data, key) for key in ("prompts", "trained_on"))
    basis, scorer, standardised = None, None, None
    if kind == "stac":
        if inputs != (MonitorInput(STAC, 1),):
            raise ValueError(f"a stac monitor reads the one input {STAC!r}, not {[i.name for i in inputs]}")
    else:
        basis, scorer = _scorer(data, kind, sum(i.dim for i in inputs) * (2 if temporal else 1))
    if kind in STANDARDISED_KINDS:
        if MonitorInput(STAC, 1) not in inputs:
            raise ValueError(f"a {kind} monitor reads {STAC!r} among its inputs, not only {[i.name for i in inputs]}")
        scales = _section(data, kind)
        pairs = {name: _array(scales, kind, name, (2,)) for name in ("probe", "stac")}
        if any(pair[1] <= 0 for pair in pairs.values()):
            raise ValueError(f"{kind} has a standard deviation <= 0")
        (p_mean, p_std), (s_mean, s_std) = (map(float, pairs[n]) for n in ("probe", "stac"))
        standardised = Standardised((p_mean, p_std), (s_mean, s_std))
    return Monitor(
        kind=kind,
        inputs=inputs,
        threshold=math.inf if threshold is None else float(threshold),
        alpha=float(alpha),
        basis=basis,
        scorer=scorer,
        temporal=temporal,
        execution_horizon=horizon,
        standardised=standardised,
        fit=dict(data.get("fit") or {}),
        sample_spread=samples,
        prompts=prompts,
        trained_on=trained_on,
    )


def _instructions(data: Mapping[str, Any], key: str) -> tuple[str, ...]:
    texts = data.get(key, [])
    if not isinstance(texts, list) or not all(isinstance(p, str) and p == instruction(p) for p in texts):
        raise ValueError(f"{key} is not a list of instructions (lower case, single spaces)")
    return tuple(sorted(set(texts)))
