"""`openpi-cam monitor fit MAPS... --out FILE`: a failure monitor fitted on labelled rollouts (maps datasets of
`next.success` recordings, explained with `--monitor-features` for the feature monitors), saved as one file that
`serve --monitor` and `explain-dataset --monitor` score with (README, "Monitoring for failures")."""

from __future__ import annotations

import dataclasses
import math
import pathlib
import sys
from typing import Literal

import numpy as np
import tyro

from openpi_cam.auroc import roc_auc
from openpi_cam.lerobot.dataset import open_dataset
from openpi_cam.maps.monitoring import Rollouts, read_rollouts
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.fit import FitOptions, episode_max, fit_monitor, split_episodes
from openpi_cam.monitor.monitor_file import Monitor
from openpi_cam.monitor.signals import STAC

DEFAULTS = FitOptions()
# Which kinds read each fitting flag (a flag given for another kind is refused, not ignored).
_PROBES = ("probe", *monitor_file.STANDARDISED_KINDS)
_FEATURE_KINDS = tuple(k for k in monitor_file.KINDS if k != "stac")
_KIND_FLAGS = {
    "l2": _PROBES,
    "shrinkage": ("mahalanobis",),
    "max_dims": _FEATURE_KINDS,
    "temporal": _FEATURE_KINDS,
    "trained_on": ("gated",),
    "trained_prompts": ("gated",),
}


def main(
    maps: tyro.conf.Positional[tuple[pathlib.Path, ...]],
    out: pathlib.Path,
    kind: Literal["probe", "mahalanobis", "stac", "union", "gated"] = "probe",
    inputs: tuple[str, ...] = (),
    alpha: float = DEFAULTS.alpha,
    calibration_share: float = DEFAULTS.calibration_share,
    seed: int = DEFAULTS.seed,
    max_dims: int = DEFAULTS.max_dims,
    shrinkage: float | None = DEFAULTS.shrinkage,
    l2: float = DEFAULTS.l2,
    temporal: bool = DEFAULTS.temporal,
    trained_on: tuple[pathlib.Path, ...] = (),
    trained_prompts: tuple[str, ...] = (),
) -> int:
    """Fit a failure monitor on the labelled episodes of maps datasets and save it; print its training AUROC and its
    conformal threshold with the false-alarm rate it has on the calibration episodes. Exit status 2 with one line
    on bad input.

    Args:
        maps: maps datasets (`explain-dataset` of rollouts that record `next.success`) whose rows carry the monitor's
            columns; the feature monitors need `--monitor-features` there.
        out: the monitor file to write (JSON).
        kind: `probe` (a logistic probe's log-odds of failure), `mahalanobis` (the distance to the successful
            episodes' steps), `stac` (the consecutive-chunk disagreement itself, training-free), `union` (the
            larger of a probe's and `stac`'s scores, each standardised on the training successes' steps) or `gated`
            (the union under the instructions of the episodes it was fitted on, the standardised `stac` alone under
            any other: for tasks the probe never saw).
        inputs: the monitor inputs to read, e.g. `features/base_0_rgb stac` (default: every input the episodes carry
            with a value; `stac` alone for `--kind stac`). A monitor that reads `sample_spread` (rows explained with
            `--sample-spread N`) records N: `serve` and `explain-dataset` draw as many chunks a call to score with it.
        alpha: the false-alarm rate on successful episodes the threshold is calibrated for.
        calibration_share: the share of the successful episodes held out to set the threshold.
        seed: the seed of that split.
        max_dims: inputs wider than this are projected onto their leading principal directions (probe, mahalanobis,
            union, gated).
        shrinkage: Mahalanobis covariance shrinkage in [0, 1] (default: Ledoit-Wolf's estimate).
        l2: the probe's L2 penalty (probe, union, gated).
        temporal: score each step beside the running mean of its episode's inputs (probe, mahalanobis, union,
            gated).
        trained_on: the LeRobot datasets the policy was trained on (gated): their task strings are the
            instructions it knows, and a step under any other flags its episode from the first call.
        trained_prompts: instructions the policy was trained on, given as text (gated; beside `--trained-on`).
    """
    try:
        flags = {"l2": l2, "shrinkage": shrinkage, "max_dims": max_dims, "temporal": temporal}
        _refuse_other_kinds_flags(kind, flags | {"trained_on": trained_on, "trained_prompts": trained_prompts})
        known = _trained_instructions(trained_on, trained_prompts)
        rollouts = read_rollouts(maps)
        chosen = inputs or ((STAC,) if kind == "stac" else tuple(rollouts.inputs))
        options = FitOptions(
            kind=kind,
            inputs=chosen,
            alpha=alpha,
            calibration_share=calibration_share,
            seed=seed,
            max_dims=max_dims,
            shrinkage=shrinkage,
            l2=l2,
            temporal=temporal,
            execution_horizon=rollouts.execution_horizon,
            sample_spread=rollouts.sample_spread,
            trained_on=known,
        )
        _check_options(options)
        monitor = fit_monitor(rollouts.episodes, options)
        monitor = dataclasses.replace(monitor, fit={**monitor.fit, "maps": [str(p) for p in maps]})
        monitor_file.save(monitor, out)
    except (ValueError, OSError) as e:
        print(f"openpi-cam monitor fit: {e}", file=sys.stderr)
        return 2
    print(report(monitor, rollouts, options, out))
    return 0


def _refuse_other_kinds_flags(kind: str, given: dict[str, object]) -> None:
    for name, readers in _KIND_FLAGS.items():
        if given[name] != getattr(DEFAULTS, name, ()) and kind not in readers:
            flag = "--" + name.replace("_", "-")
            raise ValueError(f"{flag} is read by --kind {' or '.join(readers)}, not {kind}")


def _trained_instructions(datasets: tuple[pathlib.Path, ...], prompts: tuple[str, ...]) -> tuple[str, ...]:
    """Every instruction given and every task string of the training datasets (`fit_monitor` normalises them)."""
    texts = [*prompts]
    for path in datasets:
        tasks = list(open_dataset(path).tasks().values())
        if not tasks:
            raise ValueError(f"{path}: the dataset names no task (meta/tasks), so it tells no instruction")
        texts += tasks
    return tuple(texts)


def _check_options(options: FitOptions) -> None:
    if not 0 < options.alpha < 1:
        raise ValueError(f"--alpha must be in (0, 1), got {options.alpha}")
    if not 0 < options.calibration_share < 1:
        raise ValueError(f"--calibration-share must be in (0, 1), got {options.calibration_share}")
    if options.max_dims < 1 or options.l2 < 0:
        raise ValueError(f"--max-dims must be >= 1 and --l2 >= 0, got {options.max_dims} and {options.l2}")
    if not options.inputs:
        raise ValueError("the episodes carry no monitor input with a value: name some with --inputs")


def _rate(flags: np.ndarray) -> str:
    return "n/a" if flags.size == 0 else f"{flags.mean():.3f} ({int(flags.sum())}/{flags.size})"


def report(monitor: Monitor, rollouts: Rollouts, options: FitOptions, out: pathlib.Path) -> str:
    """One short table: what was fitted on what, its AUROC on the training episodes (each episode's maximum step
    score against its outcome), and the threshold with the share of calibration successes it flags."""
    success = np.array([e.success for e in rollouts.episodes])
    training, calibration = split_episodes(success, options.calibration_share, options.seed)
    scores = [monitor.score_steps(e.matrix(monitor.inputs), e.prompts) for e in rollouts.episodes]
    maxima = np.array([episode_max(s) for s in scores])
    auroc = roc_auc(~success[training], maxima[training])
    ranked = f"AUROC {auroc:.3f}" if math.isfinite(auroc) else "no AUROC (a failure and a success are needed)"
    threshold = "never flags" if math.isinf(monitor.threshold) else f"{monitor.threshold:.6g}"
    inputs = ", ".join(i.name for i in monitor.inputs)
    rows = [
        ("monitor", f"{out} ({monitor.kind}{', temporal' if monitor.temporal else ''})"),
        ("inputs", inputs if len(inputs) <= 80 else f"{len(monitor.inputs)} inputs, {monitor.input_dim} values"),
        *(
            [("samples", f"{monitor.sample_spread} action chunks a call for sample_spread")]
            if monitor.sample_spread
            else []
        ),
        ("episodes", f"{success.size} ({int((~success).sum())} failed), horizon {rollouts.execution_horizon}"),
        *([("trusted on", "; ".join(monitor.prompts))] if monitor.kind == "gated" else []),
        *(
            [("trained on", f"{len(monitor.trained_on)} instructions; a step under any other flags at once")]
            if monitor.trained_on
            else []
        ),
        ("training", f"{training.size} episodes ({int((~success[training]).sum())} failed), {ranked}"),
        ("threshold", f"{threshold} for alpha {monitor.alpha:g}"),
        ("calibration", f"{calibration.size} successes, false alarms {_rate(maxima[calibration] > monitor.threshold)}"),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
