"""Reading CAM run directories, and the format definitions the logger shares (see docs/FORMAT.md).

The step files are the source of truth. `index.jsonl` and `manifest.json` are conveniences that may be stale or
damaged after a crash; everything here copes with that by falling back to the step files.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import os
import pathlib
import re
import secrets
import sys
import zipfile
from collections.abc import Iterable, Mapping
from typing import Any, NamedTuple

import numpy as np
import tyro

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
RUN_JSON = "run.json"
INDEX_JSONL = "index.jsonl"
MANIFEST_JSON = "manifest.json"
STEPS_DIR = "steps"
MAP_PREFIX = "cam/"
GRADNORM_PREFIX = "gradnorm/"
FRAME_PREFIX = "frame/"
MODEL_FRAME_PREFIX = "frame_model/"
META_KEY = "meta"

_STEP_FILE_RE = re.compile(r"^(\d{8,})\.npz$")
# What np.load and the meta lookup raise for a damaged or foreign step file.
_UNREADABLE = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def step_file(seq: int) -> str:
    """Path of a step file relative to the run directory."""
    return f"{STEPS_DIR}/{seq:08d}.npz"


def utc_now_iso() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def json_default(value: Any) -> Any:
    """Lets numpy scalars and arrays (common in Grad-CAM metadata) pass through `json.dumps`."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, pathlib.Path):
        return str(value)
    raise TypeError(f"object of type {type(value).__name__} is not JSON serialisable")


def dumps(obj: Any, *, indent: int | None = None) -> str:
    return json.dumps(obj, default=json_default, indent=indent, ensure_ascii=False)


def write_bytes_atomic(path: pathlib.Path, data: bytes) -> None:
    """Writes to a unique temporary name in the same directory, then renames: readers never see a partial file."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json_atomic(path: pathlib.Path, obj: Any) -> None:
    write_bytes_atomic(path, (dumps(obj, indent=1) + "\n").encode())


def map_summary(cam_map: np.ndarray) -> dict[str, Any]:
    """max, mean and argmax [row, col] of a (Hp, Wp) map, or of the mean over T of a (T, Hp, Wp) stack.

    Non-finite cells are ignored; a map without any finite cell summarises to None values.
    """
    m = np.asarray(cam_map, dtype=np.float32)
    if m.ndim == 3:
        m = m.mean(axis=0)
    if m.ndim != 2 or m.size == 0:
        raise ValueError(f"expected a non-empty (Hp, Wp) or (T, Hp, Wp) map, got shape {np.shape(cam_map)}")
    finite = np.isfinite(m)
    if not finite.any():
        return {"max": None, "mean": None, "argmax": None}
    masked = np.where(finite, m, -np.inf)
    row, col = np.unravel_index(int(np.argmax(masked)), m.shape)
    return {"max": float(masked[row, col]), "mean": float(m[finite].mean()), "argmax": [int(row), int(col)]}


def summarize_maps(maps: Mapping[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    return {camera: map_summary(m) for camera, m in maps.items()}


def index_entry(seq: int, meta: Mapping[str, Any], summary: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """One line of index.jsonl (also one element of the manifest's "steps")."""
    return {
        "seq": seq,
        "file": step_file(seq),
        "connection": meta.get("connection"),
        "step": meta.get("step"),
        "timestamp": meta.get("timestamp"),
        "target": meta.get("target"),
        "summary": summary,
    }


def build_manifest(
    run_info: Mapping[str, Any], counters: Mapping[str, Any], entries: Iterable[dict[str, Any]], **extra: Any
) -> dict[str, Any]:
    steps = sorted(entries, key=lambda e: e["seq"])
    head = {**run_info, **extra, "updated_at": utc_now_iso(), "num_steps": len(steps)}
    return head | {"counters": counters, "steps": steps}


class StepArrays(NamedTuple):
    maps: dict[str, np.ndarray]
    frames: dict[str, np.ndarray]
    model_frames: dict[str, np.ndarray]
    gradnorm_maps: dict[str, np.ndarray]  # empty for steps written before the key existed


_ARRAY_PREFIXES = (MAP_PREFIX, FRAME_PREFIX, MODEL_FRAME_PREFIX, GRADNORM_PREFIX)  # StepArrays' field order


def _split_arrays(npz: Any) -> StepArrays:
    arrays = StepArrays({}, {}, {}, {})
    for key in npz.files:
        for prefix, target in zip(_ARRAY_PREFIXES, arrays, strict=True):
            if key.startswith(prefix):
                target[key[len(prefix) :]] = npz[key]
    return arrays


def _read_meta(npz: Any) -> dict[str, Any]:
    return json.loads(str(npz[META_KEY][()]))


class CAMStep:
    """One logged step. Arrays are read from the step file on first access unless loaded eagerly."""

    def __init__(self, seq: int, meta: dict[str, Any], file: pathlib.Path, arrays: StepArrays | None = None) -> None:
        self.seq = seq
        self.meta = meta
        self.file = file
        self._arrays = arrays

    def arrays(self) -> StepArrays:
        if self._arrays is None:
            with np.load(self.file, allow_pickle=False) as npz:
                self._arrays = _split_arrays(npz)
        return self._arrays

    @property
    def maps(self) -> dict[str, np.ndarray]:
        return self.arrays().maps

    @property
    def gradnorm_maps(self) -> dict[str, np.ndarray]:
        return self.arrays().gradnorm_maps

    @property
    def frames(self) -> dict[str, np.ndarray]:
        return self.arrays().frames

    @property
    def model_frames(self) -> dict[str, np.ndarray]:
        return self.arrays().model_frames

    def __repr__(self) -> str:
        return f"CAMStep(seq={self.seq}, file={str(self.file)!r})"


@dataclasses.dataclass
class CAMRun:
    run_dir: pathlib.Path
    run_info: dict[str, Any]
    manifest: dict[str, Any]
    steps: list[CAMStep]
    # Step files that could not be read (disk corruption, foreign files); reported rather than fatal.
    problems: list[str] = dataclasses.field(default_factory=list)


def _read_json(path: pathlib.Path) -> dict[str, Any] | None:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _read_index(run_dir: pathlib.Path) -> dict[int, dict[str, Any]]:
    """Parseable lines of index.jsonl by seq; a line cut short by a crash is skipped."""
    entries: dict[int, dict[str, Any]] = {}
    try:
        text = (run_dir / INDEX_JSONL).read_text(errors="replace")
    except OSError:
        return entries
    for line in text.splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and isinstance(entry.get("seq"), int):
            entries[entry["seq"]] = entry
    return entries


def _step_files(run_dir: pathlib.Path) -> dict[int, pathlib.Path]:
    steps_dir = run_dir / STEPS_DIR
    if not steps_dir.is_dir():
        return {}
    found = {}
    for path in steps_dir.iterdir():
        match = _STEP_FILE_RE.match(path.name)
        if match and path.is_file():
            found[int(match.group(1))] = path
    return dict(sorted(found.items()))


def _scan(run_dir: pathlib.Path, *, load_arrays: bool) -> tuple[list[CAMStep], dict[int, dict[str, Any]], list[str]]:
    """Reads every step file; returns the steps, an index entry per step, and the files that failed to read."""
    index = _read_index(run_dir)
    steps, entries, problems = [], {}, []
    for seq, path in _step_files(run_dir).items():
        try:
            with np.load(path, allow_pickle=False) as npz:
                meta = _read_meta(npz)
                arrays = _split_arrays(npz) if load_arrays or seq not in index else None
        except _UNREADABLE as e:
            problems.append(f"{path.relative_to(run_dir)}: {e}")
            continue
        steps.append(CAMStep(seq, meta, path, arrays if load_arrays else None))
        # arrays were read above whenever the index lacks this step
        entries[seq] = index[seq] if seq in index else index_entry(seq, meta, summarize_maps(arrays.maps))
    return steps, entries, problems


def _manifest_is_current(manifest: dict[str, Any] | None, seqs: list[int]) -> bool:
    if manifest is None or not isinstance(manifest.get("steps"), list):
        return False
    return [e.get("seq") for e in manifest["steps"] if isinstance(e, dict)] == seqs


def _rebuilt_manifest(
    run_info: dict[str, Any], old: dict[str, Any] | None, entries: dict[int, dict[str, Any]]
) -> dict[str, Any]:
    counters = old.get("counters", {}) if old else {}
    closed = bool(old.get("closed")) if old else False
    return build_manifest(run_info, counters, entries.values(), closed=closed, rebuilt_at=utc_now_iso())


def _read_run_info(run_dir: pathlib.Path) -> dict[str, Any]:
    run_info = _read_json(run_dir / RUN_JSON)
    if run_info is None:
        raise FileNotFoundError(f"{run_dir} is not a CAM run directory (no readable {RUN_JSON})")
    version = run_info.get("schema_version")
    if not isinstance(version, int) or version > SCHEMA_VERSION:
        log.warning("%s has schema_version %r; this reader knows up to %d", run_dir, version, SCHEMA_VERSION)
    return run_info


def load_run(run_dir: str | os.PathLike[str], *, load_arrays: bool = True) -> CAMRun:
    """Reads a run directory, including one whose writer was killed; never writes to it.

    `manifest` is manifest.json when it lists exactly the step files present, otherwise one rebuilt in memory.
    """
    run_dir = pathlib.Path(run_dir)
    run_info = _read_run_info(run_dir)
    steps, entries, problems = _scan(run_dir, load_arrays=load_arrays)
    manifest = _read_json(run_dir / MANIFEST_JSON)
    if not _manifest_is_current(manifest, [s.seq for s in steps]):
        manifest = _rebuilt_manifest(run_info, manifest, entries)
    return CAMRun(run_dir, run_info, manifest, steps, problems)


def rebuild_manifest(run_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Rewrites manifest.json from the step files (and index.jsonl summaries), keeping an old manifest's counters."""
    run_dir = pathlib.Path(run_dir)
    run_info = _read_run_info(run_dir)
    _, entries, problems = _scan(run_dir, load_arrays=False)
    manifest = _rebuilt_manifest(run_info, _read_json(run_dir / MANIFEST_JSON), entries)
    if problems:
        manifest["unreadable_files"] = problems
    write_json_atomic(run_dir / MANIFEST_JSON, manifest)
    return manifest


def list_runs(cam_dir: str | os.PathLike[str]) -> list[pathlib.Path]:
    """Run directories under `cam_dir`, oldest first (names start with a UTC timestamp)."""
    cam_dir = pathlib.Path(cam_dir)
    if not cam_dir.is_dir():
        return []
    return sorted(p for p in cam_dir.iterdir() if p.is_dir() and (p / RUN_JSON).is_file())


def cam_index_cmd(run_dir: tyro.conf.Positional[pathlib.Path]) -> int:
    """Rebuild a CAM run's manifest.json from its step files (e.g. after the server was killed).

    Args:
        run_dir: the run directory (contains run.json and steps/).
    """
    try:
        manifest = rebuild_manifest(run_dir)
    except OSError as e:
        print(f"cam-index: {e}", file=sys.stderr)
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
