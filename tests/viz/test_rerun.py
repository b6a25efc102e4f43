"""The Rerun sink: a real CAM run written as an .rrd, read back with rerun's own RRD reader."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
from openpi_cam.cam.reader import load_run

from openpi_cam import cli
from openpi_cam.cam.logger import CAMLogger, StepRecord

CAMERAS = ("base_0_rgb", "left_wrist_0_rgb")
GEOMETRY = {  # a 90 x 160 client frame letterboxed into 224 x 224
    "orig_h": 90,
    "orig_w": 160,
    "model_h": 224,
    "model_w": 224,
    "resized_h": 126,
    "resized_w": 224,
    "pad_top": 49,
    "pad_left": 0,
}


def _run(tmp_path, *, gradnorm: bool = False) -> CAMLogger:
    """Two connections (one with a name that needs escaping), a masked camera, a multi-token map; with `gradnorm`,
    gradient-norm maps unlike the Grad-CAM ones."""
    rng = np.random.default_rng(0)
    cam_logger = CAMLogger(tmp_path / "cam", run_config={}, checkpoint="ck", options={})
    for i, (conn, step) in enumerate([("ep 1/a", 0), ("ep 1/a", 1), ("c2", 0)]):
        maps = {CAMERAS[0]: rng.random((16, 16), dtype=np.float32), CAMERAS[1]: rng.random((2, 16, 16), np.float32)}
        meta = {
            "target": "all-action-tokens",
            "score": [0.5 + i, 1.5 + i],
            "token_ids": [3, 4],
            "cameras": {
                CAMERAS[0]: {"obs_key": "img", "valid": True, "grid": [16, 16], "span": [0, 256], "geometry": GEOMETRY},
                CAMERAS[1]: {"obs_key": None, "valid": i != 1, "grid": [16, 16], "span": [256, 512], "geometry": None},
            },
        }
        frames = {CAMERAS[0]: rng.integers(0, 256, (90, 160, 3), dtype=np.uint8)}
        model_frames = {CAMERAS[1]: rng.integers(0, 256, (224, 224, 3), dtype=np.uint8)}
        norms = {c: np.flip(m, -1) ** 3 for c, m in maps.items()} if gradnorm else {}
        assert cam_logger.log_step(StepRecord(conn, step, time.time(), maps, frames, model_frames, meta, norms))
    cam_logger.close()
    return cam_logger


def _columns(path) -> dict[str, dict[str, list]]:
    """entity path -> {"step": [...], "seq": [...], "value": [...]} from the recording (all chunks of an entity)."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(str(path)).store().stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        value = next((n for n in ("Scalars:scalars", "Image:buffer") if n in names), None)
        if value is None:
            continue
        cols = out.setdefault(chunk.entity_path, {"step": [], "seq": [], "value": [], "format": []})
        cols["step"] += batch.column("step").to_pylist()
        cols["seq"] += batch.column("seq").to_pylist()
        cols["value"] += batch.column(value).to_pylist()
        if "Image:format" in names:
            cols["format"] += batch.column("Image:format").to_pylist()
    return out


def test_write_rrd_logs_frames_overlays_and_shares(tmp_path):
    pytest.importorskip("rerun")
    from openpi_cam.viz.render import camera_image, camera_overlay, step_scale
    from openpi_cam.viz.rerun_sink import entity_paths, write_rrd
    from openpi_cam.viz.stats import compute_stats

    run_dir = _run(tmp_path).run_dir
    path = write_rrd(run_dir, tmp_path / "viz" / "run.rrd")
    assert path.is_file() and path.stat().st_size > 10_000  # holds several full frames
    try:
        from rerun.chunk import RrdReader  # noqa: F401
    except ImportError:
        pytest.skip("this rerun-sdk cannot read recordings back (rerun.chunk.RrdReader)")
    cols = _columns(path)
    expected = set(entity_paths("ep 1/a", list(CAMERAS))) | set(entity_paths("c2", list(CAMERAS)))
    assert set(cols) == expected
    assert r"/ep\ 1\/a/base_0_rgb/overlay" in cols  # one escaped path part per connection

    steps = load_run(run_dir).steps
    stats = compute_stats(steps)
    for step, st in zip(steps, stats, strict=True):
        conn = r"ep\ 1\/a" if st.connection == "ep 1/a" else "c2"
        shares = []
        for c in CAMERAS:
            share = cols[f"/{conn}/share/{c}"]
            row = share["seq"].index(st.seq)
            assert share["step"][row] == st.step
            shares.append(share["value"][row][0])
            assert shares[-1] == pytest.approx(st.cameras[c].share)
            image, _ = camera_image(step, c)
            for kind, want in (("frame", image), ("overlay", camera_overlay(step, c, step_scale(st), 0.5))):
                logged = cols[f"/{conn}/{c}/{kind}"]
                row = logged["seq"].index(st.seq)
                fmt = logged["format"][row][0]
                assert (fmt["height"], fmt["width"]) == want.shape[:2]
                assert np.array_equal(np.asarray(logged["value"][row][0], np.uint8).reshape(want.shape), want)
        assert sum(shares) == pytest.approx(1.0)
        score = cols[f"/{conn}/score"]
        assert score["value"][score["seq"].index(st.seq)][0] == pytest.approx(np.mean(step.meta["score"]))
    # The masked camera of seq 1 carries no attention and is drawn without a heatmap.
    masked = cols[r"/ep\ 1\/a/share/left_wrist_0_rgb"]
    assert masked["value"][masked["seq"].index(1)][0] == 0.0
    frame, overlay = cols[r"/ep\ 1\/a/left_wrist_0_rgb/frame"], cols[r"/ep\ 1\/a/left_wrist_0_rgb/overlay"]
    assert frame["value"][frame["seq"].index(1)] == overlay["value"][overlay["seq"].index(1)]


def test_write_rrd_can_draw_the_gradient_norm_maps(tmp_path):
    pytest.importorskip("rerun")
    from openpi_cam.viz.render import camera_overlay, step_scale
    from openpi_cam.viz.rerun_sink import write_rrd
    from openpi_cam.viz.stats import compute_stats, with_map_kind

    with pytest.raises(ValueError, match="no gradient-norm maps"):
        write_rrd(_run(tmp_path / "old").run_dir, tmp_path / "old.rrd", map_kind="gradnorm")
    run_dir = _run(tmp_path, gradnorm=True).run_dir
    path = write_rrd(run_dir, tmp_path / "gradnorm.rrd", map_kind="gradnorm")
    try:
        from rerun.chunk import RrdReader  # noqa: F401
    except ImportError:
        pytest.skip("this rerun-sdk cannot read recordings back (rerun.chunk.RrdReader)")
    cols = _columns(path)
    steps = load_run(run_dir).steps
    views = with_map_kind(steps, "gradnorm")
    for step, view, st in zip(steps, views, compute_stats(views), strict=True):
        conn = r"ep\ 1\/a" if st.connection == "ep 1/a" else "c2"
        logged = cols[f"/{conn}/{CAMERAS[0]}/overlay"]
        drawn = np.asarray(logged["value"][logged["seq"].index(st.seq)][0], np.uint8)
        want = camera_overlay(view, CAMERAS[0], step_scale(st), 0.5)
        assert np.array_equal(drawn.reshape(want.shape), want)
        assert not np.array_equal(want, camera_overlay(step, CAMERAS[0], step_scale(st), 0.5))


def test_render_cli_writes_a_recording(tmp_path):
    pytest.importorskip("rerun")
    run_dir = _run(tmp_path).run_dir
    rrd = tmp_path / "out.rrd"
    argv = ["render", str(run_dir), "--out", str(tmp_path / "render"), "--no-videos", "--no-html", "--no-progress"]
    cli.main([*argv, "--rerun", str(rrd)])
    assert rrd.is_file() and rrd.stat().st_size > 10_000
    assert (tmp_path / "render" / "panels" / "00000002.png").is_file()  # the rest of render still ran


def test_missing_rerun_names_the_extra(tmp_path, monkeypatch):
    from openpi_cam.viz.rerun_sink import write_rrd

    run_dir = _run(tmp_path).run_dir
    monkeypatch.setitem(sys.modules, "rerun", None)  # what an environment without rerun-sdk looks like to import
    with pytest.raises(ImportError, match=r"openpi-cam\[rerun\]"):
        write_rrd(run_dir, tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists()
