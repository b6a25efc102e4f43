"""Write a LeRobot dataset in layout v3.0 with pyarrow and PyAV, as LeRobot 0.6.1's recorder lays it out, so that
LeRobot's own `LeRobotDataset` (and `lerobot.dataset.open_dataset`) opens it.

    writer = create_dataset(root, fps=10, features={**cameras, **numeric, **OUTCOME_FEATURES}, robot_type="...")
    writer.add_frame({...})                      # one per step: every declared feature, nothing else
    writer.save_episode(task="reach the red block")
    writer.finalize()

What lands on disk (paths as LeRobot names them):

- `data/chunk-CCC/file-FFF.parquet`: one row per frame, one row group per episode; image cameras as PNG bytes.
- `videos/<camera>/chunk-CCC/file-FFF.mp4`: video cameras, episodes one after another in the file (`lerobot.video`).
- `meta/episodes/chunk-CCC/file-FFF.parquet`: one row per episode: its length, tasks, where its rows and video
  segments are, and its statistics (`stats/<feature>/<stat>`, `lerobot.stats`).
- `meta/tasks.parquet`, `meta/stats.json` (statistics over all episodes), `meta/info.json`.

The jobs split as LeRobot splits them: this module the data and metadata files (LeRobot's dataset writer),
`lerobot.stats` the statistics (its `compute_stats`), `lerobot.video` the videos (its `video_utils`).

A file takes episodes until the next one would push it past `data_files_size_in_mb` / `video_files_size_in_mb`;
then the next file index is used, and the next chunk after `chunks_size` files.

Every `save_episode` leaves a complete dataset: each file it changes is written whole beside the dataset (in
`.staging/`) and moved into place, the episode metadata and info.json last. A crash while an episode is recorded, or
while it is saved, leaves the episodes saved before it readable. The price is that appending an episode rewrites the
current data file and remuxes the current video files (LeRobot remuxes its video files the same way).

Outcome features are ordinary features: `OUTCOME_FEATURES` declares them as `lerobot-eval --eval.recording=true`
does (`next.reward` float32, `next.success` and `next.done` bool, each of shape [1]).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from openpi_cam.lerobot.dataset import CAMERA_DTYPES, DatasetError, dataset_error
from openpi_cam.lerobot.stats import Stats, camera_stats, feature_stats, merge_stats
from openpi_cam.lerobot.video import (
    VideoEncodingError,
    VideoOptions,
    append_video,
    duration_s,
    encode_video,
    video_info,
)

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
STAGING = ".staging"
CAMERA_NAMES = ("height", "width", "channels")
PNG_COMPRESS_LEVEL = 6  # what LeRobot uses for image-dtype cameras
MB = 1024**2
SUPPORTED_DTYPES = ("bool", "float32", "float64", *(f"{s}int{b}" for s in ("", "u") for b in (8, 16, 32, 64)))


@dataclass(frozen=True)
class Feature:
    """One feature as info.json declares it. `dtype`: "video" or "image" for a camera (uint8 [H, W, 3] frames), else
    a numpy dtype name; numeric features have shape [1] (a scalar per frame) or [n]."""

    dtype: str
    shape: tuple[int, ...]
    names: tuple[str, ...] | None = None

    @classmethod
    def camera(cls, height: int, width: int, *, video: bool = True) -> Feature:
        return cls("video" if video else "image", (height, width, 3), CAMERA_NAMES)

    @property
    def is_camera(self) -> bool:
        return self.dtype in CAMERA_DTYPES

    def info(self) -> dict[str, Any]:
        return {
            "dtype": self.dtype,
            "shape": list(self.shape),
            "names": None if self.names is None else list(self.names),
        }


# What followed a frame's action, by lerobot-eval's names.
REWARD, SUCCESS, DONE = "next.reward", "next.success", "next.done"
OUTCOME_FEATURES: dict[str, Feature] = {
    REWARD: Feature("float32", (1,)),
    SUCCESS: Feature("bool", (1,)),
    DONE: Feature("bool", (1,)),
}
# Written by the writer for every frame; a frame may not carry them.
DEFAULT_FEATURES: dict[str, Feature] = {
    "timestamp": Feature("float32", (1,)),
    "frame_index": Feature("int64", (1,)),
    "episode_index": Feature("int64", (1,)),
    "index": Feature("int64", (1,)),
    "task_index": Feature("int64", (1,)),
}


# --- files -----------------------------------------------------------------------------------------------------


def _arrow_type(feature: Feature) -> pa.DataType:
    if feature.dtype == "image":
        return pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    scalar = pa.from_numpy_dtype(np.dtype(feature.dtype))
    # `datasets` names a list's items "element"; the name is part of the parquet schema
    return scalar if feature.shape == (1,) else pa.list_(pa.field("element", scalar), feature.shape[0])


def _hf_feature(feature: Feature) -> dict[str, Any]:
    """The feature as the `datasets` library describes it in a parquet file's schema metadata."""
    if feature.dtype == "image":
        return {"_type": "Image"}
    value = {"dtype": feature.dtype, "_type": "Value"}
    return value if feature.shape == (1,) else {"feature": value, "length": feature.shape[0], "_type": "List"}


def _tasks_table(tasks: list[str]) -> pa.Table:
    """meta/tasks.parquet as pandas writes a frame indexed by the task string, so that LeRobot's pandas reader gets
    the strings back as the index it looks tasks up in."""
    pandas = {
        "index_columns": ["task"],
        "column_indexes": [
            {
                "name": None,
                "field_name": None,
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": {"encoding": "UTF-8"},
            }
        ],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64"},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object"},
        ],
        "attributes": {},
        "creator": {"library": "pyarrow", "version": pa.__version__},
    }
    for column in pandas["columns"]:
        column["metadata"] = None
    schema = pa.schema([("task_index", pa.int64()), ("task", pa.string())], metadata={"pandas": json.dumps(pandas)})
    return pa.table({"task_index": list(range(len(tasks))), "task": tasks}, schema=schema)


def _png(frame: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buffer.getvalue()


def _next_file(chunk: int, file: int, chunks_size: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)


@dataclass(frozen=True)
class _Slot:
    """A file episodes are appended to: its chunk and file index, the episodes (and frames) it holds and, for a video,
    where the next episode starts in it."""

    chunk: int = 0
    file: int = 0
    episodes: int = 0
    frames: int = 0
    end_s: float = 0.0


def _json(value: Any) -> bytes:
    return json.dumps(value, indent=4, ensure_ascii=False).encode()


@dataclass
class _Frame:
    values: dict[str, Any]
    task: str | None


class DatasetWriter:
    """Records episodes into a new LeRobot v3.0 dataset; made by `create_dataset`.

    Frames are held in memory until `save_episode` writes them. A context manager: leaving the `with` block
    finalizes the dataset, or, when an exception leaves it, drops the unsaved episode and keeps the saved ones."""

    def __init__(
        self,
        root: Path,
        fps: int,
        features: dict[str, Feature],
        robot_type: str | None,
        video: VideoOptions,
        chunks_size: int,
        data_files_size_in_mb: float,
        video_files_size_in_mb: float,
    ):
        self.root = root
        self.fps = fps
        self.features = {**features, **DEFAULT_FEATURES}
        self.video = video
        self.videos = [name for name, f in features.items() if f.dtype == "video"]
        self._schema = pa.schema(
            [(name, _arrow_type(f)) for name, f in self.features.items() if f.dtype != "video"],
            metadata={"huggingface": json.dumps({"info": {"features": self._hf_features()}})},
        )
        self._info: dict[str, Any] = {
            "codebase_version": CODEBASE_VERSION,
            "fps": fps,
            "features": {name: f.info() for name, f in self.features.items()},
            "total_episodes": 0,
            "total_frames": 0,
            "total_tasks": 0,
            "chunks_size": chunks_size,
            "data_files_size_in_mb": data_files_size_in_mb,
            "video_files_size_in_mb": video_files_size_in_mb,
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.videos else None,
            "robot_type": robot_type,
            "splits": {},
        }
        self.tasks: list[str] = []
        self.stats: dict[str, Stats] = {}
        self._frames: list[_Frame] = []
        self._data = _Slot()
        self._meta, self._meta_rows = _Slot(), []  # the rows of the current episode metadata file
        self._videos = {name: _Slot() for name in self.videos}
        self._finalized = False
        self._staging = root / STAGING
        self._staging.mkdir(parents=True)
        self._commit({root / "meta" / "info.json": _json(self._info)})

    # -- public API ---------------------------------------------------------------------------------------------

    @property
    def num_episodes(self) -> int:
        return self._info["total_episodes"]

    @property
    def num_frames(self) -> int:
        return self._info["total_frames"]

    @property
    def pending_frames(self) -> int:
        return len(self._frames)

    def add_frame(self, frame: Mapping[str, Any], *, task: str | None = None) -> None:
        """Adds one frame to the current episode: every declared feature (cameras uint8 [H, W, 3]; numeric values
        of the declared dtype and shape; a shape-[1] feature may also be a scalar, a Python scalar of the matching
        kind being converted). `task` overrides the episode's task (`save_episode(task=)`) for this frame."""
        self._check_open()
        where = {"file": self.root, "episode": self.num_episodes}
        step = len(self._frames)
        extra = [name for name in frame if name not in self.features or name in DEFAULT_FEATURES]
        if extra:
            problem = "is set by the writer" if extra[0] in DEFAULT_FEATURES else "is not a declared feature"
            raise dataset_error(f"frame {step}: {problem}", **where, feature=extra[0])
        missing = [name for name in self.features if name not in DEFAULT_FEATURES and name not in frame]
        if missing:
            raise dataset_error(f"frame {step}: missing", **where, feature=missing[0])
        if task is not None and (not isinstance(task, str) or not task):
            raise dataset_error(f"frame {step}: the task must be a non-empty string, got {task!r}", **where)
        values = {name: self._checked(name, frame[name], step) for name in frame}
        self._frames.append(_Frame(values, task))

    def clear_episode(self) -> None:
        """Drops the frames added since the last saved episode."""
        self._frames = []

    def save_episode(self, *, task: str | None = None) -> int:
        """Writes the frames added since the last call as the next episode and returns its index. `task`: the
        prompt of every frame that was added without one."""
        self._check_open()
        episode = self.num_episodes
        where = {"file": self.root, "episode": episode}
        if not self._frames:
            raise dataset_error("no frames added since the last saved episode", **where)
        if task is not None and (not isinstance(task, str) or not task):
            raise dataset_error(f"the task must be a non-empty string, got {task!r}", **where)
        frame_tasks = []
        for step, frame in enumerate(self._frames):
            if frame.task is None and task is None:
                raise dataset_error(f"frame {step} has no task: pass task= to save_episode or add_frame", **where)
            frame_tasks.append(frame.task or task)
        try:
            self._write_episode(episode, frame_tasks)
        finally:
            shutil.rmtree(self._staging, ignore_errors=True)
            self._staging.mkdir()
        self._frames = []
        return episode

    def finalize(self) -> None:
        """Ends recording. Unsaved frames are an error (save or clear them first); a second call does nothing."""
        if self._finalized:
            return
        if self._frames:
            raise dataset_error(
                f"{len(self._frames)} frames added but not saved (save_episode or clear_episode first)",
                file=self.root,
                episode=self.num_episodes,
            )
        shutil.rmtree(self._staging, ignore_errors=True)
        self._finalized = True

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self._frames = []
        self.finalize()

    # -- checks -------------------------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._finalized:
            raise dataset_error("the writer is finalized", file=self.root)

    def _checked(self, name: str, value: Any, step: int) -> Any:
        feature = self.features[name]
        where = {"file": self.root, "episode": self.num_episodes, "feature": name}
        if feature.is_camera:
            if not isinstance(value, np.ndarray) or value.dtype != np.uint8 or value.shape != feature.shape:
                got = f"{value.dtype} {list(value.shape)}" if isinstance(value, np.ndarray) else type(value).__name__
                raise dataset_error(f"frame {step}: a camera frame is uint8 {list(feature.shape)}, got {got}", **where)
            return value.copy()
        dtype = np.dtype(feature.dtype)
        if isinstance(value, np.ndarray | np.generic):
            if value.dtype != dtype:
                raise dataset_error(f"frame {step}: dtype {value.dtype}, the feature is {dtype}", **where)
            array = np.array(value)
        elif isinstance(value, bool | int | float) and _fits(value, dtype):
            array = np.array(value, dtype)
        else:
            raise dataset_error(f"frame {step}: a {type(value).__name__} where the feature is {dtype}", **where)
        if array.shape != feature.shape and not (array.shape == () and feature.shape == (1,)):
            raise dataset_error(
                f"frame {step}: shape {list(array.shape)}, the feature is {list(feature.shape)}", **where
            )
        return array.reshape(feature.shape)

    # -- writing ------------------------------------------------------------------------------------------------

    def _hf_features(self) -> dict[str, Any]:
        return {name: _hf_feature(f) for name, f in self.features.items() if f.dtype != "video"}

    def _columns(self, episode: int, task_indices: list[int]) -> dict[str, np.ndarray]:
        """Every non-camera feature of the episode as one array [frames, *shape] (shape-[1] ones as [frames])."""
        n = len(self._frames)
        frame_index = np.arange(n, dtype=np.int64)
        columns = {
            # LeRobot keeps the timestamps as Python floats until the parquet stores them as float32
            "timestamp": frame_index / self.fps,
            "frame_index": frame_index,
            "episode_index": np.full(n, episode, np.int64),
            "index": np.arange(self.num_frames, self.num_frames + n, dtype=np.int64),
            "task_index": np.array(task_indices, np.int64),
        }
        for name, feature in self.features.items():
            if name not in DEFAULT_FEATURES and not feature.is_camera:
                stacked = np.stack([frame.values[name] for frame in self._frames])
                columns[name] = stacked.reshape(n) if feature.shape == (1,) else stacked
        return columns

    def _episode_table(self, columns: dict[str, np.ndarray]) -> pa.Table:
        arrays = []
        for schema_field in self._schema:
            name, feature = schema_field.name, self.features[schema_field.name]
            if feature.dtype == "image":
                items = [
                    {"bytes": _png(frame.values[name]), "path": f"frame-{i:06d}.png"}
                    for i, frame in enumerate(self._frames)
                ]
                arrays.append(pa.array(items, schema_field.type))
            elif feature.shape == (1,):
                arrays.append(pa.array(columns[name].astype(feature.dtype), schema_field.type))
            else:
                flat = pa.array(columns[name].reshape(-1))
                arrays.append(pa.FixedSizeListArray.from_arrays(flat, type=schema_field.type))
        return pa.Table.from_arrays(arrays, schema=self._schema)

    def _write_episode(self, episode: int, frame_tasks: list[str]) -> None:
        """Stages every file the episode changes (its data, its videos, its statistics, then the metadata), moves them
        into place, then advances the writer's state: a failure before the last move leaves the state as it was, so
        that saving again rewrites the same files."""
        writes: dict[Path, Path | bytes] = {}  # final path -> staged file or content, in the order they move
        episode_tasks = list(dict.fromkeys(frame_tasks))
        tasks = self.tasks + [t for t in episode_tasks if t not in self.tasks]
        if len(tasks) > len(self.tasks):
            writes[self.root / "meta" / "tasks.parquet"] = self._staged_table("tasks.parquet", _tasks_table(tasks))
        columns = self._columns(episode, [tasks.index(t) for t in frame_tasks])
        data, row = self._stage_data(columns, writes)
        info = json.loads(json.dumps(self._info))
        videos = self._stage_videos(episode, row, info, writes)
        episode_stats = self._episode_stats(columns)
        meta, rows = self._stage_episode_row(
            {"episode_index": episode, "tasks": episode_tasks, "length": len(self._frames), **row},
            episode_stats,
            writes,
        )
        stats = {
            name: merge_stats(self.stats[name], value) if name in self.stats else value
            for name, value in episode_stats.items()
        }
        writes[self.root / "meta" / "stats.json"] = _json(
            {name: {key: value.tolist() for key, value in s.items()} for name, s in stats.items()}
        )
        info |= {
            "total_episodes": episode + 1,
            "total_frames": self.num_frames + len(self._frames),
            "total_tasks": len(tasks),
            "splits": {"train": f"0:{episode + 1}"},
        }
        writes[self.root / "meta" / "info.json"] = _json(info)

        self._commit(writes)
        self.tasks, self.stats, self._info = tasks, stats, info
        self._data, self._meta, self._meta_rows = data, meta, rows
        self._videos |= videos

    def _next_slot(self, slot: _Slot) -> _Slot:
        return _Slot(*_next_file(slot.chunk, slot.file, self._info["chunks_size"]))

    def _stage_data(self, columns: dict[str, np.ndarray], writes: dict[Path, Path | bytes]) -> tuple[_Slot, dict]:
        """The data file with the episode's rows appended (or a new file), and the episode row's data fields. A file
        takes the episode unless its size, grown by the episode's share at the file's size per frame so far, would
        reach the limit (LeRobot's rule)."""
        n = len(self._frames)
        data = self._data
        previous = self._path(DATA_PATH, data) if data.episodes else None
        if previous and previous.stat().st_size / MB * (1 + n / data.frames) >= self._info["data_files_size_in_mb"]:
            data, previous = self._next_slot(data), None
        writes[self._path(DATA_PATH, data)] = self._staged_data(self._episode_table(columns), previous, data.episodes)
        row = {
            "data/chunk_index": data.chunk,
            "data/file_index": data.file,
            "dataset_from_index": self.num_frames,
            "dataset_to_index": self.num_frames + n,
        }
        return dataclasses.replace(data, episodes=data.episodes + 1, frames=data.frames + n), row

    def _stage_videos(
        self, episode: int, row: dict[str, Any], info: dict[str, Any], writes: dict[Path, Path | bytes]
    ) -> dict[str, _Slot]:
        """Each video camera's episode encoded and appended to the camera's current file (or a new one past the
        size limit); its segment goes into the episode `row`, and the first episode's stream into `info`."""
        videos = {}
        for name in self.videos:
            encoded = self._staging / f"{name}.episode.mp4"
            try:
                encode_video([frame.values[name] for frame in self._frames], encoded, self.fps, self.video)
            except VideoEncodingError as e:
                raise dataset_error(
                    f"video encoding failed ({e})", file=self.root, episode=episode, feature=name
                ) from e
            slot = self._videos[name]
            path = self._path(VIDEO_PATH, slot, video_key=name)
            if (
                slot.episodes
                and (path.stat().st_size + encoded.stat().st_size) / MB >= self._info["video_files_size_in_mb"]
            ):
                slot = self._next_slot(slot)
            staged = encoded
            if slot.episodes:
                staged = self._staging / f"{name}.mp4"
                append_video(path, encoded, slot.end_s, staged)
            writes[self._path(VIDEO_PATH, slot, video_key=name)] = staged
            end_s = slot.end_s + duration_s(encoded)
            row |= {
                f"videos/{name}/chunk_index": slot.chunk,
                f"videos/{name}/file_index": slot.file,
                f"videos/{name}/from_timestamp": slot.end_s,
                f"videos/{name}/to_timestamp": end_s,
            }
            videos[name] = dataclasses.replace(slot, episodes=slot.episodes + 1, end_s=end_s)
            if episode == 0:
                info["features"][name]["info"] = video_info(encoded, self.video)
        return videos

    def _stage_episode_row(
        self, row: dict[str, Any], episode_stats: dict[str, Stats], writes: dict[Path, Path | bytes]
    ) -> tuple[_Slot, list[dict[str, Any]]]:
        """The episode metadata file with the episode's row (its statistics included) appended, or a new file."""
        row = row | {
            f"stats/{name}/{key}": value.tolist() for name, s in episode_stats.items() for key, value in s.items()
        }
        meta, rows = self._meta, self._meta_rows
        path = self._path(EPISODES_PATH, meta)
        if meta.episodes and path.stat().st_size / MB * (1 + 1 / meta.episodes) >= self._info["data_files_size_in_mb"]:
            meta, rows = self._next_slot(meta), []
        rows = [*rows, row | {"meta/episodes/chunk_index": meta.chunk, "meta/episodes/file_index": meta.file}]
        writes[self._path(EPISODES_PATH, meta)] = self._staged_table("episodes.parquet", pa.Table.from_pylist(rows))
        return dataclasses.replace(meta, episodes=meta.episodes + 1), rows

    def _episode_stats(self, columns: dict[str, np.ndarray]) -> dict[str, Stats]:
        """Each feature's statistics over the episode (`lerobot.stats`), in the features' order."""
        stats = {}
        for name, feature in self.features.items():
            if feature.is_camera:
                stats[name] = camera_stats([frame.values[name] for frame in self._frames])
            else:
                values = columns[name]
                stats[name] = feature_stats(values.reshape(len(values), -1), len(values))
        return stats

    def _staged_data(self, table: pa.Table, previous: Path | None, episodes: int) -> Path:
        """The data file with the episode appended after the first `episodes` row groups (one per episode) of the
        `previous` file: rows of an episode whose save failed after its data file moved are left out."""
        out = self._staging / "data.parquet"
        with pq.ParquetWriter(out, self._schema, compression="snappy", use_dictionary=True) as writer:
            if previous is not None:
                source = pq.ParquetFile(previous)
                for group in range(episodes):
                    writer.write_table(source.read_row_group(group))
            writer.write_table(table)
        return out

    def _path(self, template: str, slot: _Slot, **fields: str) -> Path:
        return self.root / template.format(chunk_index=slot.chunk, file_index=slot.file, **fields)

    def _staged_table(self, name: str, table: pa.Table) -> Path:
        out = self._staging / name
        pq.write_table(table, out, compression="snappy")
        return out

    def _commit(self, writes: dict[Path, Path | bytes]) -> None:
        """Moves every staged file into place in the order given: tasks, data and videos first, then the episode
        metadata, stats.json and info.json, so that until the metadata lands readers see the dataset as it was."""
        for path in writes:
            content = writes[path]
            path.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, bytes):
                staged = self._staging / f"{path.name}.staged"
                staged.write_bytes(content)
                content = staged
            os.replace(content, path)


def _fits(value: bool | int | float, dtype: np.dtype) -> bool:
    """Whether a Python scalar may stand for a value of `dtype`: bools for bool, ints for ints and floats, floats for
    floats."""
    if isinstance(value, bool):
        return dtype.kind == "b"
    if isinstance(value, int):
        return dtype.kind in "iuf"
    return dtype.kind == "f"


def create_dataset(
    root: str | Path,
    *,
    fps: int,
    features: Mapping[str, Feature],
    robot_type: str | None = None,
    video: VideoOptions | None = None,
    chunks_size: int = 1000,
    data_files_size_in_mb: float = 100,
    video_files_size_in_mb: float = 200,
) -> DatasetWriter:
    """A writer for a new dataset at `root` (absent or an empty folder). `features`: the recorded features in the
    order info.json lists them; the writer adds timestamp, frame_index, episode_index, index and task_index."""
    root = Path(root)
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise dataset_error("exists and is not an empty folder: a new dataset needs its own root", file=root)
    if not isinstance(fps, int) or fps <= 0:
        raise dataset_error(f"fps must be a positive int, got {fps!r}", file=root)
    sizes = {
        "chunks_size": chunks_size,
        "data_files_size_in_mb": data_files_size_in_mb,
        "video_files_size_in_mb": video_files_size_in_mb,
    }
    for key, value in sizes.items():
        if value <= 0:
            raise dataset_error(f"{key} must be positive, got {value!r}", file=root)
    checked = {name: _checked_feature(root, name, feature) for name, feature in features.items()}
    video = video or VideoOptions()
    if any(f.dtype == "video" for f in checked.values()):
        try:
            av.codec.Codec(video.codec, "w")
        except (av.FFmpegError, ValueError) as e:
            raise dataset_error(
                f"PyAV has no {video.codec!r} encoder here ({e}); pick VideoOptions(codec=)", file=root
            ) from e
    root.mkdir(parents=True, exist_ok=True)
    return DatasetWriter(
        root, fps, checked, robot_type, video, chunks_size, data_files_size_in_mb, video_files_size_in_mb
    )


def _checked_feature(root: Path, name: str, feature: Any) -> Feature:
    where = {"file": root, "feature": name}
    if not isinstance(feature, Feature):
        raise dataset_error(f"declare features as Feature, got {type(feature).__name__}", **where)
    if "/" in name or not name:
        raise dataset_error("a feature name must be non-empty and hold no '/'", **where)
    if name in DEFAULT_FEATURES or name == "task":
        raise dataset_error("is written by the writer; do not declare it", **where)
    shape = tuple(int(s) for s in feature.shape)
    if feature.is_camera:
        if len(shape) != 3 or shape[2] != 3 or min(shape) <= 0:
            raise dataset_error(f"a camera's shape is [height, width, 3], got {list(shape)}", **where)
    elif feature.dtype not in SUPPORTED_DTYPES:
        raise dataset_error(
            f"dtype {feature.dtype!r} is not one of video, image, {', '.join(SUPPORTED_DTYPES)}", **where
        )
    elif len(shape) != 1 or shape[0] <= 0:
        raise dataset_error(f"a numeric feature has shape [n], got {list(shape)}", **where)
    names = None if feature.names is None else tuple(feature.names)
    return Feature(feature.dtype, shape, names)


__all__ = [
    "DEFAULT_FEATURES",
    "DONE",
    "OUTCOME_FEATURES",
    "REWARD",
    "SUCCESS",
    "DatasetError",
    "DatasetWriter",
    "Feature",
    "create_dataset",
]
