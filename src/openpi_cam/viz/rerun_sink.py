"""A CAM run as a Rerun recording (`.rrd`), for people who already look at robot data in the Rerun viewer.

Layout, per connection `<conn>` (escaped as one entity-path part) and model camera `<cam>`:
  /<conn>/<cam>/frame     the image the map is drawn on (client frame, else model frame)
  /<conn>/<cam>/overlay   the map blended over it, as `openpi-cam render` draws it
  /<conn>/share/<cam>     the camera's share of the step's attention mass (scalar; openpi_cam.viz.stats)
  /<conn>/score           the explained score (mean over tokens for multi-token targets)
  /<conn>/faithfulness/<cam>  with a faithfulness report for the run: the score drop of painting the step's top patch
                          alone / the best single patch's drop (`viz.evidence`); where the report has that step
  /faithfulness           (static) what the drawn kind is and how faithful it measured on this run, or that it was not
Timelines: `step` (the request's index in its connection), `seq` (logging order) and `time` (request time).

`rerun-sdk` is optional (`pip install "openpi-cam[rerun]"`); it is imported only when a recording is written.
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Mapping
from typing import Any, Literal

from openpi_cam.cam.run_format import load_run
from openpi_cam.viz.evidence import (
    CHECK_COLUMNS,
    SUMMARY_COLUMNS,
    MapEvidence,
    check_rows,
    map_evidence,
    summary_rows,
)
from openpi_cam.viz.overlay import camera_image, camera_overlay
from openpi_cam.viz.stats import compute_stats, step_scale, view_steps
from openpi_cam.vocabulary import DEFAULT_MAP_KIND

RERUN_MISSING = 'writing a Rerun recording needs rerun-sdk: pip install "openpi-cam[rerun]"'


def import_rerun() -> Any:
    try:
        import rerun
    except ImportError as e:
        raise ImportError(RERUN_MISSING) from e
    return rerun


def _markdown_table(columns: tuple[str, ...], rows: list[tuple[str, ...]]) -> list[str]:
    return ["| " + " | ".join(row) + " |" for row in (columns, ("---",) * len(columns), *rows)]


def _evidence_text(evidence: MapEvidence) -> str:
    """The run-level evidence as Markdown, as the HTML report's section: the kind's note, where the figures come
    from, the report's row per camera and the stored spot checks' summary."""
    lines = [f"# how faithful are these {evidence.kind} maps?", "", evidence.note, "", evidence.status_line]
    if evidence.cameras:
        lines += ["", *_markdown_table(SUMMARY_COLUMNS, summary_rows(evidence))]
    if evidence.check_summary:
        lines += ["", "spot checks stored with the steps (live or offline explain)", ""]
        lines += _markdown_table(CHECK_COLUMNS, check_rows(evidence))
    return "\n".join(lines)


def log_reliance(rec: Any, rr: Any, root: str, figures: Mapping[str, float | None]) -> None:
    """Logs a step's reliance figures (`<camera or prompt>/reliance_<score or actions>`, `Reliance.figures`) as
    scalars at `<root>/reliance_<score or actions>/<camera or prompt>`; figures not measured (None) are left out."""
    for name, value in figures.items():
        if value is not None:
            what, figure = name.rsplit("/", 1)
            rec.log(f"{root}/{figure}/{rr.escape_entity_path_part(what)}", rr.Scalars(value))


def write_rrd(
    run_dir: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    norm: Literal["step", "run"] = "step",
    alpha: float = 0.5,
    map_kind: str = DEFAULT_MAP_KIND,
) -> pathlib.Path:
    """Writes the run's frames, overlays (of `map_kind` maps), per-camera attention shares, each step's reliance
    when it was measured and, when the run has a faithfulness report, each step's figure for the drawn kind to
    `out_path`."""
    rr = import_rerun()
    run = load_run(run_dir, load_arrays=False)
    steps = view_steps(run.steps, map_kind)
    stats = compute_stats(steps)
    evidence = map_evidence(run, map_kind, stats)
    run_max = max((step_scale(st) for st in stats), default=0.0)
    out_path = pathlib.Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("openpi-cam", recording_id=str(run.run_info.get("run_id", run.run_dir.name)))
    rec.save(out_path)
    try:
        text = rr.TextDocument(_evidence_text(evidence), media_type=rr.MediaType.MARKDOWN)
        rec.log("/faithfulness", text, static=True)
        for view, st in zip(steps, stats, strict=True):
            step = view.loaded()
            rec.set_time("step", sequence=st.step)
            rec.set_time("seq", sequence=st.seq)
            if math.isfinite(st.timestamp):
                rec.set_time("time", timestamp=st.timestamp)
            conn = rr.escape_entity_path_part(st.connection)
            scale = run_max if norm == "run" else step_scale(st)
            if math.isfinite(st.score):
                rec.log(f"/{conn}/score", rr.Scalars(st.score))
            log_reliance(rec, rr, f"/{conn}", st.reliance)
            for camera in list(step.meta.cameras) or list(step.maps):
                cam = rr.escape_entity_path_part(camera)
                image, _ = camera_image(step, camera)
                rec.log(f"/{conn}/{cam}/frame", rr.Image(image))
                rec.log(f"/{conn}/{cam}/overlay", rr.Image(camera_overlay(step, camera, scale, alpha)))
                if camera in st.cameras:
                    rec.log(f"/{conn}/share/{cam}", rr.Scalars(st.cameras[camera].share))
                figure = evidence.steps.get(st.seq, {}).get(camera)
                if figure is not None and figure.deletion_k1 is not None:
                    rec.log(f"/{conn}/faithfulness/{cam}", rr.Scalars(figure.deletion_k1))
    finally:
        rec.flush()
        rec.disconnect()
    return out_path
