"""`openpi-cam stats RUN_DIR | MAPS_DATASET`: per-step (per-frame), per-camera statistics of one kind of map, as CSV,
JSON or parquet."""

from __future__ import annotations

import pathlib
import sys
from typing import Annotated, Literal

import tyro

from openpi_cam.cam.run_format import load_run
from openpi_cam.demo.recorded import PERTURBATION_FEATURE, perturbation_names
from openpi_cam.maps.dataset import MapsDataset, is_maps_dataset, open_maps_dataset
from openpi_cam.maps.views import ViewOptions, compute_views, detection_lines
from openpi_cam.viz.stats import MissingMaps, aggregate, compute_stats, emit_table, to_rows, view_steps, write_table
from openpi_cam.vocabulary import MapKind, drawn_kind

Format = Literal["csv", "json", "parquet"]


def main(
    run_dir: tyro.conf.Positional[pathlib.Path],
    format: Format = "csv",
    out: pathlib.Path | None = None,
    kind: Annotated[MapKind | None, tyro.conf.arg(aliases=("--map",))] = None,
) -> int:
    """Per-step, per-camera statistics of a CAM run's maps (one row per step, `<camera>/<field>` columns).

    Args:
        run_dir: a CAM run directory (holds run.json and steps/), or a maps dataset (`explain-dataset`'s output:
            one row per frame, and the dataset-level views in the JSON summary; `maps.views`; with outcomes, the
            failure detection table on stderr too).
        format: csv, json (rows plus a summary) or parquet (summary in the file metadata).
        out: output file; defaults to stdout for csv/json and RUN_DIR/stats.parquet (a maps dataset's
            stats-<kind>.parquet) for parquet.
        kind: which kind of map the statistics describe (README, "Which map to trust"; default: the most trusted
            kind the run carries, occlusion first, `vocabulary.TRUST_ORDER`); `--map` is its earlier
            spelling.
    """
    if is_maps_dataset(run_dir):
        return _dataset_stats(run_dir, format, out, kind)
    try:
        run = load_run(run_dir, load_arrays=False)
    except FileNotFoundError as e:  # not a run (nor a maps dataset): named in one line
        print(f"openpi-cam stats: {e}", file=sys.stderr)
        return 1
    try:
        steps = view_steps(run.steps, kind or drawn_kind(run.map_kinds))
    except MissingMaps as e:
        print(f"openpi-cam stats: {e}", file=sys.stderr)
        return 2
    stats = compute_stats(steps)
    data = write_table(to_rows(stats), format, aggregate(stats))
    if out is None and format == "parquet":
        out = pathlib.Path(run_dir) / "stats.parquet"
    emit_table(data, out, f"{len(stats)} steps")
    return 0


def view_options(ds: MapsDataset) -> ViewOptions:
    """The views of a maps dataset as the demo recorded it: each episode's perturbation is its condition (where the
    rows carry `--extra perturbation=perturbation` and outcomes), named as `demo --record` listed them."""
    return ViewOptions(group=PERTURBATION_FEATURE, group_names=tuple(perturbation_names(ds.info.source)))


def _dataset_stats(root: pathlib.Path, format: Format, out: pathlib.Path | None, kind: str | None) -> int:
    """A maps dataset's per-frame rows as CSV or parquet (the views in its metadata), or JSON holding the
    dataset-level views (`summary`) and the rows (`frames`)."""
    try:
        ds = open_maps_dataset(root)
        kind = kind or drawn_kind(ds.kinds)
        views = compute_views(ds, kind, view_options(ds))
    except ValueError as e:
        print(f"openpi-cam stats: {e}", file=sys.stderr)
        return 2
    data = write_table(views.rows, format, views.summary(), rows_key="frames")
    if out is None and format == "parquet":
        out = pathlib.Path(root) / f"stats-{kind}.parquet"
    emit_table(data, out, f"{len(views.rows)} frames")
    if views.outcomes is not None:  # on stderr, beside any format the table goes out in
        print("\n".join(detection_lines(views.outcomes["detection"])), file=sys.stderr)
    return 0
