"""Per-step, per-camera attention statistics of a CAM run, and `openpi-cam stats`.

Every number is computed on the same displayable map the renderer draws (`reduce_tokens`: multi-token maps are
averaged, negatives clipped). Cameras the model masked out (`valid: false`) carry no mass.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import pathlib
import sys
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Literal, Protocol

import numpy as np

from openpi_cam.viz.overlay import reduce_tokens


class StepLike(Protocol):
    """What the statistics need from a logged step (satisfied by the CAM reader's steps)."""

    seq: int
    meta: Mapping[str, Any]
    maps: Mapping[str, np.ndarray]


@dataclasses.dataclass(frozen=True)
class CameraStats:
    valid: bool
    mass: float
    share: float  # fraction of the step's total mass over cameras; 0 when the step has none
    entropy: float  # nats, of the map normalised to sum 1; NaN without mass
    entropy_norm: float  # entropy / log(cells), in [0, 1]
    peak: tuple[int, int] | None  # (row, col) of the maximum cell; None without mass
    peak_value: float
    peak_shift: float  # Euclidean peak displacement (cells) from this camera's previous step on the connection
    peak_stayed: bool | None  # None on a connection's first step or when either peak is missing


@dataclasses.dataclass(frozen=True)
class StepStats:
    seq: int
    connection: str
    step: int
    timestamp: float
    target: str
    score: float  # mean over tokens for multi-token targets
    token_ids: tuple[int, ...]
    cameras: dict[str, CameraStats]

    @property
    def dominant(self) -> str | None:
        """The camera holding the largest share, None when no camera has mass."""
        best = max(self.cameras.items(), key=lambda kv: kv[1].share, default=None)
        return best[0] if best is not None and best[1].share > 0 else None


def mean_score(score: float | Sequence[float] | None) -> float:
    if score is None:
        return math.nan
    values = np.atleast_1d(np.asarray(score, dtype=np.float64))
    return float(values.mean()) if values.size else math.nan


def map_entropy(m: np.ndarray) -> float:
    """Shannon entropy (nats) of a non-negative map normalised to sum 1; NaN when it has no mass."""
    total = float(m.sum())
    if total <= 0:
        return math.nan
    p = m[m > 0] / total
    return float(-(p * np.log(p)).sum())


def _camera_stats(m: np.ndarray | None, valid: bool, total: float) -> CameraStats:
    if m is None or not valid:
        return CameraStats(False, 0.0, 0.0, math.nan, math.nan, None, math.nan, math.nan, None)
    mass = float(m.sum())
    entropy = map_entropy(m)
    cells = m.size
    peak = tuple(int(i) for i in np.unravel_index(int(np.argmax(m)), m.shape)) if mass > 0 else None
    return CameraStats(
        valid=True,
        mass=mass,
        share=mass / total if total > 0 else 0.0,
        entropy=entropy,
        entropy_norm=entropy / math.log(cells) if cells > 1 and not math.isnan(entropy) else math.nan,
        peak=peak,  # type: ignore[arg-type]
        peak_value=float(m.max()) if m.size else math.nan,
        peak_shift=math.nan,
        peak_stayed=None,
    )


# The maps a logged step carries, both from one gradient: Grad-CAM (`cam/`) and the per-token gradient norm
# (`gradnorm/`).
MapKind = Literal["gradcam", "gradnorm"]
MAP_LABELS: dict[str, str] = {"gradcam": "Grad-CAM", "gradnorm": "gradient norm"}
MAP_KINDS: tuple[str, ...] = tuple(MAP_LABELS)


def maps_of(logged: Any, kind: str) -> Mapping[str, np.ndarray]:
    """The maps of one kind of a logged step or an explanation (both carry `maps` and `gradnorm_maps`)."""
    return logged.maps if kind == "gradcam" else logged.gradnorm_maps


class GradnormView:
    """A logged step whose `maps` are its per-token gradient-norm maps (`gradnorm/<camera>`), so that every renderer
    and statistic written for Grad-CAM maps works on them unchanged."""

    def __init__(self, step: Any) -> None:
        self.step = step
        self.seq = step.seq
        self.meta = step.meta

    @property
    def maps(self) -> Mapping[str, np.ndarray]:
        return maps_of(self.step, "gradnorm")

    def __getattr__(self, name: str) -> Any:  # frames, model_frames, file
        return getattr(self.step, name)


class MissingMaps(ValueError):
    """The run holds no maps of the requested kind."""


def with_map_kind(steps: Iterable[Any], kind: MapKind) -> list[Any]:
    """The steps as seen through the chosen map kind; a run logged without gradient-norm maps is refused up front."""
    steps = list(steps)
    if kind == "gradcam":
        return steps
    if kind != "gradnorm":
        raise ValueError(f"unknown map kind {kind!r}; expected one of {sorted(MAP_LABELS)}")
    if steps and not steps[0].gradnorm_maps:
        raise MissingMaps("this run has no gradient-norm maps (gradnorm/<camera>); it predates them")
    return [GradnormView(s) for s in steps]


def transient(step: StepLike) -> StepLike:
    """A copy of a reader step that reads its arrays on use and drops them afterwards, so that walking a long run
    does not keep every map and frame in memory; other step objects are returned as they are."""
    from openpi_cam.cam.reader import CAMStep

    if isinstance(step, GradnormView):
        return GradnormView(transient(step.step))  # type: ignore[return-value]
    return CAMStep(step.seq, dict(step.meta), step.file) if isinstance(step, CAMStep) else step


def compute_stats(steps: Iterable[StepLike]) -> list[StepStats]:
    """Statistics for every step in logging order; peak stability links consecutive steps of one connection."""
    out: list[StepStats] = []
    last_peak: dict[tuple[str, str], tuple[int, int] | None] = {}
    for s in map(transient, sorted(steps, key=lambda s: s.seq)):
        meta = s.meta
        cams_meta: Mapping[str, Any] = meta.get("cameras", {})
        names = list(cams_meta) + [c for c in s.maps if c not in cams_meta]
        valid = {c: bool(cams_meta.get(c, {}).get("valid", True)) for c in names}
        maps = {c: reduce_tokens(s.maps[c]) if c in s.maps else None for c in names}
        total = sum(float(m.sum()) for c, m in maps.items() if m is not None and valid[c])
        connection = str(meta.get("connection", ""))
        cameras: dict[str, CameraStats] = {}
        for c in names:
            cs = _camera_stats(maps[c], valid[c], total)
            key = (connection, c)
            if key in last_peak:
                prev = last_peak[key]
                if prev is not None and cs.peak is not None:
                    shift = math.hypot(cs.peak[0] - prev[0], cs.peak[1] - prev[1])
                    cs = dataclasses.replace(cs, peak_shift=shift, peak_stayed=shift == 0)
            last_peak[key] = cs.peak
            cameras[c] = cs
        out.append(
            StepStats(
                seq=int(s.seq),
                connection=connection,
                step=int(meta.get("step", -1)),
                timestamp=float(meta.get("timestamp", math.nan)),
                target=str(meta.get("target", "")),
                score=mean_score(meta.get("score")),
                token_ids=tuple(int(t) for t in meta.get("token_ids", ())),
                cameras=cameras,
            )
        )
    return out


def camera_names(stats: Sequence[StepStats]) -> list[str]:
    """All cameras of the run, in the order they first appear (model order)."""
    names: dict[str, None] = {}
    for st in stats:
        names.update(dict.fromkeys(st.cameras))
    return list(names)


def _nan_to_none(x: float) -> float | None:
    return None if isinstance(x, float) and math.isnan(x) else x


def to_rows(stats: Sequence[StepStats]) -> list[dict[str, Any]]:
    """One flat row per step with `<camera>/<field>` columns; missing values are None."""
    cams = camera_names(stats)
    rows = []
    for st in stats:
        row: dict[str, Any] = {
            "seq": st.seq,
            "connection": st.connection,
            "step": st.step,
            "timestamp": _nan_to_none(st.timestamp),
            "target": st.target,
            "score": _nan_to_none(st.score),
            "token_ids": " ".join(map(str, st.token_ids)),
            "dominant": st.dominant,
        }
        for c in cams:
            cs = st.cameras.get(c)
            peak = cs.peak if cs is not None else None
            row |= {
                f"{c}/valid": cs.valid if cs is not None else None,
                f"{c}/share": cs.share if cs is not None else None,
                f"{c}/entropy": _nan_to_none(cs.entropy) if cs is not None else None,
                f"{c}/entropy_norm": _nan_to_none(cs.entropy_norm) if cs is not None else None,
                f"{c}/peak_row": peak[0] if peak else None,
                f"{c}/peak_col": peak[1] if peak else None,
                f"{c}/peak_value": _nan_to_none(cs.peak_value) if cs is not None else None,
                f"{c}/peak_shift": _nan_to_none(cs.peak_shift) if cs is not None else None,
                f"{c}/peak_stayed": cs.peak_stayed if cs is not None else None,
            }
        rows.append(row)
    return rows


def _mean(values: Iterable[float]) -> float | None:
    v = [x for x in values if x is not None and not math.isnan(x)]
    return float(np.mean(v)) if v else None


def aggregate(stats: Sequence[StepStats]) -> dict[str, Any]:
    """Run-level summary: per camera mean share/entropy, peak-stay rate, mean shift, and dominance counts."""
    cams = camera_names(stats)
    dominant = [st.dominant for st in stats]
    per_camera: dict[str, Any] = {}
    for c in cams:
        cs = [st.cameras[c] for st in stats if c in st.cameras]
        stayed = [x.peak_stayed for x in cs if x.peak_stayed is not None]
        per_camera[c] = {
            "valid_steps": sum(x.valid for x in cs),
            "mean_share": _mean(x.share for x in cs if x.valid),
            "mean_entropy": _mean(x.entropy for x in cs),
            "mean_entropy_norm": _mean(x.entropy_norm for x in cs),
            "mean_peak_shift": _mean(x.peak_shift for x in cs),
            "peak_stay_rate": float(np.mean(stayed)) if stayed else None,
            "dominant_steps": dominant.count(c),
        }
    return {
        "steps": len(stats),
        "connections": len({st.connection for st in stats}),
        "mean_score": _mean(st.score for st in stats),
        "cameras": per_camera,
    }


def write_table(rows: list[dict[str, Any]], fmt: Literal["csv", "json", "parquet"], summary: dict[str, Any]) -> bytes:
    """The rows serialised as `fmt`; JSON also carries the run summary, parquet keeps it in the file metadata."""
    if fmt == "json":
        return (json.dumps({"summary": summary, "steps": rows}, indent=1) + "\n").encode()
    if fmt == "csv":
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["seq"], lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        return buf.getvalue().encode()
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as e:
        raise SystemExit("openpi-cam stats: parquet output needs pyarrow (pip install 'openpi-cam[parquet]')") from e
    table = pa.Table.from_pylist(rows).replace_schema_metadata({"openpi_cam.summary": json.dumps(summary)})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def stats_cmd(
    run_dir: pathlib.Path,
    /,
    format: Literal["csv", "json", "parquet"] = "csv",
    out: pathlib.Path | None = None,
    map: MapKind = "gradcam",
) -> int:
    """Per-step, per-camera attention statistics of a CAM run (one row per step, `<camera>/<field>` columns).

    Args:
        run_dir: a CAM run directory (holds run.json and steps/).
        format: csv, json (rows plus a run summary) or parquet (needs pyarrow; summary in the file metadata).
        out: output file; defaults to stdout for csv/json and RUN_DIR/stats.parquet for parquet.
        map: which map the statistics describe: Grad-CAM (`cam/`) or the per-token gradient norm (`gradnorm/`).
    """
    from openpi_cam.cam.reader import load_run

    try:
        steps = with_map_kind(load_run(run_dir, load_arrays=False).steps, map)
    except MissingMaps as e:
        print(f"openpi-cam stats: {e}", file=sys.stderr)
        return 2
    stats = compute_stats(steps)
    summary = aggregate(stats)
    data = write_table(to_rows(stats), format, summary)
    if out is None and format == "parquet":
        out = pathlib.Path(run_dir) / "stats.parquet"
    if out is None:
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
        print(f"wrote {len(stats)} steps to {out}", file=sys.stderr)
    return 0
