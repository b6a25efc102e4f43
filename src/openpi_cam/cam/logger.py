"""CAMLogger: all disk I/O of the explanation side channel and offline explanation (format: docs/FORMAT.md).

It runs on the side channel's background worker, next to a server that must keep serving, so I/O failures it can
classify are counted and logged once per cause (`io_error_key`) instead of raised. Wrong argument types still raise:
those are bugs.
"""

from __future__ import annotations

import contextlib
import copy
import datetime as dt
import errno
import logging
import os
import pathlib
import secrets
import threading
from typing import Any

from openpi_cam.cam.run_format import (
    INDEX_JSONL,
    MANIFEST_JSON,
    RUN_JSON,
    SCHEMA_VERSION,
    STEPS_DIR,
    StepRecord,
    build_manifest,
    dumps,
    encode_step,
    index_entry,
    read_json,
    read_run_info,
    record_arrays,
    scan_steps,
    step_file,
    step_files,
    utc_now_iso,
    write_bytes_atomic,
    write_json_atomic,
)
from openpi_cam.counters import WarnOnceCounter

log = logging.getLogger(__name__)

_ERRNO_KEYS = {
    errno.ENOSPC: "disk_full",
    errno.EDQUOT: "disk_full",
    errno.EACCES: "permission_denied",
    errno.EPERM: "permission_denied",
    errno.EROFS: "read_only_filesystem",
    errno.ENOENT: "missing_path",
    errno.ENOTDIR: "not_a_directory",
    errno.EISDIR: "is_a_directory",
    errno.EMFILE: "too_many_open_files",
    errno.ENFILE: "too_many_open_files",
    errno.EIO: "device_error",
    errno.ENAMETOOLONG: "name_too_long",
}


def io_error_key(e: OSError) -> str:
    """The counter key of an I/O error's cause, e.g. "disk_full"."""
    if e.errno in _ERRNO_KEYS:
        return _ERRNO_KEYS[e.errno]
    return errno.errorcode.get(e.errno, "unknown").lower() if e.errno else type(e).__name__


def _create_run_dir(cam_dir: pathlib.Path) -> pathlib.Path:
    try:
        cam_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OSError(e.errno, f"cannot create the CAM directory {cam_dir}: {e.strerror or e}") from e
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%d-%H%M%S")
    for _ in range(64):
        run_dir = cam_dir / f"{stamp}-{secrets.token_hex(3)}"
        try:
            # mkdir without exist_ok is the atomic claim: two loggers can never share a directory.
            run_dir.mkdir()
        except FileExistsError:
            continue
        except OSError as e:
            raise OSError(e.errno, f"cannot create a CAM run directory in {cam_dir}: {e.strerror or e}") from e
        try:
            (run_dir / STEPS_DIR).mkdir()
        except OSError as e:
            raise OSError(e.errno, f"cannot create {run_dir / STEPS_DIR}: {e.strerror or e}") from e
        return run_dir
    raise OSError(errno.EEXIST, f"no free CAM run directory name in {cam_dir} for {stamp}")


class CAMLogger:
    """Writes one run directory. Thread-safe; per-step cost does not grow with the number of earlier steps.

    Caps: after `max_steps` logged steps, or once a step would take the run past `max_bytes` (step files plus index
    lines), every later step is skipped and counted, so a capped run is always a prefix of what was offered.
    """

    def __init__(
        self,
        cam_dir: str | os.PathLike[str],
        *,
        run_config: dict[str, Any],
        checkpoint: str,
        options: dict[str, Any],
        max_steps: int | None = None,
        max_bytes: int | None = None,
        manifest_every: int = 50,
        compress: bool = True,
    ) -> None:
        self._setup(max_steps, max_bytes, manifest_every, compress)
        self._run_dir = _create_run_dir(pathlib.Path(cam_dir))
        self._run_info = {
            "schema_version": SCHEMA_VERSION,
            "run_id": self._run_dir.name,
            "started_at": utc_now_iso(),
            "config": run_config,
            "checkpoint": checkpoint,
            "options": options,
        }
        try:
            write_json_atomic(self._run_dir / RUN_JSON, self._run_info)
        except OSError as e:
            raise OSError(e.errno, f"cannot write {self._run_dir / RUN_JSON}: {e.strerror or e}") from e

    def _setup(self, max_steps: int | None, max_bytes: int | None, manifest_every: int, compress: bool) -> None:
        """State shared by a fresh logger and a resumed one (an empty run)."""
        if manifest_every < 1:
            raise ValueError(f"manifest_every must be >= 1, got {manifest_every}")
        self._max_steps = max_steps
        self._max_bytes = max_bytes
        self._manifest_every = manifest_every
        self._compress = compress
        self._lock = threading.Lock()
        self._next_seq = 0
        self._entries: list[dict[str, Any]] = []
        self._external: dict[str, Any] = {}
        self._counters: dict[str, Any] = {
            "steps_logged": 0,
            "steps_skipped_cap": 0,
            "steps_skipped_io": 0,
            "steps_skipped_closed": 0,
            "bytes_written": 0,
        }
        self._io_errors = WarnOnceCounter(log, "CAM logger: I/O error")  # by cause (`io_error_key`)
        self._cap_reached = False
        self._closed = False
        self._index_fd: int | None = None
        # After a failed append the file may end in a partial line; the next line must not be glued onto it.
        self._index_needs_newline = False
        self._resumed_at: list[str] = []

    @classmethod
    def resume(
        cls,
        run_dir: str | os.PathLike[str],
        *,
        max_steps: int | None = None,
        max_bytes: int | None = None,
        manifest_every: int = 50,
        compress: bool = True,
    ) -> CAMLogger:
        """Reopens an existing run directory (even one whose writer was killed) and appends to it.

        Step files are the source of truth: the next seq follows the highest readable step file, the manifest lists
        every step found, and the old manifest's counters are carried on. Caps count the whole run, earlier steps
        included. run.json is left as it was; each resumption is recorded in the manifest's `resumed_at`.
        """
        run_dir = pathlib.Path(run_dir)
        run_info = read_run_info(run_dir)  # raises FileNotFoundError for a directory that is not a run
        if not (run_dir / STEPS_DIR).is_dir():
            raise FileNotFoundError(f"{run_dir} has no {STEPS_DIR}/ directory")
        self = cls.__new__(cls)
        self._setup(max_steps, max_bytes, manifest_every, compress)
        self._run_dir = run_dir
        self._run_info = run_info
        steps, entries, problems = scan_steps(run_dir, load_arrays=False)
        if problems:
            log.warning("CAM logger (%s): resuming past unreadable step files: %s", run_dir, problems)
        # Unreadable step files keep their seq too: appending must never overwrite a file already on disk.
        self._next_seq = max(step_files(run_dir), default=-1) + 1
        self._entries = [entries[s.seq] for s in steps]
        old = read_json(run_dir / MANIFEST_JSON) or {}
        old_counters = old.get("counters") if isinstance(old.get("counters"), dict) else {}
        logger_counters = old_counters.get("logger") if isinstance(old_counters.get("logger"), dict) else {}
        for key, value in logger_counters.items():
            if key in self._counters and isinstance(value, type(self._counters[key])):
                self._counters[key] = copy.deepcopy(value)
        old_errors = logger_counters.get("io_errors")
        for cause, n in (old_errors if isinstance(old_errors, dict) else {}).items():
            if isinstance(n, int):
                self._io_errors.count(str(cause), n=n)
        # What is on disk wins over a stale manifest for the counts caps are checked against.
        self._counters["steps_logged"] = len(steps)
        on_disk = sum(s.file.stat().st_size for s in steps)
        self._counters["bytes_written"] = max(int(self._counters["bytes_written"]), on_disk)
        if isinstance(old_counters.get("external"), dict):
            self._external = copy.deepcopy(old_counters["external"])
        previous = old.get("resumed_at")
        self._resumed_at = [*(previous if isinstance(previous, list) else []), utc_now_iso()]
        try:
            with open(run_dir / INDEX_JSONL, "rb") as f:
                f.seek(0, os.SEEK_END)
                if f.tell():
                    f.seek(-1, os.SEEK_END)
                    self._index_needs_newline = f.read(1) != b"\n"  # a line cut short by a crash
        except FileNotFoundError:
            pass
        self._write_manifest_locked()
        return self

    @property
    def run_dir(self) -> pathlib.Path:
        return self._run_dir

    @property
    def run_id(self) -> str:
        return self._run_dir.name

    @property
    def counters(self) -> dict[str, Any]:
        with self._lock:
            return self._counters_locked()

    def set_external_counters(self, counters: dict[str, Any]) -> None:
        """The wrapper's own counters, stored under counters.external in the manifest."""
        with self._lock:
            self._external = copy.deepcopy(counters)

    def log_step(self, record: StepRecord) -> bool:
        """Writes one step; False if it was skipped (cap reached, logger closed, or an I/O error, all counted)."""
        arrays = record_arrays(record)
        base = {
            "schema_version": SCHEMA_VERSION,
            "run_id": self.run_id,
            "seq": -1,
            "connection": str(record.connection),
            "step": int(record.step),
            "timestamp": float(record.timestamp),
        }
        with self._lock:
            # Everything below is serialised so that seq order, file names and index order always agree.
            if self._closed:
                self._counters["steps_skipped_closed"] += 1
                return False
            if self._max_steps is not None and self._counters["steps_logged"] >= self._max_steps:
                self._cap_reached = True
            if self._cap_reached:
                self._counters["steps_skipped_cap"] += 1
                return False
            seq = self._next_seq
            meta = base | {"seq": seq} | record.meta
            data = encode_step(arrays, meta, compress=self._compress)
            entry = index_entry(seq, meta, record.maps)
            line = (dumps(entry) + "\n").encode()
            size = len(data) + len(line)
            if self._max_bytes is not None and self._counters["bytes_written"] + size > self._max_bytes:
                self._cap_reached = True
                self._counters["steps_skipped_cap"] += 1
                return False
            try:
                write_bytes_atomic(self._run_dir / step_file(seq), data)
            except OSError as e:
                self._count_io_error(e, f"step file {step_file(seq)}")
                self._counters["steps_skipped_io"] += 1
                return False
            # The step file exists from here on: seq is consumed even if the index append fails, so nothing
            # already on disk is ever overwritten (the reader rebuilds missing index lines from step files).
            self._next_seq += 1
            self._entries.append(entry)
            self._counters["steps_logged"] += 1
            self._counters["bytes_written"] += len(data) + self._append_index(line)
            if self._counters["steps_logged"] % self._manifest_every == 0:
                self._write_manifest_locked()
            return True

    def close(self) -> None:
        """Writes the final manifest; later log_step calls are skipped. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._index_fd is not None:
                try:
                    os.close(self._index_fd)
                except OSError as e:
                    self._count_io_error(e, INDEX_JSONL)
                self._index_fd = None
            self._write_manifest_locked()

    def __enter__(self) -> CAMLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _append_index(self, line: bytes) -> int:
        """Appends one index line with a single O_APPEND write; returns the bytes written (0 on failure)."""
        if self._index_needs_newline:
            line = b"\n" + line
        try:
            if self._index_fd is None:
                self._index_fd = os.open(self._run_dir / INDEX_JSONL, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            view = memoryview(line)
            while view:
                view = view[os.write(self._index_fd, view) :]
        except OSError as e:
            self._count_io_error(e, INDEX_JSONL)
            self._index_needs_newline = True
            if self._index_fd is not None:
                with contextlib.suppress(OSError):
                    os.close(self._index_fd)
                self._index_fd = None
            return 0
        self._index_needs_newline = False
        return len(line)

    def _write_manifest_locked(self) -> bool:
        counters = {"logger": self._counters_locked(), "external": copy.deepcopy(self._external)}
        extra = {"resumed_at": self._resumed_at} if self._resumed_at else {}
        manifest = build_manifest(self._run_info, counters, self._entries, closed=self._closed, **extra)
        try:
            write_json_atomic(self._run_dir / MANIFEST_JSON, manifest)
        except OSError as e:
            self._count_io_error(e, MANIFEST_JSON)
            return False
        return True

    def _counters_locked(self) -> dict[str, Any]:
        return copy.deepcopy(self._counters) | {"io_errors": self._io_errors.snapshot()}

    def _count_io_error(self, e: OSError, what: str) -> None:
        self._io_errors.count(io_error_key(e), f"{self._run_dir}: {what}: {e}")
