"""A maps dataset as a Rerun recording (`openpi-cam render MAPS_DATASET --rerun FILE.rrd`), laid out as LeRobot's own
dataset viewer lays out a dataset, so that the frames and their maps open aligned.

Entities, per model camera whose dataset feature is `<feature>` (e.g. `observation.images.base`, the name LeRobot
logs the camera under):
  <feature>                  the dataset's frame, decoded again from the source dataset (`maps.frames`)
  <feature>/<kind>           the map as a layer over it: stretched to the frame, coloured, drawn with opacity `alpha`
                             above the frame (cleared on frames where the model did not see the camera)
  openpi_cam/<kind>/share/<camera>   the camera's share of the frame's map mass (`viz.stats`)
  openpi_cam/score           the explained score (mean over tokens for multi-token targets)
  openpi_cam/success         the episode's outcome (1: it succeeded), when the source records outcomes
  openpi_cam/reliance_score/<camera or prompt>, openpi_cam/reliance_actions/<camera or prompt>
                             the frame's reliance (`--reliance`): the score's drop and the chunk's change without it
  openpi_cam/about           (static) what the maps are, their spot checks, the flagged hot patches, how well each
                             figure finds failures (with outcomes) and the top-ranked episodes (`maps.views`)
Timelines: `frame_index` (sequence) and `timestamp` (seconds, logged as LeRobot logs it) as in LeRobot's recordings,
plus `episode_index` and `index` (the dataset-wide frame index, which plays the episodes one after another). One
recording holds every chosen episode; on `frame_index` and `timestamp` the episodes share the same times, so pick
one episode (`--episodes N`) to scrub those, or scrub `index`.

`rerun-sdk` is optional (`pip install "openpi-cam[rerun]"`); it is imported only when a recording is written.
"""

from __future__ import annotations

import math
import os
import pathlib
from typing import Literal

import numpy as np

from openpi_cam.maps.dataset import MapsDataset, reliance_columns
from openpi_cam.maps.frames import (
    aligned_frames,
    dataset_scale,
    episode_rows,
    frame_scale,
    select_episodes,
    source_dataset,
)
from openpi_cam.maps.views import DatasetViews, compute_views
from openpi_cam.viz.colormap import colorize
from openpi_cam.viz.overlay import upsample
from openpi_cam.viz.rerun_sink import import_rerun, log_reliance
from openpi_cam.viz.stats import mean_score
from openpi_cam.vocabulary import MAP_KIND_INFO, drawn_kind

FRAME_DRAW_ORDER = 0.0
LAYER_DRAW_ORDER = 1.0  # the map is drawn above the frame


def layer_image(frame_hw: tuple[int, int], m: np.ndarray, scale: float) -> np.ndarray:
    """The map's layer: the [Hp, Wp] map stretched over an H x W frame, divided by `scale`, coloured (uint8 RGB)."""
    heat = upsample(m, *frame_hw)
    return colorize(heat / scale if scale > 0 else np.zeros_like(heat))


def _about(views: DatasetViews, norm: str) -> str:
    lines = [
        f"# {MAP_KIND_INFO[views.kind].label} maps of {views.info.source}",
        "",
        MAP_KIND_INFO[views.kind].note,
        "",
        f"Each frame's map is drawn over it as the layer `<feature>/{views.kind}`, normalised per "
        + ("frame (its largest value over the cameras)." if norm == "step" else "recording (its largest value)."),
        "",
        "## spot checks stored with the frames",
        "",
        "| kind | camera | frames | top patch beats the median random patch (chance ~50%) | beats every random |",
        "| --- | --- | --- | --- | --- |",
    ]
    lines += [
        f"| {s['kind']} | {s['camera']} | {s['frames']} | {s['beats_median_random']:.0%} | "
        f"{s['beats_every_random']:.0%} (chance {s['chance_every']:.0%}) |"
        for s in views.checks
    ]
    lines += ["", "## hot patches (in the top-k of most frames whatever they show)", ""]
    hot = [h for c in views.cameras for h in views.hot[c]]
    lines += [f"- {h.camera}: row {h.row}, col {h.col}, hot in {h.rate:.0%} of frames" for h in hot] or ["- none"]
    if views.outcomes is not None:
        o = views.outcomes
        lines += ["", f"## outcomes: {o['failures']} of {o['episodes']} episodes failed", ""]
        lines += ["| figure | failure-finding AUROC (larger = failure) | early warning AUROC |", "| --- | --- | --- |"]
        early = o["early_warning"]["figures"]
        lines += [
            f"| {name} | {f['auroc']:.2f} | "
            + (f"{early[name]['auroc']:.2f}" if early.get(name, {}).get("auroc") is not None else "-")
            + " |"
            for name, f in o["failure_finding"].items()
            if f["auroc"] is not None
        ]
    lines += ["", "## episodes with the most diffuse maps (mean normalised entropy)", ""]
    lines += [
        f"- episode {e['episode_index']} ({e['task']}): z {e['z']:.2f}" if e["z"] is not None else ""
        for e in views.episodes[:10]
    ]
    return "\n".join(lines)


def write_dataset_rrd(
    ds: MapsDataset,
    out_path: str | os.PathLike[str],
    *,
    map_kind: str | None = None,
    episodes: list[int] | None = None,
    norm: Literal["step", "run"] = "step",
    alpha: float = 0.5,
    views: DatasetViews | None = None,
    source: pathlib.Path | None = None,
) -> pathlib.Path:
    """Writes `episodes` (default: every written one) of the maps dataset with their source frames to `out_path`."""
    rr = import_rerun()
    chosen = select_episodes(ds, episodes)
    map_kind = map_kind or drawn_kind(ds.kinds)
    views = views if views is not None and views.kind == map_kind else compute_views(ds, map_kind)
    lr = source_dataset(ds, source)
    features = {c: f for c, f in ds.info.camera_sources.items() if f in lr.features}
    dataset_max = dataset_scale(ds, map_kind, chosen) if norm == "run" else 0.0
    outcome = {e["episode_index"]: e.get("success") for e in views.episodes}
    reliance = reliance_columns(ds.info) if ds.info.reliance else []
    relied = {row["index"]: row for row in views.rows} if reliance else {}
    out_path = pathlib.Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("openpi-cam", recording_id=f"openpi-cam maps {ds.root.name} {map_kind}")
    rec.save(out_path)
    try:
        rec.log("openpi_cam/about", rr.TextDocument(_about(views, norm), media_type=rr.MediaType.MARKDOWN), static=True)
        for episode in chosen:
            rows = episode_rows(ds, episode, map_kind)
            for i, images in enumerate(aligned_frames(ds, lr, rows)):
                rec.set_time("index", sequence=rows.index[i])
                rec.set_time("episode_index", sequence=episode)
                rec.set_time("frame_index", sequence=rows.frame_index[i])
                rec.set_time("timestamp", timestamp=rows.timestamp[i])
                maps, valid = rows.frame_maps(i), rows.valid[i]
                scale = dataset_max if norm == "run" else frame_scale(maps, valid)
                total = sum(float(m.sum()) for c, m in maps.items() if valid.get(c, True))
                score = mean_score(rows.score[i])
                if math.isfinite(score):
                    rec.log("openpi_cam/score", rr.Scalars(score))
                if outcome.get(episode) is not None:
                    rec.log("openpi_cam/success", rr.Scalars(float(outcome[episode])))
                log_reliance(rec, rr, "openpi_cam", {name: relied[rows.index[i]].get(name) for name in reliance})
                for camera, m in maps.items():
                    share = float(m.sum()) / total if total > 0 and valid.get(camera, True) else 0.0
                    rec.log(f"openpi_cam/{map_kind}/share/{rr.escape_entity_path_part(camera)}", rr.Scalars(share))
                    feature = features.get(camera)
                    if feature is None:
                        continue
                    frame = images[camera]
                    rec.log(feature, rr.Image(frame, draw_order=FRAME_DRAW_ORDER))
                    if valid.get(camera, True):
                        layer = layer_image(frame.shape[:2], m, scale)
                        rec.log(f"{feature}/{map_kind}", rr.Image(layer, opacity=alpha, draw_order=LAYER_DRAW_ORDER))
                    else:
                        rec.log(f"{feature}/{map_kind}", rr.Clear(recursive=False))
    finally:
        rec.flush()
        rec.disconnect()
    return out_path
