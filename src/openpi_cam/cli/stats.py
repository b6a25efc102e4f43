"""`openpi-cam stats RUN_DIR`: per-step, per-camera statistics of one kind of map, as CSV, JSON or parquet."""

from __future__ import annotations

import pathlib
import sys
from typing import Literal

import tyro

from openpi_cam.cam.maps_dataset import is_maps_dataset
from openpi_cam.cam.runfmt import load_run
from openpi_cam.viz.dataset_views import dataset_stats_command
from openpi_cam.viz.stats import (
    DEFAULT_MAP_KIND,
    MissingMaps,
    aggregate,
    compute_stats,
    emit_table,
    to_rows,
    view_steps,
    write_table,
)
from openpi_cam.vocabulary import MapKind


def main(
    run_dir: tyro.conf.Positional[pathlib.Path],
    format: Literal["csv", "json", "parquet"] = "csv",
    out: pathlib.Path | None = None,
    map: MapKind = DEFAULT_MAP_KIND,  # type: ignore[assignment]
) -> int:
    """Per-step, per-camera statistics of a CAM run's maps (one row per step, `<camera>/<field>` columns).

    Args:
        run_dir: a CAM run directory (holds run.json and steps/), or a maps dataset (`explain DATASET_DIR`'s output:
            one row per frame, and the dataset-level views in the JSON summary; `viz.dataset_views`).
        format: csv, json (rows plus a run summary) or parquet (needs pyarrow; summary in the file metadata).
        out: output file; defaults to stdout for csv/json and RUN_DIR/stats.parquet for parquet.
        map: which kind of map the statistics describe (README, "Which map to trust").
    """
    if is_maps_dataset(run_dir):
        return dataset_stats_command(run_dir, format, out, map)
    try:
        steps = view_steps(load_run(run_dir, load_arrays=False).steps, map)
    except MissingMaps as e:
        print(f"openpi-cam stats: {e}", file=sys.stderr)
        return 2
    stats = compute_stats(steps)
    data = write_table(to_rows(stats), format, aggregate(stats))
    if out is None and format == "parquet":
        out = pathlib.Path(run_dir) / "stats.parquet"
    emit_table(data, out, f"{len(stats)} steps")
    return 0
