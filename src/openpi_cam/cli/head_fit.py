"""`openpi-cam head fit MAPS... --out FILE`: an occlusion head fitted to a policy's own occlusion maps, saved as one
file (`model.occlusion_head`), its held-out figures printed."""

from __future__ import annotations

import pathlib
import sys
from typing import Any

import tyro

from openpi_cam.maps.head_fit import HeadFitOptions, fit
from openpi_cam.model.occlusion_head import OcclusionHead, save
from openpi_cam.vocabulary import MapKind

COMMAND = "head fit"
DEFAULTS = HeadFitOptions()


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{value:.0%}"


def _rho(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f}"


def format_figures(head: OcclusionHead) -> str:
    """The fit's held-out figures as a table: per camera, the top-1 agreement and Spearman correlation with
    occlusion of the head, the position prior and each input kind alone."""
    record: dict[str, Any] = head.fit
    figures = record["figures"]["held_out"]
    examples, options = record["examples"], record["options"]
    lines = [
        f"occlusion head for {head.model.get('config')} ({head.family}), {head.target} maps, inputs "
        f"{' '.join(head.inputs)}, {'linear' if not head.hidden else f'{head.hidden} hidden units'}",
        f"fitted on {examples['fitting']} camera maps; held out: {examples['held_out']} camera maps of "
        f"{len(record['held_out_episodes'])} of {record['episodes']} episodes (seed {options['seed']})",
    ]
    cameras = [*figures["by_camera"].items(), ("all cameras", figures["all"])]
    width = max(len(c) for c, _ in cameras) + 2
    lines += [
        "",
        f"{'held-out, against occlusion':<{width + 18}}{'top-1':>8}{'Spearman median':>17}{'mean':>7}{'maps':>6}",
    ]
    for camera, per_camera in cameras:
        if not per_camera["head"]["examples"]:
            lines.append(f"{camera:<{width}}no held-out maps (never valid, or occlusion all zeros)")
            continue
        rows = [("head", per_camera["head"]), ("position prior", per_camera["prior"])]
        rows += [(f"{k} alone", v) for k, v in per_camera["inputs"].items()]
        for i, (name, f) in enumerate(rows):
            label = f"{camera if i == 0 else '':<{width}}{name:<18}"
            lines.append(
                f"{label}{_percent(f['top1']):>8}{_rho(f['spearman_median']):>17}{_rho(f['spearman_mean']):>7}"
                f"{f['examples']:>6}"
            )
    lines.append(f"deletion: {record['figures']['deletion']}")
    return "\n".join(lines)


def main(
    maps: tyro.conf.Positional[tuple[pathlib.Path, ...]],
    out: pathlib.Path,
    inputs: tuple[MapKind, ...] = DEFAULTS.inputs,  # type: ignore[assignment]
    hidden: int = DEFAULTS.hidden,
    seed: int = DEFAULTS.seed,
    holdout: float = DEFAULTS.holdout,
    steps: int = DEFAULTS.steps,
    learning_rate: float = DEFAULTS.learning_rate,
    temperature: float = DEFAULTS.temperature,
    mse_weight: float = DEFAULTS.mse_weight,
    weight_decay: float = DEFAULTS.weight_decay,
) -> int:
    """Fit an occlusion head to a policy's own occlusion maps and save it as one JSON file; `--head FILE` (or the
    file `occlusion_head.json` in the model's assets) then serves the `occlusion-head` kind. Exit status 1 with one
    line on bad input.

    Args:
        maps: maps datasets of one policy, explained with the input kinds and `occlusion` (`openpi-cam
            explain-dataset DATASET --maps gradcam gradnorm lrp occlusion`).
        out: the head file to write.
        inputs: the kinds the head reads (their maps are computed with the kind, at their cost).
        hidden: tanh hidden units of the per-patch model; 0: a linear head.
        seed: seeds the initialisation and which episodes are held out.
        holdout: the share of episodes held out of the fit, on which the printed figures are measured.
        steps: full-batch Adam steps.
        learning_rate: Adam's step size.
        temperature: of the listwise loss's softmax over a camera's patches (normalised maps peak at 1).
        mse_weight: weight of the squared error beside the listwise loss (it fixes the map's scale).
        weight_decay: L2 penalty on the weights.
    """
    try:
        options = HeadFitOptions(
            inputs=tuple(inputs),
            hidden=hidden,
            steps=steps,
            learning_rate=learning_rate,
            temperature=temperature,
            mse_weight=mse_weight,
            weight_decay=weight_decay,
            holdout=holdout,
            seed=seed,
        )
        head = fit(maps, options)
        save(head, out)
    except (ValueError, FileNotFoundError, OSError) as e:
        print(f"openpi-cam {COMMAND}: {e}", file=sys.stderr)
        return 1
    print(format_figures(head))
    print(f"openpi-cam {COMMAND}: wrote {out}", file=sys.stderr)
    return 0
