"""Overlays, panels, videos and the HTML report, on real run directories written by CAMLogger (and one version-1 run
written by hand)."""

from __future__ import annotations

import html.parser
import json
import os
import pathlib
import re
import shutil
import subprocess
import urllib.parse

import numpy as np
import pytest
from PIL import Image
from viz_support import assert_overlay_matches, expected_overlay, step_peak

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.run_format import StepRecord, load_run
from openpi_cam.cli import main as cli_main
from openpi_cam.letterbox import letterbox_geometry
from openpi_cam.viz.colormap import LUT, colorize
from openpi_cam.viz.overlay import map_on_original, upsample
from openpi_cam.viz.render import RenderOptions, render_run
from openpi_cam.viz.report import flag_steps, write_report
from openpi_cam.viz.stats import compute_stats, to_rows, view_steps

GRID = 16
MODEL = 224
BASE, WRIST = "base_0_rgb", "left_wrist_0_rgb"
GEOMETRY = letterbox_geometry(180, 320, MODEL, MODEL)


def _hot(cell: tuple[int, int], value: float = 1.0) -> np.ndarray:
    m = np.zeros((GRID, GRID), np.float32)
    m[cell] = value
    return m


def _meta(score: float, **fields) -> dict:
    return {
        "target": "action-token",
        "token_ids": [1234],
        "decode_steps": [3],
        "positions": [300],
        "action_indices": [0],
        "score": score,
        "prompt": "pick up the cube",
        "cameras": {
            BASE: {"obs_key": "image", "valid": True, "grid": [GRID, GRID], "span": [0, 256], "geometry": None},
            WRIST: {"obs_key": "wrist", "valid": True, "grid": [GRID, GRID], "span": [256, 512], "geometry": None},
        },
        "malformed": None,
        "extra": {},
    } | fields


def _log(cam_dir: pathlib.Path, steps: list[tuple[str, dict[str, dict[str, np.ndarray]], float, dict]]) -> pathlib.Path:
    """A run of (connection, maps by kind, score, meta fields) steps. The base camera has a black 180x320 original
    frame letterboxed into the model image; the wrist camera only a grey model frame."""
    frames = {BASE: np.zeros((180, 320, 3), np.uint8)}
    model_frames = {WRIST: np.full((MODEL, MODEL, 3), 40, np.uint8)}
    counters: dict[str, int] = {}
    with CAMLogger(cam_dir, run_config={}, checkpoint="ckpt", options={}) as logger:
        for i, (conn, maps, score, fields) in enumerate(steps):
            step = counters[conn] = counters.get(conn, -1) + 1
            meta = _meta(score, **fields)
            meta["cameras"][BASE]["geometry"] = GEOMETRY.as_dict()
            meta["map_kinds"] = list(maps)
            assert logger.log_step(StepRecord(conn, step, 100.0 + i, maps, frames, model_frames, meta=meta))
    return logger.run_dir


def _brightest(img: np.ndarray) -> tuple[int, int]:
    r, c = np.unravel_index(np.argmax(img.astype(int).sum(-1)), img.shape[:2])
    return int(r), int(c)


def test_hot_cell_lands_on_the_original_frame():
    geo = GEOMETRY
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
    """Two connections; on "a" the base camera usually dominates, step 3 looks at the wrist, step 5's score drops.
    The maps are gradient-norm maps (what render draws by default); the Grad-CAM maps beside them peak elsewhere."""
    steps = []
    for i in range(6):
        base, wrist = _hot((6, 10), 1.0), _hot((8, 8), 0.2)
        if i == 3:
            base, wrist = _hot((6, 10), 0.1), _hot((2, 12), 1.0)
        other = {BASE: _hot((0, 0)), WRIST: _hot((15, 15))}
        steps.append(("a", {"gradnorm": {BASE: base, WRIST: wrist}, "gradcam": other}, 0.2 if i == 5 else 1.0, {}))
        if i % 2 == 0:
            maps = {BASE: _hot((i, i), 0.5), WRIST: _hot((15 - i, i), 0.5)}
            steps.append(("b", {"gradnorm": maps, "gradcam": other}, 0.5, {}))
    tmp = tmp_path_factory.mktemp("viz")
    run = load_run(_log(tmp / "cam", steps))
    return run, render_run(run, tmp / "out", RenderOptions(progress=False))


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
    # Every overlay of every step, against the reference built from the step file alone.
    for step in run.steps:
        maps = step.maps_of("gradnorm")
        for camera, rel in result.steps[step.seq].overlays.items():
            meta = step.meta.to_json()  # the reference reads the JSON as stored
            want = expected_overlay(meta, maps, step.frames, step.model_frames, camera, step_peak(meta, maps))
            assert_overlay_matches(np.asarray(Image.open(result.out_dir / rel)), want, f"seq {step.seq} {camera}")


def test_run_normalisation_dims_weaker_steps(tmp_path):
    steps = [("a", {"gradnorm": {BASE: _hot((6, 10), v), WRIST: _hot((1, 1), v)}}, 1.0, {}) for v in (1.0, 0.5)]
    run = load_run(_log(tmp_path / "cam", steps))

    def peak_colour(norm: str, seq: int) -> np.ndarray:
        res = render_run(run, tmp_path / norm, RenderOptions(norm=norm, videos=False, progress=False))
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
    import av

    for conn, n in per_conn.items():
        paths = result.videos[conn]
        with av.open(str(result.out_dir / paths["mp4"])) as container:
            frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
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


def _check_links(doc: str, out_dir: pathlib.Path) -> _Collector:
    """Every in-page link has its target and every file link its file; nothing points at the network."""
    parser = _Collector()
    parser.feed(doc)
    assert not re.search(r"https?:", doc), "the report must not reference the network"
    for ref in parser.refs:
        if ref.startswith("#"):
            assert ref[1:] in parser.ids, ref
        else:
            assert (out_dir / urllib.parse.unquote(ref)).is_file(), ref
    return parser


def test_html_report_is_complete_and_offline(rendered):
    run, result = rendered
    doc = result.report.read_text()
    parser = _check_links(doc, result.out_dir)
    assert parser.steps == {s.seq for s in run.steps}
    assert "gradient norm (unsigned sensitivity) maps" in doc
    assert "failures (0)" in doc and "0 of 9 steps" in doc
    # The flagged steps follow from how the run was built: on "a", step 3 looks at the wrist and step 5's score
    # drops by 80%; nothing on "b" (its shares are even and its score constant).
    conn_a = [s for s in run.steps if s.meta.connection == "a"]
    flags = flag_steps(compute_stats(view_steps(run.steps, "gradnorm")))
    assert {(f.seq, f.reason) for f in flags} == {
        (conn_a[3].seq, "attention moved from base_0_rgb to left_wrist_0_rgb"),
        (conn_a[5].seq, "score dropped 80%"),
    }
    for f in flags:
        assert f'<li><a href="#step-{f.seq}">' in doc


def test_report_renders_in_headless_chromium(rendered):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but Chromium is not installed: .ci/run installs it, so the report test must run")
        pytest.skip("chromium is not installed (CI installs it and runs this test)")
    run, result = rendered
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--virtual-time-budget=5000", "--dump-dom", result.report.resolve().as_uri()]  # fmt: skip
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True).stdout
    rendered_seqs = {int(m) for m in re.findall(r'data-seq="(\d+)" data-rendered="1"', dom)}
    assert rendered_seqs == {s.seq for s in run.steps}
    assert f'data-rendered-steps="{len(run.steps)}"' in dom


def _failures_section(doc: str) -> str:
    start = doc.index('<section class="failures"')
    return doc[start : doc.index("</section>", start)]


def _failure_steps(n: int, malformed: dict[int, str]) -> list[tuple[str, dict, float, dict]]:
    """n steps on one connection; the steps in `malformed` failed with that reason (explained as upstream's fallback
    generation would be, with target `generated-tokens`)."""
    steps = []
    for i in range(n):
        fields = {"malformed": malformed[i], "target": "generated-tokens"} if i in malformed else {}
        steps.append(("c0", {"gradnorm": {BASE: _hot((i, 3)), WRIST: _hot((3, i), 0.5)}}, 1.0, fields))
    return steps


def test_report_lists_failures_first(tmp_path):
    run = load_run(_log(tmp_path / "cam", _failure_steps(4, {1: "no_action_prefix", 3: "wrong_action_shape"})))
    result = render_run(run, tmp_path / "out", RenderOptions(videos=False, progress=False))
    doc = result.report.read_text()
    _check_links(doc, result.out_dir)
    failures = _failures_section(doc)
    # Before any connection or step section: failures are what a reader must see first.
    assert doc.index('<section class="failures"') < doc.index('<section class="conn"') < doc.index("<h2>steps</h2>")
    assert "failures (2)" in failures and "2 of 4 steps" in doc
    items = re.findall(r"<li>(.*?)</li>", failures)
    assert len(items) == 2
    for item, (seq, reason) in zip(items, [(1, "no_action_prefix"), (3, "wrong_action_shape")], strict=True):
        assert f'href="#step-{seq}"' in item and f"step {seq}" in item
        assert f'<code class="reason">{reason}</code>' in item
        assert '<code class="target">generated-tokens</code>' in item
    for seq in range(4):
        marked = f'<section class="step failure" id="step-{seq}"' in doc
        assert marked == (seq in (1, 3))
    assert "malformed generation: wrong_action_shape" in doc

    # write_report alone, given the manifest only: schema 2 index entries name the failures too.
    bare = render_run(run, tmp_path / "bare", RenderOptions(videos=False, progress=False, html=False))
    assert bare.report is None
    doc = write_report(bare, run.manifest, map_label="x", norm="step").read_text()
    assert re.findall(r'href="#step-(\d+)"', _failures_section(doc)) == ["1", "3"]


def _write_version_1_run(run_dir: pathlib.Path, malformed: dict[int, str], n: int = 3) -> None:
    """A run as schema 1 wrote it: `cam/` and `gradnorm/` maps, `malformed_reason` and `gradcam_ms` in the meta, no
    model inputs, index entries without failure fields."""
    (run_dir / "steps").mkdir(parents=True)
    run_info = {"schema_version": 1, "run_id": run_dir.name, "started_at": "2026-01-01T00:00:00.000Z"}
    (run_dir / "run.json").write_text(json.dumps(run_info | {"config": {}, "checkpoint": "old", "options": {}}))
    for seq in range(n):
        meta = _meta(1.0) | {"schema_version": 1, "run_id": run_dir.name, "seq": seq, "connection": "old", "step": seq}
        del meta["malformed"]
        meta |= {"timestamp": 10.0 + seq, "malformed_reason": malformed.get(seq), "gradcam_ms": 5.0}
        if seq in malformed:
            meta["target"] = "chunk"
        arrays = {f"cam/{c}": _hot((seq, 2)) for c in (BASE, WRIST)}
        arrays |= {f"gradnorm/{c}": _hot((2, seq)) for c in (BASE, WRIST)}
        arrays[f"frame_model/{WRIST}"] = np.full((MODEL, MODEL, 3), 40, np.uint8)
        np.savez(run_dir / "steps" / f"{seq:08d}.npz", **arrays, meta=np.array(json.dumps(meta)))


def test_report_lists_the_failures_of_a_version_1_run(tmp_path):
    run_dir = tmp_path / "20250101-000000-abcdef"
    _write_version_1_run(run_dir, {2: "no_action_prefix"})
    run = load_run(run_dir)
    assert [s.meta.malformed for s in run.steps] == [None, None, "no_action_prefix"]  # schema 1's malformed_reason
    for kind in ("gradcam", "gradnorm"):
        result = render_run(run, tmp_path / kind, RenderOptions(map=kind, videos=False, progress=False))
        doc = result.report.read_text()
        failures = _failures_section(doc)
        assert "failures (1)" in failures and "1 of 3 steps" in doc
        assert re.findall(r'href="#step-(\d+)"', failures) == ["2"]
        assert '<code class="reason">no_action_prefix</code>' in failures
        assert '<code class="target">chunk</code>' in failures


def test_render_command(tmp_path):
    steps = [("a", {"gradnorm": {BASE: _hot((6, 10)), WRIST: _hot((1, 1))}}, 1.0, {})] * 2
    run_dir = _log(tmp_path / "cam", steps)
    cli_main(["render", str(run_dir), "--no-videos", "--norm", "run", "--no-progress"])
    out = run_dir / "render-gradnorm"
    assert (out / "index.html").is_file() and len(list((out / "panels").glob("*.png"))) == 2
    assert not any((out / "videos").iterdir())


def test_render_and_stats_draw_the_requested_kind(tmp_path, capsys):
    """`--map` picks which maps are drawn and measured, and the report says which."""
    maps = {
        "gradcam": {BASE: _hot((6, 10)), WRIST: _hot((1, 1))},
        "gradnorm": {BASE: _hot((8, 4)), WRIST: _hot((12, 12))},
    }
    run_dir = _log(tmp_path / "cam", [("a", maps, 1.0, {})])
    # Cell (6, 10) is centred on original pixel (60, 210), cell (8, 4) on ((119 - 49) * 180 / 126, 63 * 320 / 224).
    for kind, label, centre in (
        ("gradcam", "Grad-CAM maps", (60.0, 210.0)),
        ("gradnorm", "gradient norm", (100.0, 90.0)),
    ):
        cli_main(["render", str(run_dir), "--map", kind, "--no-videos", "--no-progress"])
        out = run_dir / f"render-{kind}"
        assert label in (out / "index.html").read_text()
        (overlay,) = (out / "overlays").glob(f"*-{BASE}.png")
        r, c = _brightest(np.asarray(Image.open(overlay)))
        assert abs(r + 0.5 - centre[0]) <= 1 and abs(c + 0.5 - centre[1]) <= 1
    capsys.readouterr()
    for kind, peak in (("gradcam", [6, 10]), ("gradnorm", [8, 4])):
        cli_main(["stats", str(run_dir), "--map", kind, "--format", "json"])
        (row,) = json.loads(capsys.readouterr().out)["steps"]
        assert [row[f"{BASE}/peak_row"], row[f"{BASE}/peak_col"]] == peak

    # Not told which, they draw the most trusted kind the run carries (`drawn_kind`): the gradient norm here, Grad-CAM
    # in a run of Grad-CAM alone; a kind named that the run lacks is refused before anything is written.
    cli_main(["render", str(run_dir), "--no-videos", "--no-progress", "--out", str(tmp_path / "drawn")])
    assert "gradient norm" in (tmp_path / "drawn" / "index.html").read_text()
    only_gradcam = _log(tmp_path / "old", [("a", {"gradcam": maps["gradcam"]}, 1.0, {})])
    cli_main(["render", str(only_gradcam), "--no-videos", "--no-progress"])
    assert (only_gradcam / "render-gradcam" / "index.html").is_file()
    capsys.readouterr()
    cli_main(["stats", str(only_gradcam), "--format", "json"])
    (row,) = json.loads(capsys.readouterr().out)["steps"]
    assert [row[f"{BASE}/peak_row"], row[f"{BASE}/peak_col"]] == [6, 10]
    for command in ("render", "stats"):
        with pytest.raises(SystemExit) as exc:
            cli_main([command, str(only_gradcam), "--map", "gradnorm"])
        assert exc.value.code == 2 and "no gradient norm (unsigned sensitivity) maps" in capsys.readouterr().err
    assert not (only_gradcam / "render-gradnorm").exists()


def _report_json(run_dir: pathlib.Path, run_id: str) -> None:
    """A faithfulness report in the format `openpi-cam faithfulness` writes (cam.faithfulness_run), with figures that
    differ per kind, camera and step, so a report that showed the wrong one would show another number."""
    kinds = {
        BASE: {
            "gradcam": {"deletion_k1": {"median": 0.31}, "top1_occlusion": {"mean": 0.5}},
            "gradnorm": {"deletion_k1": {"median": 0.94}, "top1_occlusion": {"mean": 1.0}},
            "random": {"deletion_k1": {"median": 0.07}},
        },
        WRIST: {
            "gradcam": {"deletion_k1": {"median": 0.22}, "randomisation_abs_spearman": {"mean": 0.45}},
            "random": {"deletion_k1": {"median": 0.09}},
        },
    }
    kinds[WRIST]["gradcam"]["null_abs_spearman"] = {"mean": 0.21}
    cameras = {c: {"steps": 2, "steps_with_positive_optimum": 2, "kinds": k} for c, k in kinds.items()}
    steps = {
        "0": {BASE: {"optimum": 1.0, "deletion_k1": {"gradcam": 0.43, "gradnorm": 0.96, "random": 0.11}}},
        "1": {
            BASE: {"optimum": 0.5, "deletion_k1": {"gradcam": 0.58, "gradnorm": 0.81, "random": 0.13}},
            WRIST: {"optimum": 0.0, "deletion_k1": {"gradcam": None, "random": None}},
        },
    }
    report = {"run_id": run_id, "steps_evaluated": 2, "cameras": cameras, "steps": steps}
    (run_dir / "faithfulness.json").write_text(json.dumps(report))


def _evidence_cells(doc: str) -> dict[int, list[str]]:
    """seq -> the evidence column of its step table, in camera order."""
    sections = re.findall(r'<section class="step[^"]*" id="step-(\d+)"(.*?)</section>', doc, re.S)
    cells = {int(seq): re.findall(r'<td class="evidence">(.*?)</td>', body) for seq, body in sections}
    return {seq: [html.unescape(c) for c in row] for seq, row in cells.items()}


def test_report_shows_the_runs_faithfulness_for_the_drawn_kind(tmp_path):
    """Every rendered map comes with its evidence: the run's own faithfulness figures for the kind drawn (run level
    and per step, next to a random patch's), the share of all-zero maps, and where there is no report for this run,
    a plain "not measured" with the command that measures it."""
    zero = np.zeros((GRID, GRID), np.float32)
    steps = [
        ("a", {"gradcam": {BASE: _hot((6, 10)), WRIST: zero}, "gradnorm": {BASE: _hot((1, 2)), WRIST: _hot((3, 3))}}),
        (
            "a",
            {
                "gradcam": {BASE: _hot((2, 2)), WRIST: _hot((1, 1))},
                "gradnorm": {BASE: _hot((4, 5)), WRIST: _hot((5, 5))},
            },
        ),
        ("a", {"gradcam": {BASE: zero, WRIST: _hot((3, 3))}, "gradnorm": {BASE: _hot((9, 9)), WRIST: _hot((7, 7))}}),
    ]
    run_dir = _log(tmp_path / "cam", [(conn, maps, 1.0, {}) for conn, maps in steps])
    run = load_run(run_dir, load_arrays=False)

    def report(kind: str) -> str:
        return render_run(
            run, tmp_path / kind, RenderOptions(map=kind, videos=False, progress=False)
        ).report.read_text()

    doc = report("gradcam")
    assert 'data-status="missing"' in doc and f"openpi-cam faithfulness {run_dir}" in doc
    assert "33.3% of the drawn camera-steps have an all-zero" in doc  # 2 of the 6 camera-steps above
    assert all(cells == ["not measured"] * 2 for cells in _evidence_cells(doc).values())

    _report_json(run_dir, run_dir.name)
    doc = report("gradcam")
    assert 'data-status="measured"' in doc and "2 steps re-scored of the 3 drawn" in doc
    assert "0.31 (random 0.07)" in doc and "0.22 (random 0.09)" in doc and "0.45 (null 0.21)" in doc
    assert "0.94" not in doc  # the gradient norm's figures belong to the other report
    assert _evidence_cells(doc) == {
        0: ["0.43 of best (random 0.11)", "step not in the report"],
        1: ["0.58 of best (random 0.13)", "no patch lowers the score"],
        2: ["step not in the report", "step not in the report"],
    }
    doc = report("gradnorm")
    assert "0.94 (random 0.07)" in doc and "0.31" not in doc
    assert _evidence_cells(doc)[1][0] == "0.81 of best (random 0.13)"

    _report_json(run_dir, "20200101-000000-another")  # a report copied from another run is not this run's evidence
    assert 'data-status="missing"' in report("gradcam")


def test_report_shows_the_spot_checks_without_a_faithfulness_report(tmp_path):
    """Steps carry their spot check (`meta.check`): with no faithfulness report the report is "spot-checked", gives
    each step's top-patch drop next to the largest random one, and counts how often the top patch beats every random
    patch next to chance 1 / (R + 1). A random draw of the kind's own top patch is not a competitor (step 2: counted,
    it would tie, and the step would not beat)."""

    def check(top: int, top_drop: float, randoms: list[int], drops: list[float]) -> dict:
        camera = {"top_patch": {"gradnorm": top}, "top_patch_drop": {"gradnorm": top_drop}}
        return {
            "patches": len(randoms),
            "cameras": {BASE: camera | {"random_patches": randoms, "random_patch_drops": drops}},
        }

    maps = {"gradnorm": {BASE: _hot((6, 10)), WRIST: _hot((1, 1))}}
    checks = [
        check(170, 0.5, [1, 2, 3, 4], [0.1, 0.2, -0.1, 0.05]),  # beats
        check(170, 0.05, [1, 2, 3, 4], [0.3, 0.0, 0.01, 0.02]),  # does not
        check(7, 0.4, [7, 8, 9, 10], [0.4, 0.1, 0.1, 0.1]),  # beats the three others
    ]
    run_dir = _log(tmp_path / "cam", [("a", maps, 1.0, {"check": c}) for c in checks])
    run = load_run(run_dir, load_arrays=False)
    doc = render_run(run, tmp_path / "out", RenderOptions(videos=False, progress=False)).report.read_text()
    assert 'data-status="spot-checked"' in doc and "Spot-checked live (3 of 3 steps)" in doc
    assert "67% (chance 22%)" in doc  # 2 of 3; chance (1/5 + 1/5 + 1/4) / 3
    assert _evidence_cells(doc) == {
        0: ["drop 0.5 (random <= 0.2)", "not measured"],
        1: ["drop 0.05 (random <= 0.3)", "not measured"],
        2: ["drop 0.4 (random <= 0.1)", "not measured"],
    }
    rows = to_rows(compute_stats(view_steps(run.steps, "gradnorm")))  # `openpi-cam stats`: the same figures
    assert [(r[f"{BASE}/check_top_drop"], r[f"{BASE}/check_random_max"]) for r in rows] == [
        (0.5, 0.2),
        (0.05, 0.3),
        (0.4, 0.1),
    ]
    assert all(r[f"{WRIST}/check_top_drop"] is None for r in rows)  # no check for that camera
