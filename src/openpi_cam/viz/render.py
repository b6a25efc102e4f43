"""Rendering a CAM run: per-camera overlays, per-step panels, a video per connection, and the HTML report."""

from __future__ import annotations

import dataclasses
import math
import pathlib
import re
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from openpi_cam.cam.run_format import CAMRun
from openpi_cam.viz.colormap import LUT
from openpi_cam.viz.evidence import MapEvidence, map_evidence, panel_header
from openpi_cam.viz.overlay import StepView, camera_overlay
from openpi_cam.viz.progress import progress
from openpi_cam.viz.report import RenderResult, StepAssets, write_report
from openpi_cam.viz.stats import StepStats, compute_stats, step_scale, view_steps
from openpi_cam.viz.video import Mp4Writer
from openpi_cam.vocabulary import MAP_KIND_INFO, drawn_kind

Norm = Literal["step", "run"]

_BG = (24, 24, 28)
_FG = (232, 232, 232)
_DIM = (150, 150, 160)
_PAD = 8
_LINE = 18


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    map: str | None = None  # which kind of the steps' maps to draw (None: the run's most trusted, `drawn_kind`)
    norm: Norm = "step"
    alpha: float = 0.5
    tile_height: int = 240
    thumb_height: int = 72
    fps: float = 5.0
    videos: bool = True
    gif_max_width: int = 640
    gif_max_frames: int = 400
    html: bool = True
    progress: bool = True


def slug(name: str) -> str:
    """A file-name-safe version of a connection or camera name."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "_"


def label_font(size: int = 13) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # Pillow without FreeType: fixed bitmap font
        return ImageFont.load_default()


def _fmt_list(values: Any, limit: int = 8) -> str:
    items = list(np.atleast_1d(values)) if values is not None else []
    text = " ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in items[:limit])
    return text + (f" ... (+{len(items) - limit})" if len(items) > limit else "")


def _colorbar(height: int, width: int = 12) -> Image.Image:
    ramp = LUT[np.linspace(len(LUT) - 1, 0, height).round().astype(int)]
    return Image.fromarray(np.repeat(ramp[:, None, :], width, axis=1))


def step_panel(
    step: StepView,
    st: StepStats,
    overlays: Mapping[str, np.ndarray],
    norm_label: str,
    tile_height: int,
    evidence: MapEvidence | None = None,
) -> Image.Image:
    """All cameras of a step side by side, with the explained tokens, score and normalisation written above, and
    (`evidence`) how faithful this step's map of each camera measured, under its caption."""
    meta = step.meta
    font, small = label_font(13), label_font(11)
    tiles = []
    for camera, img in overlays.items():
        h, w = img.shape[:2]
        tw = max(1, round(w * tile_height / h))
        tiles.append((camera, Image.fromarray(img).resize((tw, tile_height), Image.Resampling.BILINEAR)))
    header = [
        f"seq {st.seq} | connection {st.connection} | step {st.step} | target {st.target}",
        f"tokens [{_fmt_list(meta.token_ids)}] decode steps [{_fmt_list(meta.decode_steps)}]"
        f" | score {_fmt_list(meta.score, 4)}",
        f"{norm_label} | prompt: {meta.prompt[:90]}",
        *([panel_header(evidence)] if evidence else []),
    ]
    notes = evidence is not None and evidence.status != "missing"
    caption_h = _LINE * (2 if notes else 1)
    bar_w = 12 + 40
    width = _PAD + sum(t.width + _PAD for _, t in tiles) + bar_w
    width = max(width, 560)
    height = _PAD + len(header) * _LINE + _PAD + caption_h + tile_height + _PAD
    panel = Image.new("RGB", (width, height), _BG)
    draw = ImageDraw.Draw(panel)
    for i, line in enumerate(header):
        draw.text((_PAD, _PAD + i * _LINE), line, fill=_FG if i == 0 else _DIM, font=font)
    top = _PAD + len(header) * _LINE + _PAD
    x = _PAD
    for camera, tile in tiles:
        cs = st.cameras.get(camera)
        if cs is None or not cs.valid:
            caption = f"{camera} (masked)"
        else:
            peak = f"peak {cs.peak[0]},{cs.peak[1]}" if cs.peak else "no mass"
            caption = f"{camera}  {100 * cs.share:.0f}%  {peak}"
        draw.text((x, top), caption, fill=_FG, font=small)
        if notes and cs is not None and cs.valid:
            draw.text((x, top + _LINE), f"top patch {evidence.step_line(st.seq, camera)}", fill=_DIM, font=small)
        panel.paste(tile, (x, top + caption_h))
        x += tile.width + _PAD
    bar = _colorbar(tile_height)
    panel.paste(bar, (x, top + caption_h))
    draw.text((x + bar.width + 3, top + caption_h), "max", fill=_DIM, font=small)
    draw.text((x + bar.width + 3, top + caption_h + tile_height - 12), "0", fill=_DIM, font=small)
    return panel


def _fit(img: Image.Image, size: tuple[int, int]) -> Image.Image:
    """`img` scaled down to fit `size` if needed and centred on a background canvas of exactly that size."""
    if img.width > size[0] or img.height > size[1]:
        img = img.copy()
        img.thumbnail(size, Image.Resampling.BILINEAR)
    canvas = Image.new("RGB", size, _BG)
    canvas.paste(img, ((size[0] - img.width) // 2, (size[1] - img.height) // 2))
    return canvas


class _ConnectionVideo:
    """Streams one connection's panels into an MP4 and collects a subsampled, downscaled GIF."""

    def __init__(self, mp4: pathlib.Path, gif: pathlib.Path, fps: float, total: int, opts: RenderOptions):
        self.mp4, self.gif, self.fps = mp4, gif, fps
        self.stride = max(1, math.ceil(total / opts.gif_max_frames))
        self.gif_max_width = opts.gif_max_width
        self.size: tuple[int, int] | None = None
        self.writer: Any = None
        self.gif_frames: list[Image.Image] = []
        self.count = 0

    def add(self, panel: Image.Image) -> None:
        if self.size is None:
            # Every frame of a video has the first panel's size; 16-aligned sides suit H.264's macroblocks.
            self.size = (-(-panel.width // 16) * 16, -(-panel.height // 16) * 16)
            self.writer = Mp4Writer(self.mp4, self.fps)
        frame = _fit(panel, self.size)
        self.writer.add(np.asarray(frame))
        if self.count % self.stride == 0:
            small = frame.copy()
            small.thumbnail((self.gif_max_width, self.gif_max_width), Image.Resampling.BILINEAR)
            self.gif_frames.append(small.quantize(colors=255, method=Image.Quantize.MEDIANCUT))
        self.count += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        if self.gif_frames:
            duration = round(1000 * self.stride / self.fps)
            self.gif_frames[0].save(
                self.gif, save_all=True, append_images=self.gif_frames[1:], duration=duration, loop=0
            )


def render_run(run: CAMRun, out_dir: pathlib.Path, opts: RenderOptions) -> RenderResult:
    """Writes overlays, panels, thumbnails, per-connection videos and (with `opts.html`) index.html for a run under
    `out_dir` (`MissingMaps`, before anything is written, when the run has no `opts.map` maps)."""
    opts = dataclasses.replace(opts, map=opts.map or drawn_kind(run.map_kinds))
    steps = view_steps(run.steps, opts.map)
    stats = compute_stats(steps)
    evidence = map_evidence(run, opts.map, stats)
    for sub in ("panels", "thumbs", "overlays", "videos"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    run_max = max((step_scale(st) for st in stats), default=0.0)
    per_connection: dict[str, int] = {}
    for st in stats:
        per_connection[st.connection] = per_connection.get(st.connection, 0) + 1
    make_videos = opts.videos
    videos: dict[str, _ConnectionVideo] = {}
    assets: dict[int, StepAssets] = {}
    for view, st in progress(zip(steps, stats, strict=True), len(steps), "render", opts.progress):
        step = view.loaded()
        scale = run_max if opts.norm == "run" else step_scale(st)
        norm_label = f"{MAP_KIND_INFO[opts.map].label}, normalised per {opts.norm} (max {scale:.3g})"
        cameras = list(step.meta.cameras) or list(step.maps)
        overlays = {c: camera_overlay(step, c, scale, opts.alpha) for c in cameras}
        name = f"{st.seq:08d}"
        overlay_paths = {}
        for c, img in overlays.items():
            rel = f"overlays/{name}-{slug(c)}.png"
            Image.fromarray(img).save(out_dir / rel)
            overlay_paths[c] = rel
        panel = step_panel(step, st, overlays, norm_label=norm_label, tile_height=opts.tile_height, evidence=evidence)
        panel.save(out_dir / f"panels/{name}.png")
        thumb = panel.copy()
        thumb.thumbnail((10 * opts.thumb_height, opts.thumb_height), Image.Resampling.BILINEAR)
        thumb.save(out_dir / f"thumbs/{name}.jpg", quality=85)
        assets[st.seq] = StepAssets(f"panels/{name}.png", f"thumbs/{name}.jpg", overlay_paths)
        if make_videos:
            if st.connection not in videos:
                base = out_dir / "videos" / slug(st.connection)
                videos[st.connection] = _ConnectionVideo(
                    mp4=base.with_suffix(".mp4"),
                    gif=base.with_suffix(".gif"),
                    fps=opts.fps,
                    total=per_connection[st.connection],
                    opts=opts,
                )
            videos[st.connection].add(panel)
    for v in videos.values():
        v.close()
    video_paths = {
        conn: {"mp4": v.mp4.relative_to(out_dir).as_posix(), "gif": v.gif.relative_to(out_dir).as_posix()}
        for conn, v in videos.items()
    }
    result = RenderResult(out_dir, assets, video_paths, stats)
    if opts.html:
        metas = {v.seq: v.meta for v in steps}
        result.report = write_report(
            result,
            dict(run.manifest),
            map_label=MAP_KIND_INFO[opts.map].label,
            norm=opts.norm,
            step_meta=metas,
            evidence=evidence,
        )
    return result


def default_render_dir(run_dir: pathlib.Path, map_kind: str) -> pathlib.Path:
    """RUN_DIR/render-<kind>: each map kind renders into its own directory."""
    return pathlib.Path(run_dir) / f"render-{map_kind}"
