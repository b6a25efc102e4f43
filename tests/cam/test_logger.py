"""CAMLogger and reader against real files: round trip, manifest, caps, I/O failures, kill -9, threads."""

from __future__ import annotations

import json
import logging
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import pytest
from paths import REPO_ROOT

from openpi_cam import cli
from openpi_cam.cam import logger as logger_mod
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.run_format import (
    RUN_JSON,
    SCHEMA_VERSION,
    StepMeta,
    StepRecord,
    load_run,
    map_summary,
    rebuild_manifest,
)
from openpi_cam.cli import rebuild_manifest as rebuild_manifest_command

REPO = REPO_ROOT
CAMERAS = ("base_0_rgb", "left_wrist_0_rgb")
GEOMETRY = {
    "orig_h": 100,
    "orig_w": 200,
    "model_h": 224,
    "model_w": 224,
    "resized_h": 112,
    "resized_w": 224,
    "pad_top": 56,
    "pad_left": 0,
}


def make_record(
    i: int, *, connection: str = "c0", stack: bool = False, frames: bool = True, gradnorm: bool = True
) -> StepRecord:
    rng = np.random.default_rng(i)
    gradcam = {
        CAMERAS[0]: rng.random((3, 16, 16) if stack else (16, 16), dtype=np.float32),
        CAMERAS[1]: rng.normal(size=(16, 16)).astype(np.float32),
    }
    maps = {"gradcam": gradcam}
    if gradnorm:  # same shapes, different values
        maps["gradnorm"] = {c: np.abs(m[..., ::-1, :]) + 1.0 for c, m in gradcam.items()}
    meta = {
        "target": "all-action-tokens" if stack else "action-token",
        "token_ids": [int(t) for t in rng.integers(0, 2048, 3 if stack else 1)],
        "decode_steps": [0, 1, 2] if stack else [i % 7],
        "positions": [40, 41, 42] if stack else [40 + i % 7],
        "action_indices": None,
        "score": [1.0, 2.0, 3.5] if stack else np.float32(0.25 * i),
        "map_kinds": list(maps),
        "prompt": f"pick up the cube #{i} ü",
        "cameras": {
            c: {
                "obs_key": f"observation/{c}",
                "valid": c == CAMERAS[0],
                "grid": [16, 16],
                "span": [256 * k, 256 * k + 256],
                "geometry": GEOMETRY if c == CAMERAS[0] else None,
            }
            for k, c in enumerate(CAMERAS)
        },
        "malformed": None,
        "extra": {"target_box": [1, 2, 3, 4]},
    }
    inputs = {"output": rng.integers(0, 2048, 32).astype(np.int32), "state": rng.normal(size=8).astype(np.float32)}
    rec = StepRecord(connection=connection, step=i, timestamp=1_700_000_000.0 + i, maps=maps, inputs=inputs, meta=meta)
    if frames:
        rec.frames = {CAMERAS[0]: rng.integers(0, 256, (100, 200, 3), dtype=np.uint8)}
        rec.model_frames = {c: rng.integers(0, 256, (224, 224, 3), dtype=np.uint8) for c in CAMERAS}
    return rec


def new_logger(cam_dir: pathlib.Path, **kw) -> CAMLogger:
    return CAMLogger(cam_dir, run_config={"policy": "droid"}, checkpoint="gs://ckpt/pi0_fast", options={"t": 1}, **kw)


# What a subprocess needs on sys.path to import this module (and its `paths` import).
SUBPROCESS_PATH = [str(pathlib.Path(__file__).parent), str(REPO / "tests" / "support")]


def subprocess_env() -> dict[str, str]:
    """This checkout's sources first, whatever the venv's editable install points at."""
    return os.environ | {"PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")])}


def step_seqs(run_dir: pathlib.Path) -> list[int]:
    return sorted(int(p.stem) for p in (run_dir / "steps").glob("*.npz"))


# The step-file key prefix of each map kind, as docs/FORMAT.md spells it.
KEY_PREFIX = {"gradcam": "cam/", "gradnorm": "gradnorm/"}


def test_step_meta_keeps_unknown_fields_and_reads_older_schemas():
    """Fields this reader does not know (a newer writer's) survive a read and write back; a schema 1 step (its
    `malformed_reason`, no `map_kinds`, cameras without `obs_key`) reads with defaults for what it lacks."""
    written = {
        "target": "action",
        "action_index": [2, 1],
        "future_field": {"x": 1},
        "score": 0.5,
        "map_kinds": ["ig"],
        "prompt": "p",
        "cameras": {
            "a": {"obs_key": "img", "valid": True, "grid": [4, 4], "span": [0, 16], "geometry": None, "new": 2}
        },
        "malformed": None,
        "explain_ms": 1.5,
        "extra": {},
        "extra_arrays": [],
    }
    meta = StepMeta.from_json(written)
    assert meta.details == {"action_index": [2, 1], "future_field": {"x": 1}} and meta.action_index == (2, 1)
    assert meta.cameras["a"].details == {"new": 2} and meta.to_json() == written
    assert StepMeta.from_json(meta.to_json()) == meta
    old = StepMeta.from_json(
        {"target": "action-token", "malformed_reason": "no_action_prefix", "cameras": {"a": {"valid": False}}}
    )
    assert old.malformed == "no_action_prefix" and old.map_kinds is None and old.details == {}
    assert old.cameras["a"].obs_key is None and not old.cameras["a"].valid and old.score is None


def test_round_trip_with_numpy_alone(tmp_path):
    lg = new_logger(tmp_path, compress=True)
    # a record without gradient-norm maps writes no gradnorm/ keys
    records = [make_record(0), make_record(1, stack=True), make_record(2, frames=False, gradnorm=False)]
    assert [lg.log_step(r) for r in records] == [True, True, True]
    lg.close()

    run_info = json.loads((lg.run_dir / "run.json").read_text())
    assert SCHEMA_VERSION == 3
    assert run_info["schema_version"] == 3 and run_info["run_id"] == lg.run_dir.name
    assert run_info["config"] == {"policy": "droid"} and run_info["checkpoint"] == "gs://ckpt/pi0_fast"
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", run_info["started_at"])
    assert re.fullmatch(r"\d{8}-\d{6}-[0-9a-f]{6}", lg.run_dir.name)

    for seq, rec in enumerate(records):
        with np.load(lg.run_dir / "steps" / f"{seq:08d}.npz", allow_pickle=False) as z:
            meta = json.loads(z["meta"].item())
            assert z["meta"].shape == () and z["meta"].dtype.kind == "U"
            for kind, maps in rec.maps.items():
                for c, m in maps.items():
                    assert z[KEY_PREFIX[kind] + c].dtype == np.float32
                    np.testing.assert_array_equal(z[KEY_PREFIX[kind] + c], m)
            for c, frame in rec.frames.items():
                assert z[f"frame/{c}"].dtype == np.uint8
                np.testing.assert_array_equal(z[f"frame/{c}"], frame)
            for c, frame in rec.model_frames.items():
                np.testing.assert_array_equal(z[f"frame_model/{c}"], frame)
            for name, value in rec.inputs.items():
                assert z[f"input/{name}"].dtype == value.dtype
                np.testing.assert_array_equal(z[f"input/{name}"], value)
            assert sorted(z.files) == sorted(
                ["meta"]
                + [KEY_PREFIX[kind] + c for kind, maps in rec.maps.items() for c in maps]
                + [f"frame/{c}" for c in rec.frames]
                + [f"frame_model/{c}" for c in rec.model_frames]
                + [f"input/{name}" for name in rec.inputs]
            )
        expected = json.loads(json.dumps(rec.meta, default=lambda v: v.item()))
        assert (
            meta
            == {
                "schema_version": 3,
                "run_id": lg.run_dir.name,
                "seq": seq,
                "connection": "c0",
                "step": seq,
                "timestamp": 1_700_000_000.0 + seq,
            }
            | expected
        )
        assert list(meta["cameras"]) == list(CAMERAS)  # model order survives

    for load_arrays in (True, False):
        run = load_run(lg.run_dir, load_arrays=load_arrays)
        assert [s.seq for s in run.steps] == [0, 1, 2] and not run.problems
        assert run.run_info == run_info
        for step, rec in zip(run.steps, records, strict=True):
            assert step.meta.prompt == rec.meta["prompt"]
            # The typed metadata gives the stored JSON back (nothing lost; the fields this record left out read as
            # their defaults), and each field reads as its type.
            with np.load(step.file, allow_pickle=False) as z:
                stored = json.loads(z["meta"].item())
            assert step.meta.to_json() == stored | {"explain_ms": None, "extra_arrays": []}
            base, wrist = step.meta.cameras[CAMERAS[0]], step.meta.cameras[CAMERAS[1]]
            assert (base.obs_key, base.valid, base.grid) == (f"observation/{CAMERAS[0]}", True, (16, 16))
            assert base.geometry == GEOMETRY
            assert not wrist.valid and wrist.span == (256, 512) and wrist.geometry is None
            assert step.meta.token_ids == tuple(rec.meta["token_ids"])
            assert step.meta.decode_steps == tuple(rec.meta["decode_steps"]) and step.meta.action_indices is None
            assert step.meta.details["positions"] == rec.meta["positions"]
            assert (step.meta.seq, step.meta.connection, step.meta.step) == (step.seq, "c0", step.seq)
            assert step.meta.extra == {"target_box": [1, 2, 3, 4]} and step.meta.check is None
            assert step.file == lg.run_dir / "steps" / f"{step.seq:08d}.npz"
            assert step.map_kinds == tuple(rec.maps) and set(step.frames) == set(rec.frames)
            for kind, maps in rec.maps.items():
                assert set(step.maps_of(kind)) == set(CAMERAS)
                for c, m in maps.items():
                    np.testing.assert_array_equal(step.maps_of(kind)[c], m)
            for c in rec.model_frames:
                np.testing.assert_array_equal(step.model_frames[c], rec.model_frames[c])
            for name, value in rec.inputs.items():
                np.testing.assert_array_equal(step.inputs[name], value)
        assert run.steps[2].maps_of("gradnorm") == {}


def test_the_last_step_survives_close(tmp_path):
    """Every accepted step is on disk after `close()`, the last one included: its step file, its index line and its
    manifest entry (the periodic manifest never covers it here, so only close() can have listed it)."""
    lg = new_logger(tmp_path, manifest_every=100)
    records = [make_record(i, frames=False) for i in range(3)]
    assert all(lg.log_step(r) for r in records)
    lg.close()
    run_dir = lg.run_dir
    assert step_seqs(run_dir) == [0, 1, 2]
    index = [json.loads(line)["seq"] for line in (run_dir / "index.jsonl").read_text().splitlines()]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert index == [0, 1, 2] and [e["seq"] for e in manifest["steps"]] == [0, 1, 2]
    assert manifest["num_steps"] == 3 and manifest["counters"]["logger"]["steps_logged"] == 3 and manifest["closed"]
    last = load_run(run_dir).steps[-1]
    assert last.meta.step == 2
    np.testing.assert_array_equal(last.maps_of("gradcam")[CAMERAS[1]], records[2].maps["gradcam"][CAMERAS[1]])


def test_manifest_and_index_summaries_match_numpy(tmp_path):
    lg = new_logger(tmp_path, manifest_every=2, compress=False)
    records = [make_record(i, stack=i == 1, connection=f"c{i % 2}") for i in range(3)]
    lg.log_step(records[0])
    assert not (lg.run_dir / "manifest.json").exists()
    lg.log_step(records[1])
    periodic = json.loads((lg.run_dir / "manifest.json").read_text())
    assert periodic["num_steps"] == 2 and periodic["closed"] is False
    lg.log_step(records[2])
    assert json.loads((lg.run_dir / "manifest.json").read_text())["num_steps"] == 2  # not rewritten every step
    lg.set_external_counters({"requests": 7, "dropped": {"queue_full": 1}})
    lg.close()

    manifest = json.loads((lg.run_dir / "manifest.json").read_text())
    index = [json.loads(line) for line in (lg.run_dir / "index.jsonl").read_text().splitlines()]
    assert manifest["steps"] == index and manifest["num_steps"] == 3 and manifest["closed"] is True
    assert {k: manifest[k] for k in ("schema_version", "run_id", "config", "checkpoint", "options", "started_at")} == (
        json.loads((lg.run_dir / "run.json").read_text())
    )
    assert manifest["counters"]["external"] == {"requests": 7, "dropped": {"queue_full": 1}}
    logger_counters = manifest["counters"]["logger"]
    assert logger_counters == lg.counters
    assert logger_counters["steps_logged"] == 3 and logger_counters["io_errors"] == {}
    on_disk = (
        sum(p.stat().st_size for p in (lg.run_dir / "steps").iterdir()) + (lg.run_dir / "index.jsonl").stat().st_size
    )
    assert logger_counters["bytes_written"] == on_disk

    for entry, rec in zip(index, records, strict=True):
        assert entry["file"] == f"steps/{entry['seq']:08d}.npz"
        assert (entry["connection"], entry["step"], entry["target"]) == (rec.connection, rec.step, rec.meta["target"])
        assert entry["malformed"] is None and entry["summary_kind"] == "gradcam"
        for camera, m in rec.maps["gradcam"].items():
            flat = m.mean(axis=0) if m.ndim == 3 else m
            summary = entry["summary"][camera]
            assert summary["max"] == pytest.approx(float(flat.max()))
            assert summary["mean"] == pytest.approx(float(flat.mean()), rel=1e-5)
            assert summary["argmax"] == list(np.unravel_index(np.argmax(flat), flat.shape))
    assert load_run(lg.run_dir).manifest == manifest  # current manifest is used as is


def test_map_summary_edge_cases():
    m = np.zeros((4, 5), np.float32)
    m[2, 3] = 5.0
    m[0, 0] = np.nan
    assert map_summary(m) == {"max": 5.0, "mean": pytest.approx(5.0 / 19), "argmax": [2, 3]}
    stack = np.zeros((2, 3, 3), np.float32)
    stack[0, 0, 1], stack[1, 2, 2] = 4.0, 6.0  # the mean over T peaks at (2, 2)
    assert map_summary(stack)["argmax"] == [2, 2] and map_summary(stack)["max"] == 3.0
    assert map_summary(np.full((2, 2), np.nan)) == {"max": None, "mean": None, "argmax": None}
    with pytest.raises(ValueError):
        map_summary(np.zeros(5))


def test_never_overwrites_earlier_runs(tmp_path, monkeypatch):
    loggers = [new_logger(tmp_path) for _ in range(10)]
    assert len({lg.run_dir for lg in loggers}) == 10
    assert {p.parent for p in tmp_path.glob(f"*/{RUN_JSON}")} == {lg.run_dir for lg in loggers}

    # Force the random suffix to collide with existing directories for the current and next seconds.
    now = time.time()
    taken = [tmp_path / f"{time.strftime('%Y%m%d-%H%M%S', time.gmtime(now + d))}-aaaaaa" for d in range(3)]
    for d in taken:
        d.mkdir()
        (d / "run.json").write_text('{"precious": true}')
    real = logger_mod.secrets.token_hex
    calls = iter(["aaaaaa"])
    monkeypatch.setattr(logger_mod.secrets, "token_hex", lambda n=None: next(calls, None) or real(n))
    lg = new_logger(tmp_path)
    assert lg.run_dir not in taken and lg.run_dir.parent == tmp_path
    assert next(calls, None) is None  # the colliding suffix was tried first
    assert lg.run_dir.name[:15] in {d.name[:15] for d in taken}  # so the first name tried was taken
    for d in taken:
        assert (d / "run.json").read_text() == '{"precious": true}' and sorted(os.listdir(d)) == ["run.json"]


def test_caps_are_counted(tmp_path):
    lg = new_logger(tmp_path / "steps_cap", max_steps=3)
    assert [lg.log_step(make_record(i)) for i in range(5)] == [True, True, True, False, False]
    assert lg.counters["steps_logged"] == 3 and lg.counters["steps_skipped_cap"] == 2
    assert step_seqs(lg.run_dir) == [0, 1, 2]
    lg.close()
    assert json.loads((lg.run_dir / "manifest.json").read_text())["counters"]["logger"]["steps_skipped_cap"] == 2

    probe = new_logger(tmp_path / "probe", compress=False)
    probe.log_step(make_record(0))
    one_step = probe.counters["bytes_written"]
    lg = new_logger(tmp_path / "bytes_cap", max_bytes=int(2.5 * one_step), compress=False)
    assert [lg.log_step(make_record(i)) for i in range(4)] == [True, True, False, False]
    # a small step after the cap is still skipped: a capped run is a prefix of what was offered
    assert not lg.log_step(make_record(9, frames=False))
    c = lg.counters
    assert c["steps_logged"] == 2 and c["steps_skipped_cap"] == 3 and c["bytes_written"] <= 2.5 * one_step
    assert step_seqs(lg.run_dir) == [0, 1]


def _compressible(i: int) -> StepRecord:
    """A step whose frames are flat colour: compression shrinks it about 100-fold."""
    rec = make_record(i)
    rec.frames = {c: np.full_like(f, 7 * i % 256) for c, f in rec.frames.items()}
    rec.model_frames = {c: np.full_like(f, 3 * i % 256) for c, f in rec.model_frames.items()}
    return rec


def test_byte_cap_counts_the_compressed_bytes_written(tmp_path):
    """With compression on, `max_bytes` bounds what lands on disk: the compressed step files plus index lines."""
    raw = new_logger(tmp_path / "raw", compress=False)
    assert raw.log_step(_compressible(0))
    packed = new_logger(tmp_path / "packed", compress=True)
    assert packed.log_step(_compressible(0))
    uncompressed, compressed = raw.counters["bytes_written"], packed.counters["bytes_written"]
    assert compressed * 20 < uncompressed  # a cap on uncompressed bytes could not hold even one of these steps

    cap = int(3.5 * compressed)  # three steps fit, the fourth does not (they differ in size by a few bytes only)
    lg = new_logger(tmp_path / "capped", compress=True, max_bytes=cap)
    assert [lg.log_step(_compressible(i)) for i in range(6)] == [True] * 3 + [False] * 3
    lg.close()
    on_disk = sum(p.stat().st_size for p in (lg.run_dir / "steps").iterdir())
    on_disk += (lg.run_dir / "index.jsonl").stat().st_size
    c = lg.counters
    assert c["bytes_written"] == on_disk <= cap
    assert c["steps_logged"] == 3 and c["steps_skipped_cap"] == 3 and step_seqs(lg.run_dir) == [0, 1, 2]
    with np.load(lg.run_dir / "steps" / "00000000.npz") as z:  # the files really are compressed
        assert all(info.compress_type == 8 for info in z.zip.infolist())


def test_unwritable_steps_dir_is_counted_not_raised(tmp_path, caplog):
    lg = new_logger(tmp_path)
    assert lg.log_step(make_record(0)) and lg.log_step(make_record(1))
    steps, aside = lg.run_dir / "steps", lg.run_dir / "steps.aside"
    steps.rename(aside)
    steps.write_bytes(b"not a directory")  # a real ENOTDIR, even for root
    with caplog.at_level(logging.WARNING, logger="openpi_cam.cam.logger"):
        assert not lg.log_step(make_record(2))
        assert not lg.log_step(make_record(3))
    assert lg.counters["io_errors"] == {"not_a_directory": 2} and lg.counters["steps_skipped_io"] == 2
    assert sum("not_a_directory" in r.getMessage() for r in caplog.records) == 1  # logged once per kind

    steps.unlink()
    aside.rename(steps)
    assert lg.log_step(make_record(4))
    assert step_seqs(lg.run_dir) == [0, 1, 2]  # the failed steps did not use up a seq
    assert load_run(lg.run_dir).steps[2].meta.step == 4

    (lg.run_dir / "manifest.json").mkdir()  # the final manifest cannot replace a directory
    lg.close()
    assert lg.counters["io_errors"] == {"not_a_directory": 2, "is_a_directory": 1}
    assert lg.counters["steps_logged"] == 3 and not lg.log_step(make_record(5))
    assert lg.counters["steps_skipped_closed"] == 1


def test_index_write_failure_keeps_step_and_seq(tmp_path):
    lg = new_logger(tmp_path)
    (lg.run_dir / "index.jsonl").mkdir()  # the index cannot be opened for appending
    assert lg.log_step(make_record(0)) and lg.log_step(make_record(1))  # step files are the source of truth
    assert lg.counters["io_errors"] == {"is_a_directory": 2}
    (lg.run_dir / "index.jsonl").rmdir()
    assert lg.log_step(make_record(2))
    lg.close()
    lines = (lg.run_dir / "index.jsonl").read_text().splitlines()
    assert [json.loads(line)["seq"] for line in lines if line] == [2]
    assert step_seqs(lg.run_dir) == [0, 1, 2]
    assert [e["seq"] for e in json.loads((lg.run_dir / "manifest.json").read_text())["steps"]] == [0, 1, 2]
    assert [e["seq"] for e in rebuild_manifest(lg.run_dir)["steps"]] == [0, 1, 2]


NOBODY = 65534

# Run as root: the logger is created as root, then the process takes the effective ids of `nobody`, for whom steps/
# (root's, 0o755) is read-only while the run directory (given to nobody) stays writable; root comes back afterwards
# (the real and saved ids stay 0). Effective capabilities are dropped with the effective uid, so the kernel checks
# permissions for real. A subprocess keeps the id switch away from pytest's own threads.
UNPRIVILEGED_WRITER = """
import json, os, pathlib, sys
sys.path[:0] = {tests!r}
from test_logger import make_record, new_logger
cam_dir = pathlib.Path({cam_dir!r})
lg = new_logger(cam_dir)
ok = [lg.log_step(make_record(0))]
os.chown(lg.run_dir, {nobody}, {nobody})
os.chmod(lg.run_dir / "steps", 0o755)
os.setegid({nobody})
os.seteuid({nobody})
probe = lg.run_dir / "nobody-can-write-here"
probe.write_text("x")  # the run directory is reachable and writable: only steps/ refuses
probe.unlink()
ok.append(lg.log_step(make_record(1)))
os.seteuid(0)
os.setegid(0)
ok.append(lg.log_step(make_record(2)))
lg.close()
print(json.dumps({{"ok": ok, "counters": lg.counters, "run_dir": str(lg.run_dir)}}))
"""


def test_permission_denied_steps_dir_is_counted(tmp_path):
    if os.geteuid() != 0:  # an ordinary user: a read-only directory refuses writes by itself
        lg = new_logger(tmp_path)
        (lg.run_dir / "steps").chmod(0o500)
        try:
            ok = [True, lg.log_step(make_record(1))]
        finally:
            (lg.run_dir / "steps").chmod(0o700)
        ok.append(lg.log_step(make_record(2)))
        counters, run_dir = lg.counters, lg.run_dir
    else:
        # pytest's tmp_path sits under a 0o700 directory nobody cannot enter; this one (in /tmp) is world-readable.
        cam_dir = pathlib.Path(tempfile.mkdtemp(prefix="cam-permissions-"))
        cam_dir.chmod(0o755)
        try:
            script = UNPRIVILEGED_WRITER.format(tests=SUBPROCESS_PATH, cam_dir=str(cam_dir), nobody=NOBODY)
            proc = subprocess.run(
                [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=subprocess_env()
            )
            assert proc.returncode == 0, proc.stderr[-3000:]
            out = json.loads(proc.stdout.strip().splitlines()[-1])
            ok, counters, run_dir = out["ok"], out["counters"], pathlib.Path(out["run_dir"])
            shutil.copytree(run_dir, tmp_path / run_dir.name)
            run_dir = tmp_path / run_dir.name
        finally:
            shutil.rmtree(cam_dir)
    assert ok[1:] == [False, True]
    assert counters["io_errors"] == {"permission_denied": 1} and counters["steps_skipped_io"] == 1
    # the refused step used up no seq; the run reads back whole
    run = load_run(run_dir)
    assert [(s.seq, s.meta.step) for s in run.steps][-1] == (len(run.steps) - 1, 2)


def test_uncreatable_run_dir_raises_clear_oserror(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OSError, match="cannot create the CAM directory"):
        new_logger(blocker / "cam")


def test_wrong_types_raise(tmp_path):
    lg = new_logger(tmp_path)
    rec = make_record(0)
    rec.frames = {CAMERAS[0]: rec.frames[CAMERAS[0]].astype(np.float32)}
    with pytest.raises(TypeError, match="uint8"):
        lg.log_step(rec)
    with pytest.raises(ValueError, match="must not set"):
        lg.log_step(StepRecord("c", 0, 0.0, {"gradcam": {"a": np.zeros((2, 2))}}, meta={"seq": 3}))
    with pytest.raises(ValueError, match="Hp, Wp"):
        lg.log_step(StepRecord("c", 0, 0.0, {"gradcam": {"a": np.zeros(4)}}))
    with pytest.raises(ValueError, match="gradnorm map 'a' must be"):
        lg.log_step(StepRecord("c", 0, 0.0, {"gradcam": {"a": np.zeros((2, 2))}, "gradnorm": {"a": np.zeros(4)}}))
    with pytest.raises(ValueError, match="unknown map kind 'saliency'"):
        lg.log_step(StepRecord("c", 0, 0.0, {"saliency": {"a": np.zeros((2, 2))}}))
    with pytest.raises(TypeError, match="must be a dict"):
        lg.log_step(StepRecord("c", 0, 0.0, {"gradcam": np.zeros((2, 2))}))
    assert lg.counters["steps_logged"] == 0 and step_seqs(lg.run_dir) == []


def test_reader_tolerates_crash_debris(tmp_path):
    lg = new_logger(tmp_path, compress=False)
    records = [make_record(i) for i in range(4)]
    for rec in records:
        lg.log_step(rec)
    lg.close()
    run_dir = lg.run_dir
    original = json.loads((run_dir / "manifest.json").read_text())
    # index line for seq 2 lost, a truncated last line, stray temporary files, stale manifest
    lines = (run_dir / "index.jsonl").read_text().splitlines()
    (run_dir / "index.jsonl").write_text("\n".join(lines[:2] + lines[3:]) + '\n{"seq": 4, "file": "ste')
    (run_dir / "steps" / "00000004.npz.123-abcd.tmp").write_bytes(b"PK\x03\x04 half a zip")
    (run_dir / "manifest.json.99-ffff.tmp").write_text("{")
    stale = dict(original, steps=original["steps"][:1], num_steps=1)
    (run_dir / "manifest.json").write_text(json.dumps(stale))

    run = load_run(run_dir, load_arrays=False)
    assert [s.seq for s in run.steps] == [0, 1, 2, 3] and not run.problems
    assert [e["seq"] for e in run.manifest["steps"]] == [0, 1, 2, 3]
    assert run.manifest["steps"][2]["summary"] == original["steps"][2]["summary"]  # recomputed from the maps
    assert run.manifest["counters"] == original["counters"]
    assert json.loads((run_dir / "manifest.json").read_text()) == stale  # load_run never writes

    (run_dir / "manifest.json").unlink()
    rebuilt = rebuild_manifest(run_dir)
    assert json.loads((run_dir / "manifest.json").read_text()) == rebuilt
    assert [e["seq"] for e in rebuilt["steps"]] == [0, 1, 2, 3] and rebuilt["counters"] == {}
    assert [e["summary"] for e in rebuilt["steps"]] == [e["summary"] for e in original["steps"]]


WRITER = """
import sys, numpy as np
sys.path[:0] = {tests!r}
from test_logger import new_logger, make_record
import pathlib
lg = new_logger(pathlib.Path({cam_dir!r}), manifest_every=5, compress=False)
# a large constant frame makes the file write a big share of each step, so the kill often lands inside one
big = np.random.default_rng(0).integers(0, 256, (1024, 1024, 3), dtype=np.uint8)
print(lg.run_dir, flush=True)
i = 0
while True:
    rec = make_record(i)
    rec.model_frames["big"] = big
    assert lg.log_step(rec)
    print(i, flush=True)
    i += 1
"""


def test_kill_9_mid_run_loses_no_completed_step(tmp_path, capsys):
    cam_dir = tmp_path / "cam"
    script = tmp_path / "writer.py"
    script.write_text(WRITER.format(tests=SUBPROCESS_PATH, cam_dir=str(cam_dir)))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=subprocess_env())
    try:
        run_dir = pathlib.Path(proc.stdout.readline().strip())
        completed = -1
        while completed < 12:
            line = proc.stdout.readline()
            assert line, "writer exited early"
            completed = int(line)
        # kill as soon as a step file is being written, so the kill usually lands inside a write
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and not any(n.endswith(".tmp") for n in os.listdir(run_dir / "steps")):
            pass
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL

    run = load_run(run_dir)
    seqs = [s.seq for s in run.steps]
    assert seqs == list(range(len(seqs))) and len(seqs) >= completed + 1 and not run.problems
    for step in run.steps:
        rec = make_record(step.seq)
        assert step.meta.step == step.seq
        np.testing.assert_array_equal(step.maps_of("gradcam")[CAMERAS[1]], rec.maps["gradcam"][CAMERAS[1]])
        np.testing.assert_array_equal(step.maps_of("gradnorm")[CAMERAS[0]], rec.maps["gradnorm"][CAMERAS[0]])
        np.testing.assert_array_equal(step.frames[CAMERAS[0]], rec.frames[CAMERAS[0]])
    assert [e["seq"] for e in run.manifest["steps"]] == seqs

    old = json.loads((run_dir / "manifest.json").read_text())
    assert old["closed"] is False and old["num_steps"] % 5 == 0 and old["num_steps"] <= len(seqs)
    assert rebuild_manifest_command.main(run_dir) == 0
    assert f"{len(seqs)} steps" in capsys.readouterr().out
    rebuilt = json.loads((run_dir / "manifest.json").read_text())
    assert [e["seq"] for e in rebuilt["steps"]] == seqs and rebuilt["num_steps"] == len(seqs)
    assert rebuilt["counters"] == old["counters"] and "rebuilt_at" in rebuilt
    for entry in rebuilt["steps"]:
        flat = make_record(entry["seq"]).maps["gradcam"][CAMERAS[1]]
        assert entry["summary"][CAMERAS[1]]["argmax"] == list(np.unravel_index(np.argmax(flat), flat.shape))


def test_two_threads(tmp_path):
    lg = new_logger(tmp_path, manifest_every=7)
    results: dict[str, list[bool]] = {"a": [], "b": []}

    def work(connection: str) -> None:
        for i in range(20):
            results[connection].append(lg.log_step(make_record(i, connection=connection, frames=False)))

    threads = [threading.Thread(target=work, args=(c,)) for c in results]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lg.close()
    assert all(results["a"]) and all(results["b"]) and lg.counters["steps_logged"] == 40
    run = load_run(lg.run_dir)
    assert [s.seq for s in run.steps] == list(range(40))
    index = [json.loads(line) for line in (lg.run_dir / "index.jsonl").read_text().splitlines()]
    assert [e["seq"] for e in index] == list(range(40)) and run.manifest["steps"] == index
    for connection in results:
        steps = [s for s in run.steps if s.meta.connection == connection]
        assert [s.meta.step for s in steps] == list(range(20))  # each thread's order is kept
        for s in steps:
            want = make_record(s.meta.step, connection=connection, frames=False).maps["gradcam"][CAMERAS[0]]
            np.testing.assert_array_equal(s.maps_of("gradcam")[CAMERAS[0]], want)


def test_cli_and_docs_example(tmp_path, capsys):
    lg = new_logger(tmp_path)
    rec = make_record(0)
    hot = np.zeros((16, 16), np.float32)
    hot[6, 3] = 1.0  # model rows [84, 98), cols [42, 56)
    rec.maps["gradcam"][CAMERAS[0]] = hot
    lg.log_step(rec)
    lg.close()

    for name in ("rebuild-manifest", "cam-index"):  # the command and its earlier name
        cli.main([name, str(lg.run_dir)])
        out = capsys.readouterr().out
        assert re.search(r": 1 steps \(seq 0\.\.0\), cameras \['base_0_rgb', 'left_wrist_0_rgb'\]", out)
    assert rebuild_manifest_command.main(tmp_path / "missing") == 1

    # the NumPy-only example in docs/FORMAT.md runs as written and its geometry recipe is right
    doc = (REPO / "docs" / "FORMAT.md").read_text()
    example = re.search(r"## Reading with NumPy alone\n\n```python\n(.*?)```", doc, re.S).group(1)
    scope = {"run_dir": str(lg.run_dir)}
    exec(compile(example, "FORMAT.md", "exec"), scope)
    assert scope["meta"]["seq"] == 0 and scope["arrays"][f"frame/{CAMERAS[0]}"].shape == (100, 200, 3)
    heat = scope["map_on_original"](hot, GEOMETRY)
    assert heat.shape == (100, 200)
    rows, cols = np.nonzero(heat)
    # original row Y sits at model row (Y + 0.5) * 112 / 100 + 56, column X at (X + 0.5) * 224 / 200
    assert sorted(set(rows)) == list(range(25, 37)) and sorted(set(cols)) == list(range(37, 50))


def test_a_run_without_its_steps_folder_reads_as_empty(tmp_path):
    lg = new_logger(tmp_path)
    shutil.rmtree(lg.run_dir / "steps")
    assert load_run(lg.run_dir).steps == []


def test_cam_extra_arrays_are_stored_as_arrays_within_byte_limits(tmp_path):
    """Numeric `cam_extra/` arrays go to the step file as `extra/<key>` with their dtype, byte order and shape; other
    values (and arrays under keys unfit for a file member name) stay JSON in meta. Limits count the bytes as stored:
    a 16,000-element int8 array passes a 16 KiB per-value limit that its JSON text (~3 bytes per element) would not."""
    from openpi_cam.cam.records import bounded_extra, split_extra_values

    joint = np.arange(7, dtype=">f8") / 3  # big-endian, as some clients send
    depth = np.ones((125, 128), np.int8)
    extra = {"obs/joint": joint, "depth": depth, "note": "hi", "scalar": np.float32(0.5), "../up": np.arange(3)}
    kept, dropped = bounded_extra(extra, max_value_bytes=16 * 1024, max_total_bytes=64 * 1024)
    assert dropped == [] and set(kept) == set(extra)
    assert bounded_extra(extra, max_value_bytes=8 * 1024, max_total_bytes=64 * 1024)[1] == ["depth"]
    assert bounded_extra(extra, max_value_bytes=16 * 1024, max_total_bytes=16_090)[1] == ["../up"]  # in key order
    values, arrays = split_extra_values(kept)
    assert set(arrays) == {"obs/joint", "depth"}
    assert values == {"note": "hi", "scalar": 0.5, "../up": [0, 1, 2]}

    lg = new_logger(tmp_path)
    record = make_record(0)
    record.meta["extra"], record.meta["extra_arrays"] = values, sorted(arrays)
    record.extra_arrays = arrays
    assert lg.log_step(record)
    lg.close()
    (step,) = load_run(lg.run_dir, load_arrays=False).steps
    assert step.meta.extra == values
    for key, sent in arrays.items():
        stored = step.extra[key]
        assert stored.dtype == sent.dtype and stored.shape == sent.shape
        np.testing.assert_array_equal(stored, sent)
    with np.load(step.file) as z:
        assert {"extra/obs/joint", "extra/depth"} <= set(z.files)
