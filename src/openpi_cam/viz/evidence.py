"""The evidence drawn beside a map: how faithful that kind of map measured on this run, and on this step.

A heatmap alone invites belief. Every rendering therefore carries, for the kind it draws:
* the run's own `openpi-cam faithfulness` figures when the run has a report (RUN_DIR/faithfulness.json,
  `cam.faithfulness_run`), per run and per step;
* the spot check stored with each step (`meta.check`, `cam.spot_check`): the score drop of painting the map's top
  patch alone next to the drops of a few random patches; a top patch no better than a random one beats all R of
  them in 1 / (R + 1) of the steps, the chance level shown beside the rate;
* or, with neither, a plain statement that the maps were not measured and the command that measures them;
* and what the maps show by themselves: the share of camera-steps whose map is all zero (Grad-CAM's ReLU empties it
  often) and, for IG, the completeness check stored with every step.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.cam.run_evidence import REPORT_FILE, ig_summary, read_check, read_report
from openpi_cam.cam.run_format import CAMRun
from openpi_cam.viz.stats import StepStats
from openpi_cam.viz.text import percent
from openpi_cam.vocabulary import MAP_KIND_INFO


@dataclasses.dataclass(frozen=True)
class CameraFigures:
    """A camera's run-level figures for one kind, from the faithfulness report (None: not measured)."""

    camera: str
    steps: int  # steps whose best single patch lowered the score (the deletion figures' sample)
    deletion_k1: float | None  # median drop of the top patch / the best patch's drop
    random_k1: float | None  # the same for a random patch
    top1_occlusion: float | None  # share of steps whose top patch is the best patch
    randomisation: float | None  # mean |Spearman| with a re-initialised model's map (lower: more model-dependent)
    null: float | None  # mean |Spearman| between unrelated steps' maps
    pointing: float | None  # share of boxed steps whose peak lies in the box
    pointing_chance: float | None


@dataclasses.dataclass(frozen=True)
class StepFigures:
    """One step and camera: the drop of painting the map's top patch alone, as a fraction of the best patch's."""

    deletion_k1: float | None
    random_k1: float | None
    top1_occlusion: bool | None


@dataclasses.dataclass(frozen=True)
class CheckFigures:
    """One step and camera's spot check for one kind: score drops of painting single patches."""

    top_drop: float  # the map's top patch
    random_drops: tuple[float, ...]  # the random patches

    @property
    def beats_random(self) -> bool:
        return bool(self.random_drops) and self.top_drop > max(self.random_drops)


@dataclasses.dataclass(frozen=True)
class CheckSummary:
    """A camera's spot checks over the run, for one kind."""

    camera: str
    steps: int
    median_top_drop: float
    median_random_drop: float  # median over steps of the mean random drop
    beats_random: float  # share of steps whose top patch drops the score more than every random patch
    chance: float  # that share for a top patch no better than a random one: 1 / (R + 1)


@dataclasses.dataclass(frozen=True)
class MapEvidence:
    kind: str
    note: str
    status: str  # "measured" (a report), "spot-checked" (only the steps' checks) or "missing"
    status_line: str  # one sentence on where the figures come from, or how to get them
    cameras: tuple[CameraFigures, ...]
    steps: Mapping[int, Mapping[str, StepFigures]]
    checks: Mapping[int, Mapping[str, CheckFigures]]  # seq -> camera -> the step's spot check of this kind
    check_summary: tuple[CheckSummary, ...]
    zero_share: float | None  # share of valid camera-steps whose map is all zero (None: no valid camera-step)
    ig_completeness: Mapping[str, Any] | None  # `run_evidence.ig_summary` of the run's steps (ig only)

    def step_line(self, seq: int, camera: str) -> str:
        """This step's figure for one camera, in a few words: the report's (top patch's drop / the best patch's, next
        to a random patch's), else the spot check's (the top patch's score drop next to the largest random one)."""
        figures = self.steps.get(seq, {}).get(camera)
        check = self.checks.get(seq, {}).get(camera)
        if figures is not None:
            if figures.deletion_k1 is None:
                return "no patch lowers the score"
            return f"{figures.deletion_k1:.2f} of best (random {_num(figures.random_k1)})"
        if check is not None:
            worst = f"random <= {max(check.random_drops):.3g}" if check.random_drops else "no random patch"
            return f"drop {check.top_drop:.3g} ({worst})"
        return "step not in the report" if self.status == "measured" else "not measured"


def _finite(value: Any) -> float | None:
    """A report's number, None where it has none (null; a report written with NaN reads the same)."""
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _field(entry: Mapping[str, Any] | None, field: str = "median") -> float | None:
    return _finite(entry.get(field)) if isinstance(entry, Mapping) else None


def _camera_figures(camera: str, cam: Mapping[str, Any], kind: str) -> CameraFigures:
    kinds = cam.get("kinds", {})
    e, rand = kinds.get(kind, {}), kinds.get("random", {})
    chance = e.get("pointing_chance")
    return CameraFigures(
        camera=camera,
        steps=int(cam.get("steps_with_positive_optimum", 0)),
        deletion_k1=_field(e.get("deletion_k1")),
        random_k1=_field(rand.get("deletion_k1")),
        top1_occlusion=_field(e.get("top1_occlusion"), "mean"),
        randomisation=_field(e.get("randomisation_abs_spearman"), "mean"),
        null=_field(e.get("null_abs_spearman"), "mean"),
        pointing=_field(e.get("pointing"), "mean"),
        pointing_chance=_finite(chance),
    )


def _step_figures(report: Mapping[str, Any], kind: str) -> dict[int, dict[str, StepFigures]]:
    out: dict[int, dict[str, StepFigures]] = {}
    for seq, cams in (report.get("steps") or {}).items():
        if not str(seq).isdigit() or not isinstance(cams, Mapping):
            continue
        for camera, f in cams.items():
            k1, top1 = f.get("deletion_k1", {}), f.get("top1_occlusion", {})
            if kind in k1:
                figures = StepFigures(_finite(k1[kind]), _finite(k1.get("random")), top1.get(kind))
                out.setdefault(int(seq), {})[camera] = figures
    return out


def zero_share(stats: Sequence[StepStats]) -> float | None:
    """Share of the valid camera-steps whose drawn map carries no positive mass."""
    flags = [cs.mass <= 0 for st in stats for cs in st.cameras.values() if cs.valid]
    return sum(flags) / len(flags) if flags else None


def _checks(run: CAMRun, kind: str) -> dict[int, dict[str, CheckFigures]]:
    out: dict[int, dict[str, CheckFigures]] = {}
    for step in run.steps:
        if checked := read_check(step.meta, kind):
            out[step.seq] = {camera: CheckFigures(*figures) for camera, figures in checked.items()}
    return out


def _check_summary(checks: Mapping[int, Mapping[str, CheckFigures]]) -> tuple[CheckSummary, ...]:
    by_camera: dict[str, list[CheckFigures]] = {}
    for cams in checks.values():
        for camera, f in cams.items():
            if f.random_drops:
                by_camera.setdefault(camera, []).append(f)
    return tuple(
        CheckSummary(
            camera=camera,
            steps=len(fs),
            median_top_drop=float(np.median([f.top_drop for f in fs])),
            median_random_drop=float(np.median([np.mean(f.random_drops) for f in fs])),
            beats_random=float(np.mean([f.beats_random for f in fs])),
            chance=float(np.mean([1.0 / (len(f.random_drops) + 1) for f in fs])),
        )
        for camera, fs in by_camera.items()
    )


def map_evidence(run: CAMRun, kind: str, stats: Sequence[StepStats]) -> MapEvidence:
    """The evidence for `kind`'s maps in `run`: its faithfulness report if it has one for this run (a report written
    for another run is not used), and the spot checks its steps carry; with neither, a plain statement that the
    maps were not measured."""
    report = read_report(run.run_dir)
    run_id = run.run_info.get("run_id", run.run_dir.name)
    drawn = len(stats)
    command = f"openpi-cam faithfulness {run.run_dir}"
    cameras: tuple[CameraFigures, ...] = ()
    steps: dict[int, dict[str, StepFigures]] = {}
    checks = _checks(run, kind)
    usable = (
        report is not None
        and report.get("run_id", run_id) == run_id
        and isinstance(report.get("cameras"), Mapping)
        and any(kind in cam.get("kinds", {}) for cam in report["cameras"].values())
    )
    if not usable:
        status = "spot-checked" if checks else "missing"
        line = (
            f"No faithfulness report for this run's {kind} maps: `{command}` re-runs the model under interventions "
            f"and writes {REPORT_FILE} beside the steps; render again to see its figures here."
        )
        if checks:
            line = f"Spot-checked live ({len(checks)} of {drawn} steps). " + line
    else:
        status = "measured"
        cameras = tuple(_camera_figures(c, cam, kind) for c, cam in report["cameras"].items())
        steps = _step_figures(report, kind)
        evaluated = int(report.get("steps_evaluated", 0))
        line = f"Measured on this run by `openpi-cam faithfulness` ({REPORT_FILE}): {evaluated} steps re-scored"
        line += f" of the {drawn} drawn." if evaluated < drawn else "."
    return MapEvidence(
        kind=kind,
        note=MAP_KIND_INFO[kind].note if kind in MAP_KIND_INFO else "",
        status=status,
        status_line=line,
        cameras=cameras,
        steps=steps,
        checks=checks,
        check_summary=_check_summary(checks),
        zero_share=zero_share(stats),
        ig_completeness=ig_summary(run) if kind == "ig" else None,
    )


def _pct(x: float | None) -> str:
    return percent(x, 0)


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def panel_header(evidence: MapEvidence) -> str:
    """The line a panel carries above its cameras: what the figure under each camera is, or why there is none."""
    if evidence.status == "measured":
        return "faithfulness, under each camera: its top patch's score drop / the best patch's"
    if evidence.status == "spot-checked":
        return "spot check, under each camera: score drop of painting its top patch vs random patches"
    return "faithfulness: not measured on this run (openpi-cam faithfulness RUN_DIR)"


def check_rows(evidence: MapEvidence) -> list[tuple[str, ...]]:
    """(camera, steps checked, median top-patch drop, median random-patch drop, beats every random patch (chance))"""
    return [
        (
            s.camera,
            str(s.steps),
            f"{s.median_top_drop:.3g}",
            f"{s.median_random_drop:.3g}",
            f"{_pct(s.beats_random)} (chance {_pct(s.chance)})",
        )
        for s in evidence.check_summary
    ]


# The columns of `summary_rows` and `check_rows`, as every renderer heads them.
SUMMARY_COLUMNS = (
    "camera",
    "steps scored",
    "top patch's drop / best patch's (median)",
    "top patch = best patch",
    "|rho| with a re-initialised model",
    "pointing",
)
CHECK_COLUMNS = (
    "camera",
    "steps spot-checked",
    "top patch's score drop (median)",
    "random patch's (median)",
    "top patch beats every random patch",
)


def summary_rows(evidence: MapEvidence) -> list[tuple[str, ...]]:
    """(camera, steps, deletion k=1 vs random, top-1 = occlusion, randomisation vs null, pointing vs chance) rows."""
    rows = []
    for f in evidence.cameras:
        rand = "-" if f.randomisation is None else f"{f.randomisation:.2f} (null {_num(f.null)})"
        point = "-" if f.pointing is None else f"{_pct(f.pointing)} (chance {_pct(f.pointing_chance)})"
        deletion = f"{_num(f.deletion_k1)} (random {_num(f.random_k1)})"
        rows.append((f.camera, str(f.steps), deletion, _pct(f.top1_occlusion), rand, point))
    return rows
