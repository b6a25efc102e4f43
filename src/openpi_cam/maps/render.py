"""Rendering a maps dataset (`openpi-cam render MAPS_DATASET`): per episode an overlay video aligned with the
dataset's frames, and one HTML report of the dataset-level views.

The frames are decoded again from the LeRobot dataset the maps were computed from (`MapsInfo.source`, read with
`data.lerobot`), frame by frame as the maps dataset lists them, and each row's `index` is checked against the
source's (`maps.frames`), so a video can never pair a map with another frame. Each explained frame becomes one
video frame, the cameras side by side (the map bilinearly stretched over the frame and colour-blended,
`viz.overlay`), at the source's frame rate divided by the explain job's `every`. Videos are H.264 (libx264, yuv420p)
written with PyAV.

The report (OUT/index.html, relative links to the files beside it, no network) opens with the spot checks stored in
the maps dataset, then the positional prior with its flagged hot patches, failed and successful episodes side by side
(when the source records outcomes), the episodes ranked with the most diffuse maps first, the per-task table, and a
section per rendered episode (its video and a strip of its frames). Figures: `maps.views`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from openpi_cam.cam.run_format import RELIANCE_PROMPT
from openpi_cam.lerobot.dataset import LeRobotDataset
from openpi_cam.maps.dataset import MapsDataset
from openpi_cam.maps.frames import (
    EpisodeRows,
    aligned_frames,
    dataset_scale,
    episode_rows,
    frame_scale,
    select_episodes,
    source_dataset,
    video_fps,
)
from openpi_cam.maps.views import DatasetViews, ViewOptions, compute_views, top_k
from openpi_cam.viz.colormap import colorize
from openpi_cam.viz.overlay import blend, upsample
from openpi_cam.viz.progress import progress
from openpi_cam.viz.render import Norm, label_font, slug
from openpi_cam.viz.report import REPORT_STYLE, write_page
from openpi_cam.viz.text import escape, html_table, number, percent
from openpi_cam.viz.video import Mp4Writer
from openpi_cam.vocabulary import MAP_KIND_INFO, drawn_kind

_BG = (24, 24, 28)
_FG = (232, 232, 232)
_DIM = (150, 150, 160)
_HOT = (80, 230, 255)  # outline of a flagged hot patch: a colour the heat colormap never takes
_PAD = 6
_LINE = 16


@dataclasses.dataclass(frozen=True)
class DatasetRenderOptions:
    map: str | None = None  # None: the dataset's most trusted kind (`drawn_kind`)
    norm: Norm = "step"  # "step": each frame's maximum over its cameras; "run": the rendered episodes' maximum
    alpha: float = 0.5
    tile_height: int = 240
    videos: bool = True
    html: bool = True
    progress: bool = True
    strip_frames: int = 6  # frames shown per episode in the report
    strip_height: int = 96
    prior_height: int = 160
    crf: int = 18  # libx264 quality: visually lossless for these overlays
    fps: float | None = None  # video frame rate; None: the source's rate divided by the explain job's `every`
    # what the report's dataset-level views take (the conditions among them)
    views: ViewOptions = dataclasses.field(default_factory=ViewOptions)


@dataclasses.dataclass
class DatasetRenderResult:
    out_dir: pathlib.Path
    views: DatasetViews
    videos: dict[int, str]  # episode -> path relative to out_dir
    strips: dict[int, str]
    frames: dict[int, int]  # episode -> video frames written
    report: pathlib.Path | None = None


def camera_tile(frame: np.ndarray | None, m: np.ndarray | None, scale: float, alpha: float, height: int) -> np.ndarray:
    """The frame scaled to `height` with the map stretched over it, divided by `scale` and colour-blended; without a
    map (masked camera) the plain frame; without a frame, a blank square."""
    if frame is None:
        return np.zeros((height, height, 3), np.uint8)
    h, w = frame.shape[:2]
    width = max(1, round(w * height / h))
    base = np.asarray(Image.fromarray(frame).resize((width, height), Image.Resampling.BILINEAR))
    if m is None:
        return base
    heat = upsample(m, height, width)
    heat = heat / scale if scale > 0 else np.zeros_like(heat)
    return blend(base, heat, alpha)


def compose_frame(
    frames: Mapping[str, np.ndarray],
    maps: Mapping[str, np.ndarray],
    valid: Mapping[str, bool],
    scale: float,
    caption: str,
    labels: Mapping[str, str],
    opts: DatasetRenderOptions,
) -> np.ndarray:
    """One video frame: a caption line, then per camera (in `maps` order) its label and tile, side by side. Both
    sides are even (yuv420p needs them so)."""
    tiles = {
        c: camera_tile(frames.get(c), m if valid.get(c, True) else None, scale, opts.alpha, opts.tile_height)
        for c, m in maps.items()
    }
    width = _PAD + sum(t.shape[1] + _PAD for t in tiles.values())
    height = _PAD + 2 * _LINE + opts.tile_height + _PAD
    width, height = width + width % 2, height + height % 2
    canvas = Image.new("RGB", (width, height), _BG)
    draw = ImageDraw.Draw(canvas)
    font = label_font(12)
    draw.text((_PAD, _PAD), caption, fill=_FG, font=font)
    x = _PAD
    for c, tile in tiles.items():
        draw.text((x, _PAD + _LINE), labels.get(c, c), fill=_DIM, font=font)
        canvas.paste(Image.fromarray(tile), (x, _PAD + 2 * _LINE))
        x += tile.shape[1] + _PAD
    return np.asarray(canvas)


def _labels(views: DatasetViews, row: Mapping[str, Any]) -> dict[str, str]:
    out = {}
    for c in views.cameras:
        share, peak = row.get(f"{c}/share"), (row.get(f"{c}/peak_row"), row.get(f"{c}/peak_col"))
        if not row.get(f"{c}/valid", True):
            out[c] = f"{c} (masked)"
        else:
            where = f"peak {peak[0]},{peak[1]}" if peak[0] is not None else "no mass"
            out[c] = f"{c} {100 * (share or 0):.0f}% {where}"
    return out


def render_episode(
    ds: MapsDataset,
    lr: LeRobotDataset,
    views: DatasetViews,
    episode: int,
    out_dir: pathlib.Path,
    opts: DatasetRenderOptions,
    dataset_max: float,
    stats: Mapping[int, Mapping[str, Any]],
) -> tuple[str | None, str | None, int]:
    """Writes the episode's video (with `opts.videos`) and its strip of frames; returns their paths relative to
    `out_dir` and the number of frames drawn. `stats`: the frames' rows of `views` by `index`."""
    rows = episode_rows(ds, episode, opts.map)
    name = f"episode_{episode:06d}"
    fps = video_fps(ds, lr) if opts.fps is None else opts.fps
    video = Mp4Writer(out_dir / "videos" / f"{name}.mp4", fps, opts.crf) if opts.videos else None
    n = len(rows)
    picks = set(np.linspace(0, n - 1, min(n, opts.strip_frames)).round().astype(int).tolist()) if n else set()
    strip: list[Image.Image] = []
    try:
        for i, images in enumerate(aligned_frames(ds, lr, rows)):
            image = episode_frame(rows, i, images, stats.get(rows.index[i], {}), views, opts, dataset_max)
            if video is not None:
                video.add(image)
            if i in picks:
                thumb = Image.fromarray(image)
                thumb.thumbnail((10 * opts.strip_height, opts.strip_height), Image.Resampling.BILINEAR)
                strip.append(thumb)
    finally:
        if video is not None:
            video.close()
    strip_rel = None
    if strip:
        sheet = Image.new("RGB", (sum(t.width + 4 for t in strip), opts.strip_height), _BG)
        x = 0
        for t in strip:
            sheet.paste(t, (x, 0))
            x += t.width + 4
        strip_rel = f"strips/{name}.jpg"
        (out_dir / "strips").mkdir(parents=True, exist_ok=True)
        sheet.save(out_dir / strip_rel, quality=85)
    video_rel = video.path.relative_to(out_dir).as_posix() if video is not None and video.count else None
    return video_rel, strip_rel, n


def episode_frame(
    rows: EpisodeRows,
    i: int,
    images: Mapping[str, np.ndarray],
    stats: Mapping[str, Any],
    views: DatasetViews,
    opts: DatasetRenderOptions,
    dataset_max: float,
) -> np.ndarray:
    """Row `i`'s video frame: its caption, and each camera's source frame with the map over it."""
    maps, valid = rows.frame_maps(i), rows.valid[i]
    scale = dataset_max if opts.norm == "run" else frame_scale(maps, valid)
    caption = (
        f"episode {rows.episode} | frame {rows.frame_index[i]} | t {rows.timestamp[i]:.2f} s | {opts.map} | "
        f"{rows.task[i][:60]}"
    )
    return compose_frame(images, maps, valid, scale, caption, _labels(views, stats), opts)


def prior_image(
    values: np.ndarray, hot: Sequence[tuple[int, int]], height: int, vmax: float | None = None
) -> Image.Image:
    """A [Hp, Wp] map drawn as patches (nearest, so each patch reads as a cell), divided by `vmax` (default its own
    maximum), with the `hot` patches outlined."""
    hp, wp = values.shape
    top = float(values.max()) if vmax is None else vmax
    norm = values / top if top > 0 else np.zeros_like(values)
    cell = max(1, height // hp)
    img = Image.fromarray(colorize(norm)).resize((wp * cell, hp * cell), Image.Resampling.NEAREST)
    draw = ImageDraw.Draw(img)
    for r, c in hot:
        draw.rectangle((c * cell, r * cell, (c + 1) * cell - 1, (r + 1) * cell - 1), outline=_HOT, width=2)
    return img


def render_dataset(
    ds: MapsDataset,
    out_dir: pathlib.Path,
    opts: DatasetRenderOptions = DatasetRenderOptions(),
    episodes: list[int] | None = None,
    source: pathlib.Path | None = None,
) -> DatasetRenderResult:
    """Videos and strips for `episodes` (default: every written one) and index.html over the whole dataset's views."""
    chosen = select_episodes(ds, episodes)
    opts = dataclasses.replace(opts, map=opts.map or drawn_kind(ds.kinds))
    views = compute_views(ds, opts.map, opts.views)
    lr = source_dataset(ds, source)
    out_dir.mkdir(parents=True, exist_ok=True)
    dataset_max = dataset_scale(ds, opts.map, chosen) if opts.norm == "run" else 0.0
    stats = {int(r["index"]): r for r in views.rows}
    result = DatasetRenderResult(out_dir, views, {}, {}, {})
    for episode in progress(chosen, len(chosen), "render episodes", opts.progress):
        video, strip, n = render_episode(ds, lr, views, episode, out_dir, opts, dataset_max, stats)
        if video:
            result.videos[episode] = video
        if strip:
            result.strips[episode] = strip
        result.frames[episode] = n
    if opts.html:
        result.report = write_dataset_report(ds, result, opts)
    return result


def _pct(x: Any) -> str:
    return percent(x, 0)


def _checks_section(views: DatasetViews) -> str:
    rows = [
        (
            ("<b>" + escape(s["kind"]) + "</b>") if s["kind"] == views.kind else escape(s["kind"]),
            escape(s["camera"]),
            str(s["frames"]),
            number(s["median_top_drop"]),
            number(s["median_random_drop"]),
            f"{_pct(s['beats_median_random'])} (chance ~50%)",
            f"{_pct(s['beats_every_random'])} (chance {_pct(s['chance_every'])})",
        )
        for s in views.checks
    ]
    head = (
        "kind",
        "camera",
        "frames checked",
        "top patch's score drop (median)",
        "random patch's (median)",
        "top patch beats the median random patch",
        "top patch beats every random patch",
    )
    table = (
        html_table(head, rows, raw=True)
        if rows
        else "<p class='warn'>no spot checks stored (explain with --check-patches N to store them)</p>"
    )
    return (
        "<section id='evidence'><h2>how faithful are these maps? (spot checks stored with the frames)</h2>"
        f"<p>{escape(MAP_KIND_INFO[views.kind].note)}</p>"
        "<p class='dim'>each frame's map was checked when it was computed: the explained score's drop with the map's "
        "top patch painted by the baseline, next to the drops of a few random patches painted alone</p>"
        f"{table}</section>"
    )


def _prior_section(views: DatasetViews, out_dir: pathlib.Path, opts: DatasetRenderOptions) -> str:
    (out_dir / "prior").mkdir(parents=True, exist_ok=True)
    parts = []
    for c in views.cameras:
        hot = [(h.row, h.col) for h in views.hot[c]]
        prior_rel, rate_rel = f"prior/{slug(c)}-prior.png", f"prior/{slug(c)}-hot-rate.png"
        prior_image(views.prior[c], hot, opts.prior_height).save(out_dir / prior_rel)
        prior_image(views.hot_rate[c], hot, opts.prior_height, vmax=1.0).save(out_dir / rate_rel)
        fit = views.fit[c]
        patches = int(np.prod(views.prior[c].shape))
        k = top_k(patches, views.options.top_fraction)
        flagged = "".join(
            f"<li class='warn hot' data-row='{h.row}' data-col='{h.col}'>patch row {h.row}, col {h.col}: in the "
            f"top-{k} of {_pct(h.rate)} of frames (chance {_pct(k / patches)})</li>"
            for h in views.hot[c]
        )
        parts.append(
            f"<div class='prior' data-camera='{escape(c)}'><h3>{escape(c)} <small class='dim'>"
            f"{escape(views.camera_sources.get(c, ''))}</small></h3>"
            f"<figure><img src='{escape(prior_rel)}' alt='mean map {escape(c)}'>"
            "<figcaption>mean map</figcaption></figure>"
            f"<figure><img src='{escape(rate_rel)}' alt='hot rate {escape(c)}'>"
            f"<figcaption>share of frames in the top-{k}</figcaption></figure>"
            f"<p>{fit['frames']} frames with mass; cosine to the prior: mean {number(fit['mean_cosine'])}, median "
            f"{number(fit['median_cosine'])}; pooled R² {number(fit['pooled_r2'])}; mean total-variation distance "
            f"{number(fit['mean_distance'])}; frames whose peak sits on a flagged patch: {_pct(fit['peak_on_hot'])}</p>"
            f"<ul>{flagged or '<li>no patch flagged</li>'}</ul></div>"
        )
    return (
        "<section id='prior'><h2>positional prior</h2><p class='dim'>the mean of each camera's maps (each normalised "
        "to sum 1) over the dataset; how much of a frame's map it explains; and the patches hot in most frames "
        f"whatever they show (flagged: in a frame's top-k in more than {_pct(views.options.hot_threshold)} of "
        "frames, OpenPI #947), outlined</p>" + "".join(parts) + "</section>"
    )


def _ranking_section(views: DatasetViews, result: DatasetRenderResult) -> str:
    head = ["rank", "episode", "task", "frames", "entropy (norm.)", "z", "distance to the prior", "malformed"]
    head += ["mean score"]
    head += ["outcome"] if views.outcomes is not None else []
    head += [f"{c} share" for c in views.cameras]
    rows = []
    for e in views.episodes:
        ep = e["episode_index"]
        link = f"<a href='#episode-{ep}'>{ep}</a>" if ep in result.frames else str(ep)
        rows.append(
            (
                str(e["rank"]),
                link,
                escape(e["task"]),
                str(e["frames"]),
                number(e["entropy"]),
                number(e["z"], 2),
                number(e["distance"]),
                str(e["malformed"]),
                number(e["mean_score"]),
                *([_outcome(e)] if views.outcomes is not None else []),
                *(_pct(e["cameras"][c]["mean_share"]) for c in views.cameras),
            )
        )
    return (
        "<section id='ranking'><h2>episodes, most diffuse maps first</h2><p class='dim'>entropy: the mean over the "
        "episode's frames of each camera's normalised map entropy (1: spread evenly), z over the dataset's episodes; "
        "on the demo's failing rollouts failed episodes come first this way (docs/MAP_KINDS.md). Distance: the mean "
        "total-variation distance between each camera's map and the camera's prior</p>"
        f"{html_table(head, rows, raw=True)}</section>"
    )


def _outcome(e: Mapping[str, Any]) -> str:
    return "-" if e.get("success") is None else ("success" if e["success"] else "<b class='warn'>failure</b>")


def _auroc(f: Mapping[str, Any]) -> str:
    low, high = f["auroc_ci95"]
    return "-" if f["auroc"] is None else f"{f['auroc']:.2f} ({number(low, 2)}-{number(high, 2)})"


def _outcome_table(views: DatasetViews, groups: Mapping[str, Mapping[str, Any]]) -> str:
    """Failed and successful episodes side by side: a row per outcome of `groups` (`outcome_views`' `by_outcome`)."""
    relied = views.info.reliance
    what = ("share", "entropy (norm.)", "distance", "nuisance") + (("reliance: score", "actions") if relied else ())
    keys = ("mean_share", "mean_entropy_norm", "mean_prior_distance", "mean_nuisance_mass")
    keys += ("mean_reliance_score", "mean_reliance_actions") if relied else ()
    head = ["outcome", "episodes", "frames", "mean score", *(f"{c} {w}" for c in views.cameras for w in what)]
    head += ["prompt reliance: score", "actions"] if relied else []
    rows = []
    for name, g in groups.items():
        cells = [name, str(g["episodes"]), str(g["frames"]), number(g["mean_score"])]
        cells += [
            _pct(g["cameras"][c][k]) if k == "mean_share" else number(g["cameras"][c][k])
            for c in views.cameras
            for k in keys
        ]
        if relied:
            prompt = g[RELIANCE_PROMPT]
            cells += [number(prompt["mean_reliance_score"]), number(prompt["mean_reliance_actions"])]
        rows.append(cells)
    return html_table(head, rows)


def _outcomes_section(views: DatasetViews) -> str:
    """Failed and successful episodes side by side, and how well each episode figure finds the failures."""
    o = views.outcomes
    if o is None:
        return ""
    early = o["early_warning"]["figures"]
    found = [
        (
            name,
            _auroc(f),
            number(f["precision_at_failures"], 2),
            _auroc(early[name]) if name in early else "-",
        )
        for name, f in o["failure_finding"].items()
        if f["auroc"] is not None
    ]
    chance = o["failures"] / o["episodes"] if o["episodes"] else None
    return (
        f"<section id='outcomes'><h2>failed and successful episodes</h2><p>{o['failures']} of {o['episodes']} "
        "episodes failed (an episode succeeds when any frame's outcome is true, as lerobot-eval counts it)</p>"
        f"{_outcome_table(views, o['by_outcome'])}<h3>which figure finds the failures?</h3><p class='dim'>ROC AUC of "
        "each episode figure as a failure score (larger = failure; 0.5 is chance, below 0.5 the figure finds "
        f"successes), with its 95% bootstrap interval; precision among the {o['failures']} highest-scoring episodes "
        f"(chance {number(chance, 2)}); early warning: the same figure from each episode's first "
        f"{o['early_warning']['frames']} explained frames only. Failed episodes run to the step limit, so length "
        "alone finds them: a figure is worth reading where it beats length, or early.</p>"
        f"{html_table(['figure', 'AUROC (95%)', 'precision at #failures', 'early warning AUROC'], found)}</section>"
    )


def _groups_section(views: DatasetViews, out_dir: pathlib.Path, opts: DatasetRenderOptions) -> str:
    """Per condition (`ViewOptions.group`, e.g. the demo's perturbation): its success, failed and successful episodes
    side by side, and each camera's mean map over the failed and over the successful episodes' frames."""
    group = views.options.group
    if not views.groups or group is None:
        return ""
    (out_dir / "groups").mkdir(parents=True, exist_ok=True)
    parts = []
    for g in views.groups:
        value, name = g[group], g["name"]
        label = f"{group} {value}" + (f": {name}" if name else "")
        figures = []
        for c in views.cameras:
            for outcome in ("failure", "success"):
                mean = g["mean_maps"][outcome][c]
                if mean is None:
                    continue
                rel = f"groups/{value}-{slug(c)}-{outcome}.png"
                prior_image(np.asarray(mean), [], opts.prior_height).save(out_dir / rel)
                caption = f"{escape(c)}, {'failed' if outcome == 'failure' else 'successful'} episodes"
                figures.append(f"<figure><img src='{rel}' alt='{caption}'><figcaption>{caption}</figcaption></figure>")
        parts.append(
            f"<div class='prior' data-group='{value}'><h3>{escape(label)}: {g['successes']}/{g['episodes']} episodes "
            f"succeeded</h3>{_outcome_table(views, g['by_outcome'])}{''.join(figures)}</div>"
        )
    return (
        f"<section id='groups'><h2>per {group}</h2><p class='dim'>each condition's failed and successful episodes side "
        "by side, and each camera's mean map (each frame's map normalised to sum 1) over their frames, scaled to its "
        f"own maximum; the condition is the carried feature named {group} (`--extra FEATURE={group}`), named where "
        f"the recording named its conditions</p>{''.join(parts)}</section>"
    )


def _peak(cam: Mapping[str, Any]) -> str:
    mode = cam.get("peak_mode")
    return "-" if not mode else f"{mode[0]},{mode[1]} ({_pct(cam['peak_mode_rate'])})"


def _tasks_section(views: DatasetViews) -> str:
    head = ["task", "episodes", "frames"]
    head += [f"{c} {what}" for c in views.cameras for what in ("share", "entropy (norm.)", "usual peak")]
    rows = [
        (
            t["task"],
            str(t["episodes"]),
            str(t["frames"]),
            *(
                v
                for c in views.cameras
                for v in (
                    _pct(t["cameras"][c]["mean_share"]),
                    number(t["cameras"][c]["mean_entropy_norm"]),
                    _peak(t["cameras"][c]),
                )
            ),
        )
        for t in views.tasks
    ]
    return f"<section id='tasks'><h2>per task</h2>{html_table(head, rows)}</section>"


def _episode_section(views: DatasetViews, result: DatasetRenderResult, episode: int) -> str:
    e = next((x for x in views.episodes if x["episode_index"] == episode), None)
    video, strip = result.videos.get(episode), result.strips.get(episode)
    media = (
        f"<p><a href='{escape(video)}'>MP4</a></p>"
        f"<video src='{escape(video)}' controls loop muted preload='metadata'></video>"
        if video
        else ""
    )
    media += f"<img class='strip' src='{escape(strip)}' alt='episode {episode}'>" if strip else ""
    head = ("camera", "share", "entropy (norm.)", "usual peak (row, col)", "cosine to the prior", "distance")
    rows = []
    if e is not None:
        for c in views.cameras:
            cam = e["cameras"][c]
            rows.append(
                (
                    c,
                    _pct(cam["mean_share"]),
                    number(cam["mean_entropy_norm"]),
                    _peak(cam),
                    number(cam["mean_prior_cosine"]),
                    number(cam["mean_prior_distance"]),
                )
            )
    title = f"episode {episode}" + (f" · {escape(e['task'])} · rank {e['rank']} · z {number(e['z'], 2)}" if e else "")
    title += f" · {_outcome(e)}" if e is not None and e.get("success") is not None else ""
    return (
        f"<section class='episode' id='episode-{episode}' data-episode='{episode}' "
        f"data-frames='{result.frames.get(episode, 0)}'><h3>{title}</h3>{media}{html_table(head, rows)}</section>"
    )


def write_dataset_report(ds: MapsDataset, result: DatasetRenderResult, opts: DatasetRenderOptions) -> pathlib.Path:
    views = result.views
    info = ds.info
    facts = {
        "source": f"{info.source} (LeRobot {info.source_version})",
        "model": f"{info.model.get('config')} ({info.family}), {info.model.get('checkpoint_dir') or 'bundled'}",
        "target": info.target,
        "frames": f"{len(views.rows)} in {len(views.episodes)} episodes; {len(result.frames)} episodes rendered",
        "normalisation": "per frame (the largest value over its cameras)"
        if opts.norm == "step"
        else "over the rendered episodes",
    }
    dl = "".join(f"<dt>{escape(k)}</dt><dd>{escape(v)}</dd>" for k, v in facts.items())
    episodes = "".join(_episode_section(views, result, e) for e in result.frames)
    style = (
        REPORT_STYLE + ".prior figure{display:inline-block;margin:4px 12px 4px 0}img.strip{display:block;margin:4px 0}"
    )
    body = (
        f"<h1>maps dataset {escape(ds.root.name)}: {escape(MAP_KIND_INFO[views.kind].label)} maps</h1><dl>{dl}</dl>"
        f"{_checks_section(views)}{_prior_section(views, result.out_dir, opts)}{_outcomes_section(views)}"
        f"{_groups_section(views, result.out_dir, opts)}"
        f"{_ranking_section(views, result)}"
        f"{_tasks_section(views)}<h2>episodes</h2>{episodes}"
    )
    return write_page(result.out_dir / "index.html", f"maps dataset {ds.root.name}", body, style)
