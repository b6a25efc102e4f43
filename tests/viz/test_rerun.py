"""The Rerun sink: a real CAM run written as an .rrd and read back with rerun-sdk's own reader
(`rerun.chunk.RrdReader`), its entity paths and values compared with what the step files hold."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
from viz_support import assert_overlay_matches, expected_overlay, shares, step_peak

from openpi_cam import cli
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.run_format import StepRecord, load_run

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
# Connection "ep 1/a" is one entity-path part, escaped as Rerun writes it.
ESCAPED = {"ep 1/a": r"ep\ 1\/a", "c2": "c2"}


def _run(tmp_path, *, gradnorm: bool = True, checks: list[dict] | None = None) -> CAMLogger:
    """Two connections (one with a name that needs escaping), a masked camera, a multi-token map; gradient-norm maps
    unlike the Grad-CAM ones (or none); `checks`: each step's spot check (`meta.check`)."""
    rng = np.random.default_rng(0)
    cam_logger = CAMLogger(tmp_path / "cam", run_config={}, checkpoint="ck", options={})
    for i, (conn, step) in enumerate([("ep 1/a", 0), ("ep 1/a", 1), ("c2", 0)]):
        gradcam = {
            CAMERAS[0]: rng.random((16, 16), dtype=np.float32),
            CAMERAS[1]: rng.random((2, 16, 16), np.float32) - 0.2,  # negatives carry no attention
        }
        maps = {"gradcam": gradcam}
        if gradnorm:
            maps["gradnorm"] = {c: np.flip(m, -1) ** 3 for c, m in gradcam.items()}
        meta = {
            "target": "all-action-tokens",
            "score": [0.5 + i, 1.5 + i],
            "token_ids": [3, 4],
            "cameras": {
                CAMERAS[0]: {"obs_key": "img", "valid": True, "grid": [16, 16], "span": [0, 256], "geometry": GEOMETRY},
                CAMERAS[1]: {"obs_key": None, "valid": i != 1, "grid": [16, 16], "span": [256, 512], "geometry": None},
            },
        }
        if checks:
            meta["check"] = checks[i]
        frames = {CAMERAS[0]: rng.integers(0, 256, (90, 160, 3), dtype=np.uint8)}
        model_frames = {CAMERAS[1]: rng.integers(0, 256, (224, 224, 3), dtype=np.uint8)}
        assert cam_logger.log_step(StepRecord(conn, step, time.time(), maps, frames, model_frames, meta=meta))
    cam_logger.close()
    return cam_logger


def _columns(path) -> dict[str, dict[str, list]]:
    """entity path -> {"step": [...], "seq": [...], "value": [...], "format": [...]} over all chunks of the
    recording's first store (rerun-sdk's reader; a missing reader is an error, not a skip)."""
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


def _image(cols: dict[str, dict[str, list]], path: str, seq: int) -> np.ndarray:
    logged = cols[path]
    row = logged["seq"].index(seq)
    fmt = logged["format"][row][0]
    return np.asarray(logged["value"][row][0], np.uint8).reshape(fmt["height"], fmt["width"], -1)


def _check_recording(cols: dict[str, dict[str, list]], run_dir, kind: str) -> None:
    """Every step's frames, overlays of `kind`, shares and score, as the step files define them."""
    for step in load_run(run_dir).steps:
        meta, maps = step.meta.to_json(), step.maps_of(kind)  # the reference reads the JSON as stored
        conn = ESCAPED[meta["connection"]]
        share = shares(meta, maps)
        scale = step_peak(meta, maps)
        for c in CAMERAS:
            logged = cols[f"/{conn}/share/{c}"]
            row = logged["seq"].index(step.seq)
            assert logged["step"][row] == meta["step"]
            assert logged["value"][row][0] == pytest.approx(share[c], abs=1e-9)
            frame = step.frames.get(c, step.model_frames.get(c))
            np.testing.assert_array_equal(_image(cols, f"/{conn}/{c}/frame", step.seq), frame)
            want = expected_overlay(meta, maps, step.frames, step.model_frames, c, scale)
            assert_overlay_matches(_image(cols, f"/{conn}/{c}/overlay", step.seq), want, f"seq {step.seq} {c}")
        assert sum(share.values()) == pytest.approx(1.0)
        score = cols[f"/{conn}/score"]
        assert score["value"][score["seq"].index(step.seq)][0] == pytest.approx(np.mean(meta["score"]))


def test_write_rrd_logs_frames_overlays_and_shares(tmp_path):
    from openpi_cam.viz.rerun_sink import write_rrd

    run_dir = _run(tmp_path).run_dir
    path = write_rrd(run_dir, tmp_path / "viz" / "run.rrd", map_kind="gradcam")
    cols = _columns(path)
    expected = {f"/{conn}/score" for conn in ESCAPED.values()}
    expected |= {f"/{conn}/{c}/{leaf}" for conn in ESCAPED.values() for c in CAMERAS for leaf in ("frame", "overlay")}
    expected |= {f"/{conn}/share/{c}" for conn in ESCAPED.values() for c in CAMERAS}
    assert set(cols) == expected
    assert sorted(cols[r"/ep\ 1\/a/score"]["seq"]) == [0, 1] and cols["/c2/score"]["seq"] == [2]
    _check_recording(cols, run_dir, "gradcam")
    # The masked camera of seq 1 carries no attention and is drawn without a heatmap.
    masked = cols[r"/ep\ 1\/a/share/left_wrist_0_rgb"]
    assert masked["value"][masked["seq"].index(1)][0] == 0.0
    frame = _image(cols, r"/ep\ 1\/a/left_wrist_0_rgb/frame", 1)
    np.testing.assert_array_equal(_image(cols, r"/ep\ 1\/a/left_wrist_0_rgb/overlay", 1), frame)


def test_write_rrd_draws_the_requested_kind(tmp_path):
    from openpi_cam.viz.rerun_sink import write_rrd
    from openpi_cam.viz.stats import MissingMaps

    with pytest.raises(MissingMaps, match="no gradient norm"):
        write_rrd(_run(tmp_path / "old", gradnorm=False).run_dir, tmp_path / "old.rrd", map_kind="gradnorm")
    assert not (tmp_path / "old.rrd").exists()
    run_dir = _run(tmp_path).run_dir
    cols = _columns(write_rrd(run_dir, tmp_path / "gradnorm.rrd"))  # the default kind
    _check_recording(cols, run_dir, "gradnorm")
    step = load_run(run_dir).steps[0]
    gradcam = expected_overlay(
        step.meta.to_json(), step.maps_of("gradcam"), step.frames, step.model_frames, CAMERAS[0], 1.0
    )  # any scale: the two kinds peak in different places
    assert np.abs(_image(cols, r"/ep\ 1\/a/base_0_rgb/overlay", 0).astype(int) - gradcam).max() > 50


def test_render_cli_writes_a_recording(tmp_path):
    run_dir = _run(tmp_path).run_dir
    rrd = tmp_path / "out.rrd"
    argv = ["render", str(run_dir), "--out", str(tmp_path / "render"), "--no-videos", "--no-html", "--no-progress"]
    cli.main([*argv, "--rerun", str(rrd)])
    assert (tmp_path / "render" / "panels" / "00000002.png").is_file()  # the rest of render still ran
    cols = _columns(rrd)
    _check_recording(cols, run_dir, "gradnorm")


def test_recording_carries_each_steps_faithfulness_from_the_runs_report(tmp_path):
    """With RUN_DIR/faithfulness.json (the format `openpi-cam faithfulness` writes), each step's figure for the drawn
    kind is a series next to its camera's overlay; steps and cameras the report lacks log nothing."""
    import json

    from openpi_cam.viz.rerun_sink import write_rrd

    run_dir = _run(tmp_path).run_dir
    figures = {  # seq -> camera -> kind -> top patch's drop / best patch's
        "0": {CAMERAS[0]: {"gradcam": 0.25, "gradnorm": 0.75}, CAMERAS[1]: {"gradcam": 0.5, "gradnorm": 0.125}},
        "2": {CAMERAS[0]: {"gradcam": None, "gradnorm": None}},  # no patch lowered this step's score
    }
    steps = {seq: {c: {"optimum": 1.0, "deletion_k1": f} for c, f in cams.items()} for seq, cams in figures.items()}
    cameras = {c: {"steps": 2, "kinds": {"gradcam": {}, "gradnorm": {}}} for c in CAMERAS}
    report = {"run_id": run_dir.name, "steps_evaluated": 2, "cameras": cameras, "steps": steps}
    (run_dir / "faithfulness.json").write_text(json.dumps(report))
    for kind in ("gradcam", "gradnorm"):
        cols = _columns(write_rrd(run_dir, tmp_path / f"{kind}.rrd", map_kind=kind))
        _check_recording(cols, run_dir, kind)
        logged = {path: (c["seq"], [v[0] for v in c["value"]]) for path, c in cols.items() if "/faithfulness/" in path}
        assert logged == {
            rf"/ep\ 1\/a/faithfulness/{CAMERAS[0]}": ([0], [figures["0"][CAMERAS[0]][kind]]),
            rf"/ep\ 1\/a/faithfulness/{CAMERAS[1]}": ([0], [figures["0"][CAMERAS[1]][kind]]),
        }


def _text(path, entity: str) -> str:
    from rerun.chunk import RrdReader

    for chunk in RrdReader(str(path)).store().stream():
        if chunk.entity_path == entity:
            return chunk.to_record_batch().column("TextDocument:text").to_pylist()[0][0]
    raise AssertionError(f"no text document at {entity}")


def test_recording_carries_the_spot_check_summary_of_the_drawn_kind(tmp_path):
    """Steps with a spot check (`meta.check`) and no faithfulness report: the /faithfulness document says the maps were
    spot-checked and carries the same table as the HTML report (here the gradient norm's top patch beats every random
    patch in 2 of 3 steps: 67%, chance 1/5); a kind the checks do not name gets neither."""
    from openpi_cam.viz.rerun_sink import write_rrd

    def check(top_drop: float, drops: list[float]) -> dict:
        camera = {"top_patch": {"gradnorm": 5}, "top_patch_drop": {"gradnorm": top_drop}}
        return {
            "patches": 4,
            "cameras": {CAMERAS[0]: camera | {"random_patches": [1, 2, 3, 4], "random_patch_drops": drops}},
        }

    checks = [check(0.5, [0.1, 0.2, 0.0, 0.1]), check(0.05, [0.3, 0.0, 0.0, 0.0]), check(0.4, [0.1, 0.1, 0.1, 0.2])]
    run_dir = _run(tmp_path, checks=checks).run_dir
    text = _text(write_rrd(run_dir, tmp_path / "gradnorm.rrd", map_kind="gradnorm"), "/faithfulness")
    assert "Spot-checked live (3 of 3 steps)" in text and "top patch beats every random patch" in text
    assert f"| {CAMERAS[0]} | 3 | 0.4 | 0.1 | 67% (chance 20%) |" in text
    text = _text(write_rrd(run_dir, tmp_path / "gradcam.rrd", map_kind="gradcam"), "/faithfulness")
    assert "No faithfulness report" in text and "Spot-checked" not in text and "spot checks stored" not in text


def test_missing_rerun_names_the_extra(tmp_path, monkeypatch):
    from openpi_cam.viz.rerun_sink import write_rrd

    run_dir = _run(tmp_path).run_dir
    monkeypatch.setitem(sys.modules, "rerun", None)  # what an environment without rerun-sdk looks like to import
    with pytest.raises(ImportError, match=r"openpi-cam\[rerun\]"):
        write_rrd(run_dir, tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists()
