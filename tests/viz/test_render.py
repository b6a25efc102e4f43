"""Overlays, panels, videos and the HTML report, on real run directories written by CAMLogger."""

from __future__ import annotations

import html.parser
import json
import pathlib
import re
import shutil
import subprocess
import urllib.parse

import numpy as np
import pytest
from openpi_cam.cam.reader import load_run
from PIL import Image

from openpi_cam.cam.logger import CAMLogger, StepRecord
from openpi_cam.cli import main as cli_main
from openpi_cam.image_tools import letterbox_geometry
from openpi_cam.viz.colormap import LUT, colorize
from openpi_cam.viz.overlay import map_on_original, upsample
from openpi_cam.viz.render import RenderOptions, render_run
from openpi_cam.viz.report import flag_steps, write_report
from openpi_cam.viz.stats import compute_stats

GRID = 16
MODEL = 224
BASE, WRIST = "base_0_rgb", "left_wrist_0_rgb"


def _hot(cell: tuple[int, int], value: float = 1.0) -> np.ndarray:
    m = np.zeros((GRID, GRID), np.float32)
    m[cell] = value
    return m


def _meta(score: float, base_geometry: dict | None) -> dict:
    return {
        "target": "action-token",
        "token_ids": [1234],
        "decode_steps": [3],
        "positions": [300],
        "action_indices": None,
        "score": score,
        "prompt": "pick up the cube",
        "cameras": {
            BASE: {
                "obs_key": "image",
                "valid": True,
                "grid": [GRID, GRID],
                "span": [0, 256],
                "geometry": base_geometry,
            },
            WRIST: {"obs_key": "wrist", "valid": True, "grid": [GRID, GRID], "span": [256, 512], "geometry": None},
        },
        "extra": {},
    }


def _log(
    cam_dir: pathlib.Path,
    steps: list[tuple[str, dict[str, np.ndarray], float]],
    gradnorm: dict[str, np.ndarray] | None = None,
) -> pathlib.Path:
    """A run whose base camera has a black 180x320 original frame and whose wrist camera only a model frame; every
    step carries the `gradnorm` maps when given."""
    geo = letterbox_geometry(180, 320, MODEL, MODEL)
    frames = {BASE: np.zeros((180, 320, 3), np.uint8)}
    model_frames = {WRIST: np.full((MODEL, MODEL, 3), 40, np.uint8)}
    counters: dict[str, int] = {}
    with CAMLogger(cam_dir, run_config={}, checkpoint="ckpt", options={}) as logger:
        for i, (conn, maps, score) in enumerate(steps):
            step = counters[conn] = counters.get(conn, -1) + 1
            meta = _meta(score, geo.as_dict())
            record = StepRecord(conn, step, 100.0 + i, maps, frames, model_frames, meta, gradnorm or {})
            assert logger.log_step(record)
    return logger.run_dir


def _brightest(img: np.ndarray) -> tuple[int, int]:
    r, c = np.unravel_index(np.argmax(img.astype(int).sum(-1)), img.shape[:2])
    return int(r), int(c)


def test_hot_cell_lands_on_the_original_frame():
    geo = letterbox_geometry(180, 320, MODEL, MODEL)
    assert (geo.pad_top, geo.resized_h, geo.pad_left, geo.resized_w) == (49, 126, 0, 224)  # rows 49..174 hold it
    heat = map_on_original(_hot((6, 10)), geo)
    assert heat.shape == (180, 320)
    # Cell (6, 10) is centred on model pixel (91, 147) -> original ((91 - 49) * 180 / 126, 147 * 320 / 224).
    r, c = np.unravel_index(np.argmax(heat), heat.shape)
    assert abs(r + 0.5 - 60.0) <= 0.5 and abs(c + 0.5 - 210.0) <= 0.5
    # Bilinear support reaches one cell (14 model px) around the centre and nothing beyond it.
    rows, cols = np.nonzero(heat)
    assert rows.min() >= (77 - 49) * 180 / 126 - 1 and rows.max() <= (105 - 49) * 180 / 126
    assert cols.min() >= 133 * 320 / 224 - 1 and cols.max() <= 161 * 320 / 224
    # A cell entirely inside the top padding (model rows 14..28) covers no original pixel.
    assert not map_on_original(_hot((1, 5)), geo).any()


def test_upsample_keeps_values_at_cell_centres():
    grid = np.arange(12, dtype=np.float64).reshape(3, 4)
    up = upsample(grid, 33, 44)  # 11 px per cell: the centre of cell r is the centre of pixel 11r + 5
    assert np.allclose(up[5::11, 5::11], grid)
    assert up.min() == grid.min() and up.max() == grid.max()


def test_colormap_is_monotone_in_brightness():
    assert LUT.shape == (256, 3) and LUT.dtype == np.uint8
    assert np.all(np.diff(LUT.astype(int).sum(-1)) >= 0)
    assert np.array_equal(colorize(np.array([-1.0, np.nan, 2.0])), LUT[[0, 0, 255]])


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory):
    """Two connections; on "a" the base camera usually dominates, step 3 looks at the wrist, step 5's score drops."""
    steps = []
    for i in range(6):
        base = _hot((6, 10), 1.0)
        wrist = _hot((8, 8), 0.2)
        if i == 3:
            base, wrist = _hot((6, 10), 0.1), _hot((2, 12), 1.0)
        steps.append(("a", {BASE: base, WRIST: wrist}, 0.2 if i == 5 else 1.0))
        if i % 2 == 0:
            steps.append(("b", {BASE: _hot((i, i), 0.5), WRIST: _hot((15 - i, i), 0.5)}, 0.5))
    tmp = tmp_path_factory.mktemp("viz")
    run_dir = _log(tmp / "cam", steps)
    run = load_run(run_dir)
    opts = RenderOptions(progress=False)
    result = render_run(run.steps, tmp / "out", opts)
    result.report = write_report(result, run.manifest, opts)
    return run, result


def test_overlays_follow_the_letterbox(rendered):
    run, result = rendered
    assets = result.steps[run.steps[0].seq]
    base = np.asarray(Image.open(result.out_dir / assets.overlays[BASE]))
    assert base.shape == (180, 320, 3)  # drawn on the client's original frame
    r, c = _brightest(base)
    assert abs(r + 0.5 - 60.0) <= 1 and abs(c + 0.5 - 210.0) <= 1
    wrist = np.asarray(Image.open(result.out_dir / assets.overlays[WRIST]))
    assert wrist.shape == (MODEL, MODEL, 3)  # only a model frame: the grid is stretched over it
    r, c = _brightest(wrist)
    assert abs(r + 0.5 - 8.5 * 14) <= 1 and abs(c + 0.5 - 8.5 * 14) <= 1


def test_run_normalisation_dims_weaker_steps(tmp_path):
    run_dir = _log(tmp_path / "cam", [("a", {BASE: _hot((6, 10), 1.0), WRIST: _hot((1, 1), 1.0)}, 1.0),
                                      ("a", {BASE: _hot((6, 10), 0.5), WRIST: _hot((1, 1), 0.5)}, 1.0)])  # fmt: skip
    steps = load_run(run_dir).steps

    def peak_colour(norm: str, seq: int) -> np.ndarray:
        res = render_run(steps, tmp_path / norm, RenderOptions(norm=norm, videos=False, progress=False))
        img = np.asarray(Image.open(res.out_dir / res.steps[seq].overlays[BASE]))
        return img[_brightest(img)]

    assert np.array_equal(peak_colour("step", 0), peak_colour("step", 1))
    assert peak_colour("run", 1).astype(int).sum() < peak_colour("run", 0).astype(int).sum()


def test_files_exist_and_decode(rendered):
    run, result = rendered
    per_conn = {"a": 6, "b": 3}
    assert set(result.steps) == {s.seq for s in run.steps}
    for assets in result.steps.values():
        for rel in (assets.panel, assets.thumb, *assets.overlays.values()):
            with Image.open(result.out_dir / rel) as img:
                img.load()
                assert min(img.size) > 0
    import imageio.v2 as iio

    for conn, n in per_conn.items():
        paths = result.videos[conn]
        reader = iio.get_reader(result.out_dir / paths["mp4"], format="FFMPEG")
        frames = [f for f in reader]
        reader.close()
        assert len(frames) == n and frames[0].ndim == 3
        with Image.open(result.out_dir / paths["gif"]) as gif:
            assert gif.n_frames == n


class _Collector(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()
        self.refs: list[str] = []
        self.steps: set[int] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(a["id"])
        if tag == "section" and "step" in (a.get("class") or "").split():
            self.steps.add(int(a["data-seq"]))
        self.refs += [v for k, v in attrs if k in ("src", "href") and v]


def test_html_report_is_complete_and_offline(rendered):
    run, result = rendered
    doc = result.report.read_text()
    parser = _Collector()
    parser.feed(doc)
    assert parser.steps == {s.seq for s in run.steps}
    assert not re.search(r"https?:", doc), "the report must not reference the network"
    for ref in parser.refs:
        if ref.startswith("#"):
            assert ref[1:] in parser.ids, ref
        else:
            assert (result.out_dir / urllib.parse.unquote(ref)).is_file(), ref
    # Every flagged step is reachable from its connection's flagged list.
    flags = flag_steps(compute_stats(run.steps))
    conn_a = [s for s in run.steps if s.meta["connection"] == "a"]
    assert {f.seq for f in flags} == {conn_a[3].seq, conn_a[5].seq}
    assert any("moved from base_0_rgb to left_wrist_0_rgb" in f.reason for f in flags)
    assert any("score dropped 80%" in f.reason for f in flags)
    for f in flags:
        assert f'<li><a href="#step-{f.seq}">' in doc


def test_report_renders_in_headless_chromium(rendered):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed")
    run, result = rendered
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--virtual-time-budget=5000", "--dump-dom", result.report.resolve().as_uri()]  # fmt: skip
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True).stdout
    rendered_seqs = {int(m) for m in re.findall(r'data-seq="(\d+)" data-rendered="1"', dom)}
    assert rendered_seqs == {s.seq for s in run.steps}
    assert f'data-rendered-steps="{len(run.steps)}"' in dom


def test_render_command(tmp_path):
    run_dir = _log(tmp_path / "cam", [("a", {BASE: _hot((6, 10)), WRIST: _hot((1, 1))}, 1.0)] * 2)
    cli_main(["render", str(run_dir), "--no-videos", "--norm", "run"])
    out = run_dir / "render"
    assert (out / "index.html").is_file() and len(list((out / "panels").glob("*.png"))) == 2
    assert not any((out / "videos").iterdir())


def test_render_and_stats_can_show_the_gradient_norm_maps(tmp_path, capsys):
    """`--map gradnorm` draws and measures the `gradnorm/` maps, not the Grad-CAM ones, and says so."""
    maps = {BASE: _hot((6, 10)), WRIST: _hot((1, 1))}
    run_dir = _log(tmp_path / "cam", [("a", maps, 1.0)], gradnorm={BASE: _hot((8, 4)), WRIST: _hot((12, 12))})
    cli_main(["render", str(run_dir), "--map", "gradnorm", "--no-videos"])
    out = run_dir / "render-gradnorm"
    assert "gradient norm maps" in (out / "index.html").read_text()
    (overlay,) = (out / "overlays").glob(f"*-{BASE}.png")
    r, c = _brightest(np.asarray(Image.open(overlay)))
    # Cell (8, 4) is centred on model pixel (119, 63) -> original ((119 - 49) * 180 / 126, 63 * 320 / 224).
    assert abs(r + 0.5 - 100.0) <= 1 and abs(c + 0.5 - 90.0) <= 1
    capsys.readouterr()
    for kind, peak in (("gradcam", [6, 10]), ("gradnorm", [8, 4])):
        cli_main(["stats", str(run_dir), "--map", kind, "--format", "json"])
        (row,) = json.loads(capsys.readouterr().out)["steps"]
        assert [row[f"{BASE}/peak_row"], row[f"{BASE}/peak_col"]] == peak

    older = _log(tmp_path / "old", [("a", maps, 1.0)])  # written without gradient-norm maps
    for command in ("render", "stats"):
        with pytest.raises(SystemExit) as exc:
            cli_main([command, str(older), "--map", "gradnorm"])
        assert exc.value.code == 2 and "no gradient-norm maps" in capsys.readouterr().err
