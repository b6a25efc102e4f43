"""Attention statistics of real CAM run directories (written by CAMLogger) against direct NumPy/SciPy computations.
The statistics describe one kind of map; the run's other kind holds different maps, so mixing them up shows."""

from __future__ import annotations

import csv
import io
import json
import math
import pathlib
import sys

import numpy as np
import pytest
import scipy.stats

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.run_format import StepRecord, load_run
from openpi_cam.cli import main as cli_main
from openpi_cam.viz.stats import MissingMaps, aggregate, compute_stats, to_rows, view_steps, write_table

CAMS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
GRID = (4, 5)


def _meta(valid: dict[str, bool], score: float | list[float] = 1.0) -> dict:
    return {
        "target": "action-token",
        "token_ids": [7],
        "decode_steps": [0],
        "positions": [100],
        "action_indices": None,
        "score": score,
        "prompt": "pick",
        "cameras": {
            c: {"obs_key": c, "valid": valid[c], "grid": list(GRID), "span": [i * 20, i * 20 + 20], "geometry": None}
            for i, c in enumerate(CAMS)
        },
        "extra": {},
    }


@pytest.fixture
def random_run(tmp_path: pathlib.Path) -> tuple[pathlib.Path, list[dict]]:
    """Two interleaved connections; right wrist masked on the first connection; a multi-token map; a zero step."""
    rng = np.random.default_rng(0)
    records = []
    with CAMLogger(tmp_path / "cam", run_config={}, checkpoint="ckpt", options={}) as logger:
        for i in range(10):
            conn = "a" if i % 3 else "b"
            valid = {c: not (conn == "a" and c == "right_wrist_0_rgb") for c in CAMS}
            maps = {c: rng.random(GRID).astype(np.float32) * rng.integers(0, 2, GRID) for c in CAMS}
            if i == 4:
                maps["base_0_rgb"] = rng.random((3, *GRID)).astype(np.float32)
            if i == 7:
                maps = {c: np.zeros(GRID, np.float32) for c in CAMS}
            if i in (4, 5):  # consecutive steps of connection "a" with the same left-wrist peak
                maps["left_wrist_0_rgb"] = np.zeros(GRID, np.float32)
                maps["left_wrist_0_rgb"][2, 3] = 1.0
            records.append({"conn": conn, "maps": maps, "valid": valid})
            # the Grad-CAM maps beside them peak elsewhere (flipped), so statistics of the wrong kind differ
            kinds = {"gradnorm": maps, "gradcam": {c: np.flip(m).copy() for c, m in maps.items()}}
            logger.log_step(StepRecord(conn, i, 1000.0 + i, kinds, meta=_meta(valid, score=[0.5, 1.5])))
    return logger.run_dir, records


def _stats(run_dir: pathlib.Path, kind: str = "gradnorm") -> list:
    return compute_stats(view_steps(load_run(run_dir, load_arrays=False).steps, kind))


def test_stats_match_direct_numpy(random_run):
    run_dir, records = random_run
    stats = _stats(run_dir)
    assert [st.seq for st in stats] == list(range(len(records)))
    last_peak: dict[tuple[str, str], tuple[int, int] | None] = {}
    for st, rec in zip(stats, records, strict=True):
        maps = {c: np.asarray(m, np.float64) for c, m in rec["maps"].items()}
        maps = {c: m.mean(axis=0) if m.ndim == 3 else m for c, m in maps.items()}
        total = sum(maps[c].sum() for c in CAMS if rec["valid"][c])
        assert st.score == pytest.approx(1.0)
        for c in CAMS:
            cs = st.cameras[c]
            if not rec["valid"][c]:
                assert not cs.valid and cs.share == 0 and cs.peak is None
                last_peak[(rec["conn"], c)] = None
                continue
            m = maps[c]
            assert cs.share == pytest.approx(m.sum() / total if total > 0 else 0.0)
            if m.sum() > 0:
                assert cs.entropy == pytest.approx(scipy.stats.entropy(m.ravel()))
                assert cs.entropy_norm == pytest.approx(scipy.stats.entropy(m.ravel()) / math.log(m.size))
                peak = np.unravel_index(np.argmax(m), m.shape)
                assert cs.peak == (int(peak[0]), int(peak[1]))
                assert cs.peak_value == pytest.approx(m.max())
            else:
                assert cs.peak is None and math.isnan(cs.entropy)
            prev = last_peak.get((rec["conn"], c))
            if prev is not None and cs.peak is not None:
                shift = math.dist(prev, cs.peak)
                assert cs.peak_shift == pytest.approx(shift)
                assert cs.peak_stayed == (shift == 0)
            else:
                assert cs.peak_stayed is None and math.isnan(cs.peak_shift)
            last_peak[(rec["conn"], c)] = cs.peak
        shares = sum(cs.share for cs in st.cameras.values())
        assert shares == pytest.approx(1.0 if total > 0 else 0.0)
    assert stats[5].cameras["left_wrist_0_rgb"].peak_stayed is True
    assert stats[7].dominant is None
    assert stats[8].cameras["left_wrist_0_rgb"].peak_stayed is None  # the step before it had no mass


def test_rows_and_aggregates(random_run):
    run_dir, records = random_run
    stats = _stats(run_dir)
    rows = to_rows(stats)
    assert len(rows) == len(records)
    for row, st in zip(rows, stats, strict=True):
        assert row["seq"] == st.seq and row["connection"] == st.connection
        for c in CAMS:
            assert row[f"{c}/share"] == st.cameras[c].share
            peak = st.cameras[c].peak
            assert (row[f"{c}/peak_row"], row[f"{c}/peak_col"]) == (peak if peak else (None, None))
    summary = aggregate(stats)
    assert summary["steps"] == len(records) and summary["connections"] == 2
    # Expected values from the logged maps with NumPy: per step the valid cameras' mass shares, the dominant camera
    # (largest share; none when the step has no mass), per camera the mean share over the steps where it is valid.
    expected_shares, expected_dominant = [], []
    for rec in records:
        mass = {c: np.asarray(m, np.float64) for c, m in rec["maps"].items()}
        mass = {c: (m.mean(axis=0) if m.ndim == 3 else m).sum() if rec["valid"][c] else 0.0 for c, m in mass.items()}
        total = sum(mass.values())
        expected_shares.append({c: v / total if total > 0 else 0.0 for c, v in mass.items()})
        expected_dominant.append(max(mass, key=mass.get) if total > 0 else None)
    for c in CAMS:
        agg = summary["cameras"][c]
        valid_steps = [i for i, rec in enumerate(records) if rec["valid"][c]]
        assert agg["valid_steps"] == len(valid_steps)
        assert agg["mean_share"] == pytest.approx(np.mean([expected_shares[i][c] for i in valid_steps]))
        assert agg["dominant_steps"] == expected_dominant.count(c)
    assert [st.dominant for st in stats] == expected_dominant
    assert expected_dominant.count(None) == 1  # the all-zero step


def test_formats_round_trip(random_run):
    run_dir, records = random_run
    stats = _stats(run_dir)
    rows, summary = to_rows(stats), aggregate(stats)

    parsed = list(csv.DictReader(io.StringIO(write_table(rows, "csv", summary).decode())))
    assert [int(r["seq"]) for r in parsed] == [r["seq"] for r in rows]
    assert float(parsed[2]["base_0_rgb/share"]) == pytest.approx(rows[2]["base_0_rgb/share"])

    doc = json.loads(write_table(rows, "json", summary))
    assert doc["steps"] == json.loads(json.dumps(rows)) and doc["summary"]["steps"] == len(records)

    import pyarrow as pa  # a dev dependency: its absence is an error here, not a skip
    import pyarrow.parquet as pq

    table = pq.read_table(pa.BufferReader(write_table(rows, "parquet", summary)))
    assert table.num_rows == len(rows)
    assert table.column("base_0_rgb/entropy").to_pylist() == [r["base_0_rgb/entropy"] for r in rows]
    assert json.loads(table.schema.metadata[b"openpi_cam.summary"])["steps"] == len(records)


def test_parquet_without_pyarrow_is_a_clear_error(random_run, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    with pytest.raises(SystemExit, match="pyarrow"):
        write_table([{"seq": 0}], "parquet", {})


def test_stats_command(random_run, tmp_path, capsys):
    run_dir, records = random_run
    out = tmp_path / "s.json"
    cli_main(["stats", str(run_dir), "--format", "json", "--out", str(out)])  # the default kind: gradient norm
    doc = json.loads(out.read_text())
    assert doc["steps"] == json.loads(json.dumps(to_rows(_stats(run_dir, "gradnorm"))))
    cli_main(["stats", str(run_dir), "--map", "gradcam", "--format", "json", "--out", str(out)])
    gradcam = json.loads(out.read_text())["steps"]
    assert gradcam == json.loads(json.dumps(to_rows(_stats(run_dir, "gradcam"))))
    assert gradcam != doc["steps"]
    capsys.readouterr()
    cli_main(["stats", str(run_dir)])
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == len(records) + 1 and lines[0].startswith("seq,connection,step")


def test_view_steps_refuses_a_kind_the_run_lacks(tmp_path):
    with CAMLogger(tmp_path, run_config={}, checkpoint="c", options={}) as logger:
        maps = {"gradcam": {c: np.ones(GRID, np.float32) for c in CAMS}}
        logger.log_step(StepRecord("a", 0, 0.0, maps, meta=_meta(dict.fromkeys(CAMS, True))))
    steps = load_run(logger.run_dir).steps
    assert len(view_steps(steps, "gradcam")) == 1
    with pytest.raises(MissingMaps, match="no gradient norm"):
        view_steps(steps, "gradnorm")
    with pytest.raises(ValueError, match="unknown map kind"):
        view_steps(steps, "saliency")
