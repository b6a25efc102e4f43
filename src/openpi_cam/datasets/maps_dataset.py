"""The maps dataset: the maps of a LeRobot dataset's frames, as parquet shards beside a `meta/info.json`.

Layout (docs/FORMAT.md, "Maps dataset"):

    OUT/meta/info.json                                   what was explained and how (written before any shard)
    OUT/meta/summary.json                                the last job's counts and the episodes it skipped
    OUT/data/chunk-{episode // 1000:03d}/episode_{episode:06d}.parquet

One shard per explained episode, one row per explained frame. A shard is written to a temporary name and renamed
into place, so a shard that exists is complete, a job killed mid-episode leaves no partial shard behind, and writing
the same episode twice (a retried block, a resumed job) replaces it instead of adding rows: every frame is written
at most once. Rows join the source dataset on `index`.

Columns: `index`, `episode_index`, `frame_index`, `timestamp`, `task`, `target`, `score`, `malformed`, `actions`
(the model's action chunk, row-major), `explain_ms`; per map kind and camera `<kind>/<camera>`, the raw map as
float32 in row-major order over the camera's patch grid (`info["grids"]`); the spot check as `check/<kind>/<camera>`
(the score's drop with the kind's top patch painted) and `check/random/<camera>` (the drops of the random patches),
with the whole check as JSON in `check`; `cameras` and `details` as JSON; `extra/<name>` for carried features.

Reading needs pyarrow and numpy only, so the commands that read maps (`stats`, `render`) do not load JAX.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import secrets
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from openpi_cam.cam.run_format import dumps

FORMAT = "openpi-cam maps dataset"
FORMAT_VERSION = 1
INFO_JSON = "meta/info.json"
SUMMARY_JSON = "meta/summary.json"
DATA_DIR = "data"
EPISODES_PER_CHUNK = 1000
CHECK_RANDOM = "random"  # `check/random/<camera>`: the random patches' drops
# info.json fields that must match for a resumed job to stay one explanation of one source.
RESUME_KEYS = ("source", "source_version", "checkpoint", "config", "dtype", "target", "kinds", "keys", "every")
RESUME_OPTION_KEYS = ("baseline", "ig_space", "occlusion_region", "occlusion_masks", "action_index", "check_patches")


def shard_path(episode: int) -> str:
    """Where an episode's shard lives, relative to the maps dataset's root."""
    return f"{DATA_DIR}/chunk-{episode // EPISODES_PER_CHUNK:03d}/episode_{episode:06d}.parquet"


def map_column(kind: str, camera: str) -> str:
    return f"{kind}/{camera}"


def check_column(kind: str, camera: str) -> str:
    return f"check/{kind}/{camera}"


def is_maps_dataset(path: pathlib.Path) -> bool:
    info = pathlib.Path(path) / INFO_JSON
    if not info.is_file():
        return False
    try:
        return json.loads(info.read_text()).get("format") == FORMAT
    except (OSError, ValueError):
        return False


def _write_atomic(path: pathlib.Path, write: Any) -> None:
    # Not run_format.write_bytes_atomic: the temporary name starts with ".", which pyarrow's dataset discovery
    # skips, so a reader of OUT/data never opens a shard still being written; and pyarrow writes the shard, not bytes.
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: pathlib.Path, obj: Any) -> None:
    text = dumps(obj, indent=2)
    _write_atomic(path, lambda tmp: tmp.write_text(text))


def schema(info: Mapping[str, Any]) -> pa.Schema:
    """The shards' schema, fixed by info.json: one column per map kind and camera, per spot-check figure, per extra."""
    cameras, kinds = list(info["grids"]), list(info["kinds"])
    score = pa.list_(pa.float64()) if info.get("scores_per_row", 1) != 1 else pa.float64()
    fields = [
        pa.field("index", pa.int64()),
        pa.field("episode_index", pa.int64()),
        pa.field("frame_index", pa.int64()),
        pa.field("timestamp", pa.float64()),
        pa.field("task", pa.string()),
        pa.field("target", pa.string()),
        pa.field("score", score),
        pa.field("malformed", pa.string()),
        pa.field("actions", pa.list_(pa.float32())),
        pa.field("explain_ms", pa.float64()),
        pa.field("cameras", pa.string()),
        pa.field("details", pa.string()),
        pa.field("check", pa.string()),
    ]
    fields += [pa.field(map_column(k, c), pa.list_(pa.float32())) for k in kinds for c in cameras]
    fields += [pa.field(check_column(k, c), pa.float64()) for k in kinds for c in cameras]
    fields += [pa.field(check_column(CHECK_RANDOM, c), pa.list_(pa.float64())) for c in cameras]
    fields += [pa.field(f"extra/{name}", pa.list_(pa.float64())) for name in info.get("extra", {}).values()]
    return pa.schema(fields)


def write_shard(root: pathlib.Path, info: Mapping[str, Any], episode: int, rows: Sequence[Mapping[str, Any]]) -> str:
    """Writes one episode's rows as its shard (atomically; an existing shard is replaced). Returns its path."""
    table = pa.Table.from_pylist([dict(r) for r in rows], schema=schema(info))
    rel = shard_path(episode)
    _write_atomic(pathlib.Path(root) / rel, lambda tmp: pq.write_table(table, tmp, compression="zstd"))
    return rel


def written_episodes(root: pathlib.Path) -> set[int]:
    """Episodes whose shard is complete (temporary files of an interrupted write are not shards)."""
    data = pathlib.Path(root) / DATA_DIR
    return {int(p.stem.split("_")[1]) for p in data.glob("chunk-*/episode_*.parquet")} if data.is_dir() else set()


def resume_mismatch(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """The settings of this job that differ from those of the maps dataset it would add to."""
    diffs = [f"{k}: {old.get(k)!r} != {new.get(k)!r}" for k in RESUME_KEYS if old.get(k) != new.get(k)]
    old_options, new_options = old.get("options") or {}, new.get("options") or {}
    diffs += [
        f"{k}: {old_options.get(k)!r} != {new_options.get(k)!r}"
        for k in RESUME_OPTION_KEYS
        if old_options.get(k) != new_options.get(k)
    ]
    return diffs


@dataclasses.dataclass(frozen=True)
class MapsDataset:
    """A maps dataset opened for reading."""

    root: pathlib.Path
    info: dict[str, Any]

    @property
    def kinds(self) -> list[str]:
        return list(self.info["kinds"])

    @property
    def cameras(self) -> list[str]:
        return list(self.info["grids"])

    def grid(self, camera: str) -> tuple[int, int]:
        hp, wp = self.info["grids"][camera]
        return int(hp), int(wp)

    @property
    def episodes(self) -> list[int]:
        return sorted(written_episodes(self.root))

    def summary(self) -> dict[str, Any]:
        path = self.root / SUMMARY_JSON
        return json.loads(path.read_text()) if path.is_file() else {}

    def table(self, episode: int | None = None, columns: Sequence[str] | None = None) -> pa.Table:
        """The rows of one episode or of all of them, sorted by `index`."""
        paths = (
            [self.root / shard_path(e) for e in self.episodes] if episode is None else [self.root / shard_path(episode)]
        )
        if not paths:
            return schema(self.info).empty_table()
        cols, shards = None if columns is None else list(columns), schema(self.info)
        table = pa.concat_tables([pq.read_table(p, columns=cols, schema=shards) for p in paths])
        return table.sort_by("index") if "index" in table.column_names else table

    def maps(self, kind: str, camera: str, episode: int | None = None) -> np.ndarray:
        """float32 [frames, Hp, Wp] (or [frames, T, Hp, Wp] for per-token targets) of one kind and camera."""
        column = self.table(episode, [map_column(kind, camera)]).column(0)
        hp, wp = self.grid(camera)
        flat = np.asarray(column.combine_chunks().flatten(), np.float32)
        rows = len(column)
        per_row = flat.size // max(rows, 1)
        shape = (rows, hp, wp) if per_row == hp * wp else (rows, per_row // (hp * wp), hp, wp)
        return flat.reshape(shape)

    def rows(self, episode: int | None = None) -> Iterator[dict[str, Any]]:
        yield from self.table(episode).to_pylist()


def open_maps_dataset(root: str | pathlib.Path) -> MapsDataset:
    root = pathlib.Path(root)
    if not is_maps_dataset(root):
        raise FileNotFoundError(f"{root} is not a maps dataset (no {INFO_JSON} with format {FORMAT!r})")
    return MapsDataset(root, json.loads((root / INFO_JSON).read_text()))
