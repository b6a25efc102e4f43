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

Streamed live (`serve --cam.rerun ADDRESS`, `LiveRerun`), each explained step as it is written, on the same paths,
plus:
  /<conn>/<cam>/<kind>    every kind the step carries, drawn as the overlay is
  /<conn>/chunk           the served chunk in the model's normalised action units (a tensor [horizon, dims]), where
                          the call carries it (a monitor's signals; pi0 / pi0.5's output)
  /<conn>/monitor/score, /<conn>/monitor/flag   with a failure monitor: the call's score and its connection's flag

`rerun-sdk` is optional (`pip install "openpi-cam[rerun]"`); it is imported only when a recording is written.
"""

from __future__ import annotations

import logging
import math
import os
import pathlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from openpi_cam.cam.run_format import StepMeta, StepRecord, load_run
from openpi_cam.viz.evidence import (
    CHECK_COLUMNS,
    SUMMARY_COLUMNS,
    MapEvidence,
    check_rows,
    map_evidence,
    summary_rows,
)
from openpi_cam.viz.overlay import StepView, camera_image, camera_overlay
from openpi_cam.viz.stats import LoadedView, StepStats, compute_stats, step_scale, view_steps
from openpi_cam.vocabulary import NORMALIZED_CHUNK, drawn_kind

if TYPE_CHECKING:  # the viewers import no JAX; the trace only passes through
    from openpi_cam.policies.policy import InferenceTrace

logger = logging.getLogger(__name__)

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


def cameras_of(step: StepView) -> list[str]:
    return list(step.meta.cameras) or list(step.maps)


def log_step(rec: Any, rr: Any, step: StepView, st: StepStats, scale: float, alpha: float) -> str:
    """Logs one step's score, reliance, and per camera its frame, overlay (the map divided by `scale`) and share, on
    the layout's paths; returns the step's root, `/<conn>`. The time is the caller's to set."""
    conn = "/" + rr.escape_entity_path_part(st.connection)
    if math.isfinite(st.score):
        rec.log(f"{conn}/score", rr.Scalars(st.score))
    log_reliance(rec, rr, conn, st.reliance)
    for camera in cameras_of(step):
        cam = rr.escape_entity_path_part(camera)
        image, _ = camera_image(step, camera)
        rec.log(f"{conn}/{cam}/frame", rr.Image(image))
        rec.log(f"{conn}/{cam}/overlay", rr.Image(camera_overlay(step, camera, scale, alpha)))
        if camera in st.cameras:
            rec.log(f"{conn}/share/{cam}", rr.Scalars(st.cameras[camera].share))
    return conn


def write_rrd(
    run_dir: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    norm: Literal["step", "run"] = "step",
    alpha: float = 0.5,
    map_kind: str | None = None,
) -> pathlib.Path:
    """Writes the run's frames, overlays (of `map_kind` maps), per-camera attention shares, each step's reliance
    when it was measured and, when the run has a faithfulness report, each step's figure for the drawn kind to
    `out_path`."""
    rr = import_rerun()
    run = load_run(run_dir, load_arrays=False)
    map_kind = map_kind or drawn_kind(run.map_kinds)
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
            conn = log_step(rec, rr, step, st, run_max if norm == "run" else step_scale(st), alpha)
            for camera in cameras_of(step):
                figure = evidence.steps.get(st.seq, {}).get(camera)
                if figure is not None and figure.deletion_k1 is not None:
                    rec.log(f"{conn}/faithfulness/{rr.escape_entity_path_part(camera)}", rr.Scalars(figure.deletion_k1))
    finally:
        rec.flush()
        rec.disconnect()
    return out_path


def _served_chunk(trace: InferenceTrace) -> np.ndarray | None:
    """The chunk in the model's normalised action units: the monitor's signal, else a flow family's raw output."""
    if NORMALIZED_CHUNK in trace.signals:
        return np.asarray(trace.signals[NORMALIZED_CHUNK])
    output = np.asarray(trace.output)
    return output if output.ndim == 2 and np.issubdtype(output.dtype, np.floating) else None


FLUSH_S = 2.0  # how long a step's logging waits for the viewer to take it before the stream gives up


class LiveRerun:
    """Streams each explained step of a serving side channel to a running Rerun viewer (`serve --cam.rerun`), as
    `write_rrd` lays a run out. Called on the side channel's worker only. A viewer that is not there or goes away
    must not stop serving or logging: any failure is logged once, and the stream then stops."""

    def __init__(self, address: str, kind: str | None = None, alpha: float = 0.5) -> None:
        rr = import_rerun()
        self.address, self.kind, self.alpha = address, kind, alpha
        self._rr = rr
        self._rec: Any = rr.RecordingStream("openpi-cam")
        self._seq = 0
        self.failed: str | None = None  # why the stream stopped
        try:
            self._rec.connect_grpc(address)
        except Exception as e:
            self._fail(e)

    def _fail(self, e: Exception) -> None:
        self.failed = f"{type(e).__name__}: {e}"
        logger.warning("Rerun stream to %s stopped: %s (serving and the run go on)", self.address, self.failed)

    def watch(self, record: StepRecord, trace: InferenceTrace) -> None:
        """Logs one written step (its record, and the call's trace for the chunk)."""
        if self.failed is not None:
            return
        try:
            self._log(record, trace)
            # A viewer that is not there is only found out by waiting for it: once per step, with a bound.
            self._rec.flush(timeout_sec=FLUSH_S)
        except Exception as e:
            self._fail(e)

    def _log(self, record: StepRecord, trace: InferenceTrace) -> None:
        rr, rec = self._rr, self._rec
        meta = StepMeta.from_json(
            {**record.meta, "seq": self._seq, "connection": record.connection, "step": record.step}
        )
        kinds = [k for k in record.maps if record.maps[k]]
        shown = self.kind if self.kind in kinds else (drawn_kind(kinds) if kinds else None)
        extra = {**meta.extra, **record.extra_arrays}
        views = {
            k: LoadedView(self._seq, meta, k, record.maps[k], record.frames, record.model_frames, extra) for k in kinds
        }
        rec.set_time("step", sequence=record.step)
        rec.set_time("seq", sequence=self._seq)
        rec.set_time("time", timestamp=record.timestamp)
        self._seq += 1
        if shown is None:
            return
        stats = {k: compute_stats([view])[0] for k, view in views.items()}  # type: ignore[list-item]
        conn = log_step(rec, rr, views[shown], stats[shown], step_scale(stats[shown]), self.alpha)
        for k, view in views.items():
            for camera in cameras_of(view):
                image = camera_overlay(view, camera, step_scale(stats[k]), self.alpha)
                rec.log(f"{conn}/{rr.escape_entity_path_part(camera)}/{k}", rr.Image(image))
        chunk = _served_chunk(trace)
        if chunk is not None:
            rec.log(f"{conn}/chunk", rr.Tensor(chunk, dim_names=("step", "dim")))
        if "score" in record.monitor:
            rec.log(f"{conn}/monitor/score", rr.Scalars(float(record.monitor["score"])))
        if "flag" in record.monitor:
            rec.log(f"{conn}/monitor/flag", rr.Scalars(float(record.monitor["flag"])))

    def close(self) -> None:
        """Sends what is buffered and lets the viewer go (it keeps what it received); nothing once the stream
        stopped (a disconnect would wait for the viewer that failed it)."""
        if self.failed is not None:
            return
        try:
            self._rec.flush(timeout_sec=FLUSH_S)
            self._rec.disconnect()
        except Exception as e:
            self._fail(e)
