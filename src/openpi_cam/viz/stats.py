"""Per-step, per-camera statistics of one kind of map in a CAM run (`openpi-cam stats`), and the step view every
renderer draws from.

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
from typing import Any, Literal

import numpy as np

from openpi_cam.cam.faithfulness import nuisance_mass_ratio, target_cells
from openpi_cam.cam.run_evidence import read_check
from openpi_cam.cam.run_format import CAMStep, StepMeta, client_extra
from openpi_cam.viz.overlay import reduce_tokens
from openpi_cam.viz.text import finite_mean
from openpi_cam.vocabulary import MAP_KIND_INFO


@dataclasses.dataclass(frozen=True)
class LoadedView:
    """A step's arrays of one kind, read once (what one rendering iteration needs), or not yet written (a live
    stream's step)."""

    seq: int
    meta: StepMeta
    kind: str
    maps: Mapping[str, np.ndarray]
    frames: Mapping[str, np.ndarray]
    model_frames: Mapping[str, np.ndarray]
    extra: Mapping[str, Any]


class MapView:
    """A logged step seen through one map kind. It keeps no arrays: each access reads the step file, and `loaded()`
    reads it once for a stretch of work, so walking a long run never holds every map and frame in memory."""

    def __init__(self, step: CAMStep, kind: str) -> None:
        self._step = step
        self.kind = kind
        self.seq = step.seq
        self.meta = step.meta

    def loaded(self) -> LoadedView:
        arrays = self._step.lazy().arrays()
        maps, extra = arrays.maps.get(self.kind, {}), client_extra(self.meta, arrays)
        return LoadedView(
            seq=self.seq,
            meta=self.meta,
            kind=self.kind,
            maps=maps,
            frames=arrays.frames,
            model_frames=arrays.model_frames,
            extra=extra,
        )

    @property
    def maps(self) -> Mapping[str, np.ndarray]:
        return self._step.lazy().maps_of(self.kind)

    @property
    def frames(self) -> Mapping[str, np.ndarray]:
        return self._step.lazy().frames

    @property
    def model_frames(self) -> Mapping[str, np.ndarray]:
        return self._step.lazy().model_frames

    @property
    def extra(self) -> Mapping[str, Any]:
        return self._step.lazy().extra


class MissingMaps(ValueError):
    """The run holds no maps of the requested kind."""


def view_steps(steps: Iterable[CAMStep], kind: str) -> list[MapView]:
    """The steps in logging order, seen through `kind`; a run without any map of that kind is refused up front."""
    if kind not in MAP_KIND_INFO:
        raise ValueError(f"unknown map kind {kind!r}; expected one of {sorted(MAP_KIND_INFO)}")
    steps = sorted(steps, key=lambda s: s.seq)
    if steps and not any(kind in step_kinds(s) for s in steps):
        raise MissingMaps(f"this run has no {MAP_KIND_INFO[kind].label} maps ({MAP_KIND_INFO[kind].prefix}<camera>)")
    return [MapView(s, kind) for s in steps]


def step_kinds(step: CAMStep) -> tuple[str, ...]:
    """The map kinds a step carries, from its metadata when it lists them (no array read), else from its file."""
    listed = step.meta.map_kinds
    return listed if listed is not None else step.map_kinds


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
    # Share of the map's positive mass outside the ground-truth box the client sent (`cam_extra/target_box`; Zhang
    # et al.'s nuisance mass ratio); NaN for cameras without a box.
    nuisance_mass: float = math.nan
    # The step's spot check of this kind (`meta.check`): the score drop of painting the map's top patch alone, and the
    # largest drop of the random patches painted alone; NaN without a check.
    check_top_drop: float = math.nan
    check_random_max: float = math.nan


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
    # the step's reliance on each camera and its prompt (`run_format.Reliance.figures`); {} when not measured
    reliance: dict[str, float | None] = dataclasses.field(default_factory=dict)

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


def camera_stats(m: np.ndarray | None, valid: bool, total: float) -> CameraStats:
    if m is None or not valid:
        return CameraStats(
            valid=False,
            mass=0.0,
            share=0.0,
            entropy=math.nan,
            entropy_norm=math.nan,
            peak=None,
            peak_value=math.nan,
            peak_shift=math.nan,
            peak_stayed=None,
        )
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


def compute_stats(steps: Iterable[MapView]) -> list[StepStats]:
    """Statistics for every step in logging order; peak stability links consecutive steps of one connection."""
    out: list[StepStats] = []
    last_peak: dict[tuple[str, str], tuple[int, int] | None] = {}
    for s in sorted(steps, key=lambda s: s.seq):
        meta = s.meta
        names = list(meta.cameras) + [c for c in s.maps if c not in meta.cameras]
        valid = {c: meta.cameras[c].valid if c in meta.cameras else True for c in names}
        maps = {c: reduce_tokens(s.maps[c]) if c in s.maps else None for c in names}
        total = sum(float(m.sum()) for c, m in maps.items() if m is not None and valid[c])
        connection = meta.connection or ""
        checked = read_check(meta, s.kind)
        cameras: dict[str, CameraStats] = {}
        for c in names:
            cs = camera_stats(maps[c], valid[c], total)
            if c in checked:
                top, randoms = checked[c]
                cs = dataclasses.replace(cs, check_top_drop=top, check_random_max=max(randoms, default=math.nan))
            cells = None if maps[c] is None else target_cells(meta, c, maps[c].shape, None, s.extra)
            if cs.valid and cells is not None:
                cs = dataclasses.replace(cs, nuisance_mass=nuisance_mass_ratio(maps[c], cells))
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
                step=-1 if meta.step is None else meta.step,
                timestamp=math.nan if meta.timestamp is None else meta.timestamp,
                target=meta.target,
                score=mean_score(meta.score),
                token_ids=meta.token_ids,
                cameras=cameras,
                reliance={} if meta.reliance is None else meta.reliance.figures(),
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


def _reliance_names(stats: Sequence[StepStats]) -> list[str]:
    """The reliance figures any step has, in the order the steps first give them."""
    return list(dict.fromkeys(name for st in stats for name in st.reliance))


def to_rows(stats: Sequence[StepStats]) -> list[dict[str, Any]]:
    """One flat row per step with `<camera>/<field>` columns, and the reliance figures where any step has them;
    missing values are None."""
    cams = camera_names(stats)
    reliance_names = _reliance_names(stats)
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
                f"{c}/nuisance_mass": _nan_to_none(cs.nuisance_mass) if cs is not None else None,
                f"{c}/check_top_drop": _nan_to_none(cs.check_top_drop) if cs is not None else None,
                f"{c}/check_random_max": _nan_to_none(cs.check_random_max) if cs is not None else None,
            }
        rows.append(row | {name: st.reliance.get(name) for name in reliance_names})
    return rows


def aggregate(stats: Sequence[StepStats]) -> dict[str, Any]:
    """Run-level summary: per camera mean share/entropy, peak-stay rate, mean shift, and dominance counts; the mean
    reliance figures where steps have them."""
    cams = camera_names(stats)
    dominant = [st.dominant for st in stats]
    per_camera: dict[str, Any] = {}
    for c in cams:
        cs = [st.cameras[c] for st in stats if c in st.cameras]
        stayed = [x.peak_stayed for x in cs if x.peak_stayed is not None]
        per_camera[c] = {
            "valid_steps": sum(x.valid for x in cs),
            "mean_share": finite_mean(x.share for x in cs if x.valid),
            "mean_entropy": finite_mean(x.entropy for x in cs),
            "mean_entropy_norm": finite_mean(x.entropy_norm for x in cs),
            "mean_peak_shift": finite_mean(x.peak_shift for x in cs),
            "peak_stay_rate": float(np.mean(stayed)) if stayed else None,
            "dominant_steps": dominant.count(c),
        }
    reliance_names = _reliance_names(stats)
    return {
        "steps": len(stats),
        "connections": len({st.connection for st in stats}),
        "mean_score": finite_mean(st.score for st in stats),
        "cameras": per_camera,
        **(
            {"mean_reliance": {n: finite_mean(st.reliance.get(n) for st in stats) for n in reliance_names}}
            if reliance_names
            else {}
        ),
    }


def write_table(
    rows: list[dict[str, Any]], fmt: Literal["csv", "json", "parquet"], summary: dict[str, Any], rows_key: str = "steps"
) -> bytes:
    """The rows serialised as `fmt`; JSON also carries the summary (the rows under `rows_key`: a run's steps, a maps
    dataset's frames), parquet keeps it in the file metadata."""
    if fmt == "json":
        return (json.dumps({"summary": summary, rows_key: rows}, indent=1) + "\n").encode()
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


def step_scale(st: StepStats) -> float:
    """The per-step normaliser: the largest value over the step's valid cameras."""
    values = [cs.peak_value for cs in st.cameras.values() if cs.valid and not math.isnan(cs.peak_value)]
    return max(values, default=0.0)


def emit_table(data: bytes, out: pathlib.Path | None, what: str) -> None:
    """Writes a statistics table to `out` (saying so on stderr), or to stdout when `out` is None."""
    if out is None:
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    print(f"wrote {what} to {out}", file=sys.stderr)
