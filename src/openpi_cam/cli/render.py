"""`openpi-cam render RUN_DIR | MAPS_DATASET`: overlays, panels, videos and the HTML report of one kind of map."""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from typing import Annotated

import tyro

from openpi_cam.cam.run_format import load_run
from openpi_cam.cli.stats import view_options
from openpi_cam.lerobot.dataset import parse_episodes
from openpi_cam.maps.dataset import is_maps_dataset, open_maps_dataset
from openpi_cam.maps.render import DatasetRenderOptions, render_dataset
from openpi_cam.maps.rerun import write_dataset_rrd
from openpi_cam.viz.render import Norm, RenderOptions, default_render_dir, render_run
from openpi_cam.viz.rerun_sink import write_rrd
from openpi_cam.viz.stats import MissingMaps
from openpi_cam.vocabulary import MapKind, drawn_kind


def main(
    run_dir: tyro.conf.Positional[pathlib.Path],
    out: pathlib.Path | None = None,
    kind: Annotated[MapKind | None, tyro.conf.arg(aliases=("--map",))] = None,
    norm: Norm = "step",
    alpha: float = 0.5,
    tile_height: int = 240,
    fps: float | None = None,
    videos: bool = True,
    html: bool = True,
    progress: bool = True,
    rerun: pathlib.Path | None = None,
    episodes: str | None = None,
) -> int:
    """Overlays, per-step panels, an MP4 and a GIF per connection, and a static HTML report for a CAM run; for a
    maps dataset, an overlay video per episode and a report of the dataset-level views.

    Args:
        run_dir: a CAM run directory (holds run.json and steps/), or a maps dataset (`explain-dataset`'s output):
            per episode an overlay video of the source dataset's frames, and a report of the dataset-level views.
        out: output directory; defaults to RUN_DIR/render-<kind>.
        kind: which kind of map to draw (README, "Which map to trust"; Grad-CAM is `gradcam`; default: the most
            trusted kind the run carries, occlusion first, `vocabulary.TRUST_ORDER`); `--map` is its
            earlier spelling.
        norm: divide maps by the step's maximum over cameras ("step") or by the whole run's maximum ("run").
        alpha: opacity of the heatmap over the image.
        tile_height: height in pixels of each camera tile in the panels and videos.
        fps: frames per second of the videos; default 5 for a run (one frame per logged step), and for a maps
            dataset the source's rate divided by the explain job's `--every-k` (real time).
        videos: write the videos (MP4, and a GIF per connection of a run).
        html: write index.html (self-contained, opens from disk).
        progress: show progress on stderr.
        rerun: also write the run or maps dataset as a Rerun recording to this .rrd file (needs the `rerun` extra).
        episodes: a maps dataset's episodes to draw, like 0,3,7-9 (default: all; the report covers all).
    """
    if is_maps_dataset(run_dir):
        opts = DatasetRenderOptions(
            map=kind,
            norm=norm,
            alpha=alpha,
            tile_height=tile_height,
            videos=videos,
            html=html,
            progress=progress,
            fps=fps,
        )
        return _render_dataset(run_dir, out, opts, episodes, rerun)
    if episodes is not None:
        print("openpi-cam render: --episodes selects a maps dataset's episodes; RUN_DIR is a run", file=sys.stderr)
        return 2
    try:
        run = load_run(run_dir, load_arrays=False)
    except FileNotFoundError as e:  # not a run (nor a maps dataset): named in one line
        print(f"openpi-cam render: {e}", file=sys.stderr)
        return 1
    kind = kind or drawn_kind(run.map_kinds)
    out_dir = pathlib.Path(out) if out is not None else default_render_dir(run_dir, kind)
    opts = RenderOptions(
        map=kind,
        norm=norm,
        alpha=alpha,
        tile_height=tile_height,
        fps=RenderOptions.fps if fps is None else fps,
        videos=videos,
        html=html,
        progress=progress,
    )
    try:
        result = render_run(run, out_dir, opts)
    except MissingMaps as e:
        print(f"openpi-cam render: {e}", file=sys.stderr)
        return 2
    print(f"rendered {len(result.steps)} steps to {result.report or out_dir}", file=sys.stderr)
    if rerun is not None:
        try:
            write_rrd(run_dir, rerun, norm=norm, alpha=alpha, map_kind=kind)
        except ImportError as e:
            print(f"openpi-cam render: {e}", file=sys.stderr)
            return 1
        print(f"wrote Rerun recording {rerun}", file=sys.stderr)
    return 0


def _render_dataset(
    root: pathlib.Path,
    out: pathlib.Path | None,
    opts: DatasetRenderOptions,
    episodes: str | None,
    rerun: pathlib.Path | None,
) -> int:
    """A maps dataset's videos and report, and with `rerun` its Rerun recording."""
    ds = open_maps_dataset(root)
    opts = dataclasses.replace(opts, map=opts.map or drawn_kind(ds.kinds), views=view_options(ds))
    out_dir = pathlib.Path(out) if out is not None else default_render_dir(root, opts.map)
    try:
        chosen = parse_episodes(episodes)
        result = render_dataset(ds, out_dir, opts, chosen)
    except (ValueError, FileNotFoundError) as e:
        print(f"openpi-cam render: {e}", file=sys.stderr)
        return 2
    print(
        f"rendered {sum(result.frames.values())} frames of {len(result.frames)} episodes to {result.report or out_dir}",
        file=sys.stderr,
    )
    if rerun is not None:
        try:
            write_dataset_rrd(
                ds, rerun, map_kind=opts.map, episodes=chosen, norm=opts.norm, alpha=opts.alpha, views=result.views
            )
        except ImportError as e:
            print(f"openpi-cam render: {e}", file=sys.stderr)
            return 1
        print(f"wrote Rerun recording {rerun}", file=sys.stderr)
    return 0
