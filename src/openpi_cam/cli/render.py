"""`openpi-cam render RUN_DIR`: overlays, per-step panels, videos and the HTML report of one kind of map."""

from __future__ import annotations

import pathlib
import sys

import tyro

from openpi_cam.cam.maps_dataset import is_maps_dataset
from openpi_cam.cam.runfmt import load_run
from openpi_cam.viz.dataset_render import DatasetRenderOptions, render_dataset_command
from openpi_cam.viz.render import Norm, RenderOptions, default_render_dir, render_run
from openpi_cam.viz.rerun_sink import write_rrd
from openpi_cam.viz.stats import DEFAULT_MAP_KIND, MissingMaps
from openpi_cam.vocabulary import MapKind


def main(
    run_dir: tyro.conf.Positional[pathlib.Path],
    out: pathlib.Path | None = None,
    map: MapKind = DEFAULT_MAP_KIND,  # type: ignore[assignment]
    norm: Norm = "step",
    alpha: float = 0.5,
    tile_height: int = 240,
    fps: float = 5.0,
    videos: bool = True,
    html: bool = True,
    progress: bool = True,
    rerun: pathlib.Path | None = None,
    episodes: str | None = None,
) -> int:
    """Overlays, per-step panels, an MP4 and a GIF per connection, and a static HTML report for a CAM run.

    Args:
        run_dir: a CAM run directory (holds run.json and steps/), or a maps dataset (`explain DATASET_DIR`'s output):
            per episode an overlay video of the source dataset's frames, and a report of the dataset-level views.
        out: output directory; defaults to RUN_DIR/render-<map>.
        map: which kind of map to draw (README, "Which map to trust"; Grad-CAM is `gradcam`).
        norm: divide maps by the step's maximum over cameras ("step") or by the whole run's maximum ("run").
        alpha: opacity of the heatmap over the image.
        tile_height: height in pixels of each camera tile in the panels and videos.
        fps: frames (steps) per second of the videos.
        videos: write the MP4 and GIF per connection.
        html: write index.html (self-contained, opens from disk).
        progress: show progress on stderr.
        rerun: also write the run as a Rerun recording to this .rrd file (needs the `rerun` extra).
        episodes: a maps dataset's episodes to draw, like 0,3,7-9 (default: all; the report covers all).
    """
    if is_maps_dataset(run_dir):
        dataset_opts = DatasetRenderOptions(
            map=map, norm=norm, alpha=alpha, tile_height=tile_height, videos=videos, html=html, progress=progress
        )
        return render_dataset_command(run_dir, out=out, opts=dataset_opts, episodes=episodes, rerun=rerun)
    run = load_run(run_dir, load_arrays=False)
    out_dir = pathlib.Path(out) if out is not None else default_render_dir(run_dir, map)
    opts = RenderOptions(
        map=map, norm=norm, alpha=alpha, tile_height=tile_height, fps=fps, videos=videos, html=html, progress=progress
    )
    try:
        result = render_run(run, out_dir, opts)
    except MissingMaps as e:
        print(f"openpi-cam render: {e}", file=sys.stderr)
        return 2
    print(f"rendered {len(result.steps)} steps to {result.report or out_dir}", file=sys.stderr)
    if rerun is not None:
        try:
            write_rrd(run_dir, rerun, norm=norm, alpha=alpha, map_kind=map)
        except ImportError as e:
            print(f"openpi-cam render: {e}", file=sys.stderr)
            return 1
        print(f"wrote Rerun recording {rerun}", file=sys.stderr)
    return 0
