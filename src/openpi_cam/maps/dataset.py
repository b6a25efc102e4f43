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
float32 in row-major order over the camera's patch grid (`MapsInfo.grids`); the spot check as `check/<kind>/<camera>`
(the score's drop with the kind's top patch painted) and `check/random/<camera>` (the drops of the random patches),
with the whole check as JSON in `check`; `cameras` and `details` as JSON; `extra/<name>` for carried features. When
reliance was measured (`--reliance`), `reliance` holds it as JSON (`cam.reliance`) and `<camera>/reliance_score`,
`<camera>/reliance_actions`, `prompt/reliance_score`, `prompt/reliance_actions` its figures. When
the source records outcomes (`MapsInfo.outcome`), every row carries its episode's: `episode_length` (the source
episode's frames), `episode_success` (any frame's outcome true, as lerobot-eval counts a success) and
`episode_return` (the sum of the episode's `next.reward`; null without one). Every row carries the failure monitor's
view of its frame's served call (`MONITOR_COLUMNS`): `monitor/stac` (STAC-single against the episode's previous
explained frame when it lies `execution_horizon` frames before, else null), `monitor/token_entropy` (pi0-FAST; null
for the flow families), and with a monitor (`MapsInfo.monitor`) `monitor/score` and `monitor/flag`; with
`monitor_features` the pooled features `monitor/features/<name>` (float32 lists); with `sample_spread` N,
`monitor/sample_spread` (the spread of N action chunks drawn for the frame, pi0 / pi0.5).

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

from openpi_cam.cam.run_format import RELIANCE_PROMPT, dumps
from openpi_cam.errors import BadFile, load_json, reading
from openpi_cam.monitor.signals import SAMPLE_SPREAD, STAC, TOKEN_ENTROPY
from openpi_cam.monitor.stream import FLAG, SCORE

FORMAT = "openpi-cam maps dataset"
# 2: the model as the command line names it (`model`), the explanation options in one encoding (`options`).
# 3: episode outcomes (`outcome`, `reward`; the `episode_*` columns); reliance columns (`options.reliance`).
# 4: the failure monitor's columns (`monitor/...`; `monitor`, `monitor_sha256`, `execution_horizon`,
# `monitor_features`).
# 5: the action-sample spread (`sample_spread`, `monitor/sample_spread`).
FORMAT_VERSION = 5
INFO_JSON = "meta/info.json"
SUMMARY_JSON = "meta/summary.json"
DATA_DIR = "data"
EPISODES_PER_CHUNK = 1000
CHECK_RANDOM = "random"  # `check/random/<camera>`: the random patches' drops
FRAME_INDEX = "frame_index"  # a row's frame within its episode, as LeRobot numbers it
# What every row says of its frame, whatever the maps: where it sits in the source and what was explained.
FRAME_COLUMNS = ("index", "episode_index", FRAME_INDEX, "timestamp", "task", "target", "score", "malformed")
CAMERAS_COLUMN = "cameras"  # JSON: per model camera its validity and letterbox geometry
# info.json fields, besides the model and the explanation options, that must match to add episodes to a maps dataset.
SOURCE_KEYS = (
    "source",
    "source_version",
    "recorded_actions",
    "keys",
    "every",
    "nested_keys",
    "outcome",
    "reward",
    "monitor_sha256",
    "execution_horizon",
    "monitor_features",
    "sample_spread",
)
# Each row's episode, when the source records outcomes: its length in source frames, whether it succeeded, its return.
EPISODE_LENGTH, EPISODE_SUCCESS, EPISODE_RETURN = "episode_length", "episode_success", "episode_return"
OUTCOME_COLUMNS = (EPISODE_LENGTH, EPISODE_SUCCESS, EPISODE_RETURN)
MONITOR_PREFIX = "monitor/"  # a column of the failure monitor: MONITOR_PREFIX + the name of its input or outcome
# The monitor's columns of every row (format 4): its scalar inputs, then its score and flag (null without a monitor).
MONITOR_COLUMNS = tuple(MONITOR_PREFIX + name for name in (STAC, TOKEN_ENTROPY, SCORE, FLAG))


@dataclasses.dataclass(frozen=True)
class MapsInfo:
    """A maps dataset's meta/info.json: what was explained and how. JSON-only (the viewers read it without JAX):
    `model` is a `checkpoints.model_spec.ModelSpec` and `options` a `vocabulary.ExplainOptions` as they encode
    themselves, with the job's `batch_size` beside the options."""

    source: str  # the LeRobot dataset's folder
    source_version: str  # its codebase_version
    source_fps: float
    model: dict[str, Any]
    family: str  # pi0_fast, pi0, pi05
    target: str  # the explained target (`dataset-actions` when the recorded chunk was explained)
    kinds: list[str]
    grids: dict[str, list[int]]  # model camera -> patch grid (Hp, Wp)
    camera_sources: dict[str, str | None]  # model camera -> dataset feature (None: a synthesised camera)
    keys: dict[str, str]  # observation key -> dataset feature
    options: dict[str, Any]
    recorded_actions: str | None = None  # `--target dataset-actions`: the feature of the recorded actions
    extra: dict[str, str] = dataclasses.field(default_factory=dict)  # dataset feature -> `extra/<name>` column
    every: int = 1
    nested_keys: bool = False
    scores_per_row: int = 1  # 0: one score per explained token (a list)
    outcome: str | None = None  # the source feature whose truth in any frame makes an episode a success
    reward: str | None = None  # the source feature summed into an episode's return
    monitor: str | None = None  # the monitor file the rows were scored with, and its content's SHA-256
    monitor_sha256: str | None = None
    # the actions executed per call that STAC assumed (format 4; None: a dataset made before the monitor's columns)
    execution_horizon: int | None = None
    monitor_features: list[str] = dataclasses.field(default_factory=list)  # `monitor/<name>` feature columns
    sample_spread: int = 0  # the action samples per call `monitor/sample_spread` compares (format 5; 0: no column)

    @property
    def cameras(self) -> list[str]:
        return list(self.grids)

    @property
    def monitored(self) -> bool:
        """Whether the rows carry the failure monitor's columns (`MONITOR_COLUMNS`: format 4 and later)."""
        return self.execution_horizon is not None

    @property
    def monitor_scalars(self) -> tuple[str, ...]:
        """The scalar monitor inputs the rows carry as `monitor/<name>` (with `monitored`): STAC-single and the
        token entropy, and the sample spread where it was drawn."""
        return (STAC, TOKEN_ENTROPY, SAMPLE_SPREAD) if self.sample_spread else (STAC, TOKEN_ENTROPY)

    @property
    def reliance(self) -> bool:
        """Whether the rows carry camera and prompt reliance (`--reliance`)."""
        return bool(self.options.get("reliance"))

    def grid(self, camera: str) -> tuple[int, int]:
        hp, wp = self.grids[camera]
        return int(hp), int(wp)

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "format_version": FORMAT_VERSION, **dataclasses.asdict(self)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> MapsInfo:
        """info.json as written by this or an earlier format version (version 1 named the model by `checkpoint`,
        `config` and `dtype`, and kept some options beside the others)."""
        data = dict(data)
        if int(data.get("format_version", 1)) < 2:
            data["model"] = {
                "checkpoint_dir": data.get("checkpoint"),
                "config": data.get("config"),
                "dtype": data.get("dtype"),
            }
            data["options"] = {"target": data.get("target"), "maps": data.get("kinds"), **(data.get("options") or {})}
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in fields})

    def mismatch(self, other: MapsInfo) -> list[str]:
        """`key: old != new` for each source setting that differs (the model's and the options':
        `cam.records.resume_mismatch`)."""
        old, new = dataclasses.asdict(self), dataclasses.asdict(other)
        return [f"{k}: {old[k]!r} != {new[k]!r}" for k in SOURCE_KEYS if old[k] != new[k]]


def shard_path(episode: int) -> str:
    """Where an episode's shard lives, relative to the maps dataset's root."""
    return f"{DATA_DIR}/chunk-{episode // EPISODES_PER_CHUNK:03d}/episode_{episode:06d}.parquet"


def map_column(kind: str, camera: str) -> str:
    return f"{kind}/{camera}"


def check_column(kind: str, camera: str) -> str:
    return f"check/{kind}/{camera}"


def extra_column(name: str) -> str:
    """The column of a carried feature (`DatasetJob.extra`: dataset feature -> name)."""
    return f"extra/{name}"


def map_array(column: pa.ChunkedArray, grid: tuple[int, int]) -> np.ndarray:
    """A `<kind>/<camera>` column as float32 [rows, Hp, Wp], or [rows, T, Hp, Wp] for per-token targets."""
    hp, wp = grid
    flat = np.asarray(column.combine_chunks().flatten(), np.float32)
    rows = len(column)
    per_row = flat.size // max(rows, 1)
    return flat.reshape((rows, hp, wp) if per_row == hp * wp else (rows, per_row // (hp * wp), hp, wp))


def is_maps_dataset(path: pathlib.Path) -> bool:
    """Whether `path` holds a maps dataset's info.json; one that cannot be read as a JSON object counts, so that
    opening it names what is wrong with the file instead of calling the folder something else."""
    info = pathlib.Path(path) / INFO_JSON
    if not info.is_file():
        return False
    try:
        data = load_json(info)
    except (OSError, BadFile):
        return True
    return data.get("format") == FORMAT


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


def schema(info: MapsInfo) -> pa.Schema:
    """The shards' schema, fixed by info.json: one column per map kind and camera, per spot-check figure, per extra."""
    cameras, kinds = info.cameras, info.kinds
    score = pa.list_(pa.float64()) if info.scores_per_row != 1 else pa.float64()
    frame_types = (pa.int64(), pa.int64(), pa.int64(), pa.float64(), pa.string(), pa.string(), score, pa.string())
    fields = [pa.field(name, kind) for name, kind in zip(FRAME_COLUMNS, frame_types, strict=True)]
    fields += [
        pa.field("actions", pa.list_(pa.float32())),
        pa.field("explain_ms", pa.float64()),
        pa.field(CAMERAS_COLUMN, pa.string()),
        pa.field("details", pa.string()),
        pa.field("check", pa.string()),
    ]
    fields += [pa.field(map_column(k, c), pa.list_(pa.float32())) for k in kinds for c in cameras]
    fields += [pa.field(check_column(k, c), pa.float64()) for k in kinds for c in cameras]
    fields += [pa.field(check_column(CHECK_RANDOM, c), pa.list_(pa.float64())) for c in cameras]
    fields += [pa.field(extra_column(name), pa.list_(pa.float64())) for name in info.extra.values()]
    if info.reliance:
        fields += [pa.field("reliance", pa.string())]
        fields += [pa.field(column, pa.float64()) for column in reliance_columns(info)]
    if info.outcome is not None:
        fields += [
            pa.field(EPISODE_LENGTH, pa.int64()),
            pa.field(EPISODE_SUCCESS, pa.bool_()),
            pa.field(EPISODE_RETURN, pa.float64()),
        ]
    if info.monitored:
        types = (pa.float64(), pa.float64(), pa.float64(), pa.bool_())
        fields += [pa.field(name, kind) for name, kind in zip(MONITOR_COLUMNS, types, strict=True)]
        fields += [pa.field(MONITOR_PREFIX + name, pa.list_(pa.float32())) for name in info.monitor_features]
        if info.sample_spread:
            fields += [pa.field(MONITOR_PREFIX + SAMPLE_SPREAD, pa.float64())]
    return pa.schema(fields)


def reliance_columns(info: MapsInfo) -> list[str]:
    """`<camera>/reliance_score`, `<camera>/reliance_actions` for every camera the model sees, then `prompt/...`:
    the flat figures of each row's reliance (`cam.run_format.Reliance.figures`)."""
    names = [*info.cameras, RELIANCE_PROMPT]
    return [f"{name}/reliance_{what}" for name in names for what in ("score", "actions")]


def write_shard(root: pathlib.Path, info: MapsInfo, episode: int, rows: Sequence[Mapping[str, Any]]) -> str:
    """Writes one episode's rows as its shard (atomically; an existing shard is replaced). Returns its path."""
    table = pa.Table.from_pylist([dict(r) for r in rows], schema=schema(info))
    rel = shard_path(episode)
    _write_atomic(pathlib.Path(root) / rel, lambda tmp: pq.write_table(table, tmp, compression="zstd"))
    return rel


def written_episodes(root: pathlib.Path) -> set[int]:
    """Episodes whose shard is complete (temporary files of an interrupted write are not shards)."""
    data = pathlib.Path(root) / DATA_DIR
    return {int(p.stem.split("_")[1]) for p in data.glob("chunk-*/episode_*.parquet")} if data.is_dir() else set()


@dataclasses.dataclass(frozen=True)
class EpisodeFrames:
    """One episode's explained frames, typed, column by column in `index` order: what each frame says of itself
    (`meta`: `FRAME_COLUMNS`, then the outcome and reliance columns the dataset has), what the model saw of each
    camera, one kind's maps and, where asked, the spot checks and carried features (`MapsDataset.episode_frames`)."""

    episode: int
    meta: list[dict[str, Any]]
    cameras: list[dict[str, Any]]  # per frame: the `cameras` JSON (model camera -> its validity, geometry)
    maps: dict[str, np.ndarray]  # model camera -> float32 [N, Hp, Wp] (or [N, T, Hp, Wp] for per-token targets)
    checks: dict[str, dict[str, list[Any]]]  # kind (and CHECK_RANDOM) -> camera -> per frame its drop (drops)
    extra: dict[str, list[Any]]  # carried name -> per frame its value

    def __len__(self) -> int:
        return len(self.meta)

    def valid(self, camera: str) -> np.ndarray:
        """bool [N]: whether the model saw the camera in each frame (a camera the JSON leaves out: it did)."""
        return np.array([bool(c.get(camera, {}).get("valid", True)) for c in self.cameras], bool)


@dataclasses.dataclass(frozen=True)
class MapsDataset:
    """A maps dataset opened for reading."""

    root: pathlib.Path
    info: MapsInfo

    @property
    def kinds(self) -> list[str]:
        return list(self.info.kinds)

    @property
    def cameras(self) -> list[str]:
        return self.info.cameras

    def grid(self, camera: str) -> tuple[int, int]:
        return self.info.grid(camera)

    @property
    def episodes(self) -> list[int]:
        return sorted(written_episodes(self.root))

    def summary(self) -> dict[str, Any]:
        path = self.root / SUMMARY_JSON
        return load_json(path) if path.is_file() else {}

    def table(self, episode: int | None = None, columns: Sequence[str] | None = None) -> pa.Table:
        """The rows of one episode or of all of them, sorted by `index`."""
        paths = (
            [self.root / shard_path(e) for e in self.episodes] if episode is None else [self.root / shard_path(episode)]
        )
        if not paths:
            return schema(self.info).empty_table()
        cols, shards = None if columns is None else list(columns), schema(self.info)
        table = pa.concat_tables([_read_shard(p, cols, shards) for p in paths])
        return table.sort_by("index") if "index" in table.column_names else table

    def maps(self, kind: str, camera: str, episode: int | None = None) -> np.ndarray:
        """float32 [frames, Hp, Wp] (or [frames, T, Hp, Wp] for per-token targets) of one kind and camera."""
        return map_array(self.table(episode, [map_column(kind, camera)]).column(0), self.grid(camera))

    def rows(self, episode: int | None = None) -> Iterator[dict[str, Any]]:
        yield from self.table(episode).to_pylist()

    @property
    def meta_columns(self) -> list[str]:
        """`EpisodeFrames.meta`'s columns: the frame's own, then its episode's outcome, its reliance figures and the
        monitor's scalar columns (`MONITOR_COLUMNS` and the sample spread, not the pooled features) where the dataset
        has them."""
        outcomes = OUTCOME_COLUMNS if self.info.outcome is not None else ()
        reliance = reliance_columns(self.info) if self.info.reliance else []
        scalars = [MONITOR_PREFIX + name for name in self.info.monitor_scalars]
        monitor = list(dict.fromkeys([*scalars, *MONITOR_COLUMNS])) if self.info.monitored else []
        return [*FRAME_COLUMNS, *outcomes, *reliance, *monitor]

    def require_kind(self, kind: str) -> None:
        if kind not in self.kinds:
            raise ValueError(f"this maps dataset has no {kind!r} maps (it holds {', '.join(self.kinds) or 'none'})")

    def episode_frames(
        self, episode: int, kind: str, *, checks: bool = False, extra: Sequence[str] = ()
    ) -> EpisodeFrames:
        """One episode's frames with `kind`'s maps, every kind's spot checks (`checks`) and the carried features named
        in `extra`, read in one pass over its shard."""
        self.require_kind(kind)
        cameras, meta = self.cameras, self.meta_columns
        check_columns = (
            {k: {c: check_column(k, c) for c in cameras} for k in (*self.kinds, CHECK_RANDOM)} if checks else {}
        )
        columns = [*meta, CAMERAS_COLUMN, *(map_column(kind, c) for c in cameras)]
        columns += [column for per_camera in check_columns.values() for column in per_camera.values()]
        columns += [extra_column(name) for name in extra]
        table = self.table(episode, columns)
        return EpisodeFrames(
            episode=episode,
            meta=table.select(meta).to_pylist(),
            cameras=[json.loads(text) if text else {} for text in table.column(CAMERAS_COLUMN).to_pylist()],
            maps={c: map_array(table.column(map_column(kind, c)), self.grid(c)) for c in cameras},
            checks={
                k: {c: table.column(column).to_pylist() for c, column in per_camera.items()}
                for k, per_camera in check_columns.items()
            },
            extra={name: table.column(extra_column(name)).to_pylist() for name in extra},
        )


def _read_shard(path: pathlib.Path, columns: list[str] | None, shards: pa.Schema) -> pa.Table:
    with reading(path, "parquet file"):
        return pq.read_table(path, columns=columns, schema=shards)


def open_maps_dataset(root: str | pathlib.Path) -> MapsDataset:
    root = pathlib.Path(root)
    if not is_maps_dataset(root):
        raise FileNotFoundError(f"{root} is not a maps dataset (no {INFO_JSON} with format {FORMAT!r})")
    return MapsDataset(root, MapsInfo.from_json(load_json(root / INFO_JSON)))
