"""Write a LeRobot dataset in layout v3.0 with pyarrow and PyAV, as LeRobot 0.6.1's recorder lays it out, so that
LeRobot's own `LeRobotDataset` (and `datasets.lerobot.open_dataset`) opens it.

    writer = create_dataset(root, fps=10, features={**cameras, **numeric, **OUTCOME_FEATURES}, robot_type="...")
    writer.add_frame({...})                      # one per step: every declared feature, nothing else
    writer.save_episode(task="reach the red block")
    writer.finalize()

What lands on disk (paths as LeRobot names them):

- `data/chunk-CCC/file-FFF.parquet`: one row per frame, one row group per episode; image cameras as PNG bytes.
- `videos/<camera>/chunk-CCC/file-FFF.mp4`: video cameras, episodes one after another in the file, each encoded on
  its own (AV1 through libsvtav1, yuv420p, keyframe every 2 frames: LeRobot's defaults) and starting on a keyframe.
- `meta/episodes/chunk-CCC/file-FFF.parquet`: one row per episode: its length, tasks, where its rows and video
  segments are, and its statistics (`stats/<feature>/<stat>`).
- `meta/tasks.parquet`, `meta/stats.json` (statistics over all episodes), `meta/info.json`.

A file takes episodes until the next one would push it past `data_files_size_in_mb` / `video_files_size_in_mb`;
then the next file index is used, and the next chunk after `chunks_size` files.

Every `save_episode` leaves a complete dataset: each file it changes is written whole beside the dataset (in
`.staging/`) and moved into place, the episode metadata and info.json last. A crash while an episode is recorded, or
while it is saved, leaves the episodes saved before it readable. The price is that appending an episode rewrites the
current data file and remuxes the current video files (LeRobot remuxes its video files the same way).

Statistics follow LeRobot's definitions, so that its normalisers read the numbers they expect: per episode, min /
max / mean / std and the 1, 10, 50, 90, 99 % quantiles from a 5000-bin histogram (cameras: per channel over a
sample of the episode's frames, in [0, 1]); across episodes, count-weighted means and variances, and quantiles
averaged with the counts as weights.

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

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
STAGING = ".staging"
CAMERA_NAMES = ("height", "width", "channels")
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
HISTOGRAM_BINS = 5000
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


@dataclass(frozen=True)
class VideoOptions:
    """How video cameras are encoded; recorded in info.json as LeRobot records its encoder settings. The defaults
    are LeRobot 0.6.1's. `preset` None: 12 for libsvtav1, the encoder's own default otherwise."""

    codec: str = "libsvtav1"
    pix_fmt: str = "yuv420p"
    gop: int = 2
    crf: int | None = 30
    preset: int | str | None = None
    fast_decode: int = 0

    @property
    def resolved_preset(self) -> int | str | None:
        return 12 if self.preset is None and self.codec == "libsvtav1" else self.preset

    def codec_options(self) -> dict[str, str]:
        options = {"g": str(self.gop)}
        if self.crf is not None:
            options["crf"] = str(self.crf)
        if self.resolved_preset is not None:
            options["preset"] = str(self.resolved_preset)
        if self.codec == "libsvtav1":
            options["svtav1-params"] = f"fast-decode={max(0, min(2, self.fast_decode))}"
        elif self.fast_decode and self.codec in ("libx264", "h264", "libx265", "hevc"):
            options["tune"] = "fastdecode"
        return options

    def recorded(self) -> dict[str, Any]:
        return {
            "video.g": self.gop,
            "video.crf": self.crf,
            "video.preset": self.resolved_preset,
            "video.fast_decode": self.fast_decode,
            "video.video_backend": "pyav",
            "video.extra_options": {},
        }


# --- statistics ------------------------------------------------------------------------------------------------

Stats = dict[str, np.ndarray]


def _quantile(histogram: np.ndarray, edges: np.ndarray, target: float) -> Any:
    """Where the cumulative histogram reaches `target` counts, interpolated inside the bin (LeRobot's estimate:
    a target in the first bin reads as the lowest edge)."""
    cumulative = np.cumsum(histogram)
    i = int(np.searchsorted(cumulative, target))
    if i == 0:
        return edges[0]
    if i >= len(cumulative):
        return edges[-1]
    below = cumulative[i - 1]
    inside = cumulative[i] - below
    if inside == 0:
        return edges[i]
    return edges[i] + (target - below) / inside * (edges[i + 1] - edges[i])


def _vector_stats(values: np.ndarray, count: int) -> Stats:
    """Statistics per column of `values` [rows, columns]; `count` is what the rows stand for (frames)."""
    values = values.astype(np.result_type(values.dtype, np.float32), copy=False)
    if values.shape[0] < 2:
        mean = np.mean(values, axis=0)
        stats = {"min": values.min(axis=0), "max": values.max(axis=0), "mean": mean, "std": np.std(values, axis=0)}
        return {**stats, "count": np.array([count])} | {_quantile_key(q): mean.copy() for q in QUANTILES}
    low, high = values.min(axis=0), values.max(axis=0)
    mean = np.mean(values, axis=0)
    variance = np.mean(values**2, axis=0) - mean**2
    quantiles: list[list[Any]] = [[] for _ in QUANTILES]
    for column in range(values.shape[1]):
        # the edges carry the data's dtype, as LeRobot's do; 1e-10 keeps the extremes inside the outer bins
        edges = np.linspace(low[column] - 1e-10, high[column] + 1e-10, HISTOGRAM_BINS + 1)
        histogram = np.histogram(values[:, column], bins=edges)[0].astype(np.float64)
        for q, out in zip(QUANTILES, quantiles, strict=True):
            out.append(_quantile(histogram, edges, q * values.shape[0]))
    return {
        "min": low,
        "max": high,
        "mean": mean,
        "std": np.sqrt(np.maximum(0, variance)),
        "count": np.array([count]),
    } | {_quantile_key(q): np.array(out) for q, out in zip(QUANTILES, quantiles, strict=True)}


def _quantile_key(q: float) -> str:
    return f"q{int(q * 100):02d}"


def _sampled(n: int) -> list[int]:
    """The frames of an n-frame episode whose pixels enter a camera's statistics: all of them up to 100, then
    n^0.75 spread evenly (at most 10,000)."""
    count = max(min(n, 100), min(int(n**0.75), 10_000))
    return np.round(np.linspace(0, n - 1, count)).astype(int).tolist()


def _camera_stats(frames: list[np.ndarray]) -> Stats:
    """Per-channel statistics in [0, 1], shape [3, 1, 1], over a sample of the frames (every k-th pixel of frames
    300 px or larger, k bringing the long side near 150 px)."""
    sample = np.stack([frames[i] for i in _sampled(len(frames))])
    height, width = sample.shape[1:3]
    if max(height, width) >= 300:
        step = int(width / 150) if width > height else int(height / 150)
        sample = sample[:, ::step, ::step]
    stats = _vector_stats(sample.reshape(-1, sample.shape[-1]), len(sample))
    return {key: value if key == "count" else value.reshape(-1, 1, 1) / 255.0 for key, value in stats.items()}


def _merge_stats(a: Stats, b: Stats) -> Stats:
    """Statistics of the union of two sets of frames from the statistics of each."""
    means, counts = np.stack([a["mean"], b["mean"]]), np.stack([a["count"], b["count"]])
    total = counts.sum(axis=0)
    weights = counts.reshape(counts.shape + (1,) * (means.ndim - counts.ndim))
    mean = (means * weights).sum(axis=0) / total
    # each std squared in its own dtype before the two are stacked, as LeRobot does it: the float32 of an episode's
    # camera statistics is then kept
    variances = np.stack([a["std"] ** 2, b["std"] ** 2])
    variance = ((variances + (means - mean) ** 2) * weights).sum(axis=0) / total
    merged = {
        "min": np.minimum(a["min"], b["min"]),
        "max": np.maximum(a["max"], b["max"]),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": total,
    }
    for key in map(_quantile_key, QUANTILES):
        merged[key] = (np.stack([a[key], b[key]]) * weights).sum(axis=0) / total
    return merged


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


def _encode_video(frames: list[np.ndarray], path: Path, fps: int, options: VideoOptions) -> None:
    height, width = frames[0].shape[:2]
    # SVT-AV1 prints a banner of some twenty lines to stderr for every encoder it opens unless SVT_LOG lowers its
    # level; errors still show, and a level the user set wins
    os.environ.setdefault("SVT_LOG", "1")
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream(options.codec, rate=fps, options=options.codec_options())
        stream.pix_fmt = options.pix_fmt
        stream.width, stream.height = width, height
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())


def _duration_s(path: Path) -> float:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        if stream.duration is not None:
            return float(stream.duration * stream.time_base)
        return float(container.duration / av.time_base)


def _append_video(head: Path, tail: Path, offset_s: float, out: Path) -> None:
    """`head`'s packets before `offset_s`, then `tail`'s moved there, stream-copied into `out` (no re-encoding).
    Packets of `head` past `offset_s` belong to an episode whose save failed after its video moved."""
    with av.open(str(head)) as first, av.open(str(tail)) as second:
        a, b = first.streams.video[0], second.streams.video[0]
        if a.time_base != b.time_base or a.codec_context.name != b.codec_context.name:
            raise dataset_error(f"cannot append a {b.codec_context.name} video in time base {b.time_base}", file=head)
        offset = round(offset_s / a.time_base)
        with av.open(str(out), "w", format="mp4", options={"movflags": "faststart"}) as container:
            stream = container.add_stream_from_template(a, opaque=True)
            stream.time_base = a.time_base
            for source, shift in ((first.demux(a), 0), (second.demux(b), offset)):
                for packet in source:
                    if packet.dts is None or (shift == 0 and packet.pts >= offset):  # None: the demuxer's flush
                        continue
                    packet.pts += shift
                    packet.dts += shift
                    packet.stream = stream
                    container.mux(packet)


def _video_info(path: Path, options: VideoOptions) -> dict[str, Any]:
    """info.json's `info` of a video camera: what the encoded stream says, then the encoder settings."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        info = {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec.canonical_name,
            "video.pix_fmt": stream.pix_fmt,
            "video.fps": int(stream.base_rate),
            "video.channels": len(av.VideoFormat(stream.pix_fmt).components),
            "has_audio": bool(container.streams.audio),
        }
    return info | options.recorded() | {"is_depth_map": False}


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
        """Stages every file the episode changes, moves them into place, then advances the writer's state: a failure
        before the last move leaves the state as it was, so that saving again rewrites the same files."""
        writes: dict[Path, Path | bytes] = {}  # final path -> staged file or content, in the order they move
        episode_tasks = list(dict.fromkeys(frame_tasks))
        tasks = self.tasks + [t for t in episode_tasks if t not in self.tasks]
        if len(tasks) > len(self.tasks):
            writes[self.root / "meta" / "tasks.parquet"] = self._staged_table("tasks.parquet", _tasks_table(tasks))
        columns = self._columns(episode, [tasks.index(t) for t in frame_tasks])
        n = len(self._frames)
        chunks_size, data_mb, video_mb = (
            self._info[key] for key in ("chunks_size", "data_files_size_in_mb", "video_files_size_in_mb")
        )

        # a file takes the episode unless its size, grown by the episode's share at the file's size per frame so far,
        # would reach the limit (LeRobot's rule)
        data = self._data
        previous = self._path(DATA_PATH, data) if data.episodes else None
        if previous and previous.stat().st_size / MB * (1 + n / data.frames) >= data_mb:
            data, previous = _Slot(*_next_file(data.chunk, data.file, chunks_size)), None
        writes[self._path(DATA_PATH, data)] = self._staged_data(self._episode_table(columns), previous, data.episodes)
        row: dict[str, Any] = {
            "episode_index": episode,
            "tasks": episode_tasks,
            "length": n,
            "data/chunk_index": data.chunk,
            "data/file_index": data.file,
            "dataset_from_index": self.num_frames,
            "dataset_to_index": self.num_frames + n,
        }

        info = json.loads(json.dumps(self._info))
        videos = {}
        for name in self.videos:
            encoded = self._staging / f"{name}.episode.mp4"
            try:
                _encode_video([frame.values[name] for frame in self._frames], encoded, self.fps, self.video)
            except av.FFmpegError as e:
                raise dataset_error(
                    f"video encoding failed ({e})", file=self.root, episode=episode, feature=name
                ) from e
            slot = self._videos[name]
            path = self._path(VIDEO_PATH, slot, video_key=name)
            if slot.episodes and (path.stat().st_size + encoded.stat().st_size) / MB >= video_mb:
                slot = _Slot(*_next_file(slot.chunk, slot.file, chunks_size))
            staged = encoded
            if slot.episodes:
                staged = self._staging / f"{name}.mp4"
                _append_video(path, encoded, slot.end_s, staged)
            writes[self._path(VIDEO_PATH, slot, video_key=name)] = staged
            end_s = slot.end_s + _duration_s(encoded)
            row |= {
                f"videos/{name}/chunk_index": slot.chunk,
                f"videos/{name}/file_index": slot.file,
                f"videos/{name}/from_timestamp": slot.end_s,
                f"videos/{name}/to_timestamp": end_s,
            }
            videos[name] = dataclasses.replace(slot, episodes=slot.episodes + 1, end_s=end_s)
            if episode == 0:
                info["features"][name]["info"] = _video_info(encoded, self.video)

        episode_stats = self._episode_stats(columns)
        for name, stats in episode_stats.items():
            row |= {f"stats/{name}/{key}": value.tolist() for key, value in stats.items()}
        meta, rows = self._meta, self._meta_rows
        path = self._path(EPISODES_PATH, meta)
        if meta.episodes and path.stat().st_size / MB * (1 + 1 / meta.episodes) >= data_mb:
            meta, rows = _Slot(*_next_file(meta.chunk, meta.file, chunks_size)), []
        rows = [*rows, row | {"meta/episodes/chunk_index": meta.chunk, "meta/episodes/file_index": meta.file}]
        writes[self._path(EPISODES_PATH, meta)] = self._staged_table("episodes.parquet", pa.Table.from_pylist(rows))

        stats = {
            name: _merge_stats(self.stats[name], value) if name in self.stats else value
            for name, value in episode_stats.items()
        }
        writes[self.root / "meta" / "stats.json"] = _json(
            {name: {key: value.tolist() for key, value in s.items()} for name, s in stats.items()}
        )
        info |= {
            "total_episodes": episode + 1,
            "total_frames": self.num_frames + n,
            "total_tasks": len(tasks),
            "splits": {"train": f"0:{episode + 1}"},
        }
        writes[self.root / "meta" / "info.json"] = _json(info)

        self._commit(writes)
        self.tasks, self.stats, self._info = tasks, stats, info
        self._data = dataclasses.replace(data, episodes=data.episodes + 1, frames=data.frames + n)
        self._meta, self._meta_rows = dataclasses.replace(meta, episodes=meta.episodes + 1), rows
        self._videos |= videos

    def _episode_stats(self, columns: dict[str, np.ndarray]) -> dict[str, Stats]:
        stats = {}
        for name, feature in self.features.items():
            if feature.is_camera:
                stats[name] = _camera_stats([frame.values[name] for frame in self._frames])
            else:
                values = columns[name]
                stats[name] = _vector_stats(values.reshape(len(values), -1), len(values))
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
    "VideoOptions",
    "create_dataset",
]
