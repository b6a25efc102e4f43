"""`openpi-cam rebuild-manifest RUN_DIR` (earlier `cam-index`): rebuild a run's manifest.json from its step files."""

from __future__ import annotations

import pathlib
import sys

import tyro

from openpi_cam.cam.run_format import MANIFEST_JSON, rebuild_manifest


def main(run_dir: tyro.conf.Positional[pathlib.Path]) -> int:
    """Rebuild a CAM run's manifest.json from its step files (e.g. after the server was killed).

    Args:
        run_dir: the run directory (contains run.json and steps/).
    """
    try:
        manifest = rebuild_manifest(run_dir)
    except OSError as e:
        print(f"openpi-cam rebuild-manifest: {e}", file=sys.stderr)
        return 1
    seqs = [e["seq"] for e in manifest["steps"]]
    cameras = sorted({c for e in manifest["steps"] for c in (e.get("summary") or {})})
    span = f"seq {seqs[0]}..{seqs[-1]}" if seqs else "no steps"
    gaps = "" if not seqs or seqs == list(range(seqs[0], seqs[0] + len(seqs))) else ", with gaps"
    unreadable = len(manifest.get("unreadable_files", []))
    print(
        f"{run_dir}: {len(seqs)} steps ({span}{gaps}), cameras {cameras}, "
        f"{unreadable} unreadable step files; wrote {MANIFEST_JSON}"
    )
    return 0
