"""Read a LeRobot dataset frame by frame without torch: pyarrow for the parquet files, PyAV for the videos, Pillow
for images stored inside the parquet.

Two layouts are understood, told apart by `meta/info.json`'s `codebase_version`:

- v2.0 / v2.1: one data parquet per episode and one mp4 per episode and camera. `info.json`'s `data_path` and
  `video_path` are `str.format` templates over `episode_chunk` (episode index // `chunks_size`), `episode_index`
  and `video_key`. Episodes and their lengths come from `meta/episodes.jsonl`, task strings from `meta/tasks.jsonl`.
  A camera's frame sits at the frame's own `timestamp` in its episode's video.
- v3.0: episodes share files. `meta/episodes/chunk-*/file-*.parquet` holds one row per episode: its `length`, the
  data file it lives in (`data/chunk_index`, `data/file_index`) and, per camera, the video file
  (`videos/<key>/chunk_index`, `videos/<key>/file_index`) and where the episode's segment of that video starts and
  ends (`videos/<key>/from_timestamp`, `to_timestamp`). The templates are over `chunk_index`, `file_index` and
  `video_key`. A camera's frame sits at `from_timestamp` + the frame's `timestamp`. Task strings come from
  `meta/tasks.parquet` (pandas writes the task string, the frame's index there, as a column named `task`).

Camera frames are uint8 [H, W, 3] RGB. A video is decoded forward through the episode's segment: one open and one
seek per file and episode (to the first wanted frame, the episode's start unless `frame_indices` leaves it out),
then each wanted timestamp takes the decoded frame whose pts is nearest to it, as LeRobot does; only those frames
are converted to RGB.
Features whose info.json shape is [1] (`index`, `timestamp`, ...) come out as numpy scalars of their dtype; every
other numeric feature as an array of its info.json shape and dtype.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from collections.abc import Container, Generator, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from PIL import Image

from openpi_cam.errors import BadFile, load_json

CAMERA_DTYPES = ("video", "image")
# Columns every frame carries, whether or not the caller asked for them.
ALWAYS = ("index", "episode_index", "frame_index", "timestamp", "task_index")
V2_VERSIONS = ("v2.0", "v2.1")
V3_VERSIONS = ("v3.0",)


class DatasetError(BadFile):
    """A dataset that cannot be read as asked. The message is one line naming the file, episode and feature."""


def dataset_error(
    problem: str, *, file: Path | str | None = None, episode: int | None = None, feature: str | None = None
):
    """A `DatasetError` naming where the problem is: file, episode, feature (whichever are known)."""
    where = []
    if file is not None:
        where.append(str(file))
    if episode is not None:
        where.append(f"episode {episode}")
    if feature is not None:
        where.append(f"feature {feature!r}")
    text = f"{', '.join(where)}: {problem}" if where else problem
    return DatasetError(" ".join(text.split()))  # one line, whatever a wrapped library message held


@dataclass(frozen=True)
class _Video:
    path: Path
    from_timestamp: float
    to_timestamp: float | None  # None: the file is the episode's alone


@dataclass(frozen=True)
class _Episode:
    length: int
    data_path: Path
    videos: dict[str, _Video]


@dataclass
class LeRobotDataset:
    """An opened dataset: its metadata, read once, and `frames(episode)` to read one episode at a time.

    `video_opens` and `video_seeks` count the video containers opened and the seeks made, so that a caller can
    check the one-open, one-seek-per-file-and-episode promise."""

    root: Path
    version: str
    fps: int
    features: dict[str, dict]
    episodes: list[int]
    tolerance_s: float
    episode_info: dict[int, _Episode] = field(repr=False)
    task_names: dict[int, str] = field(repr=False)
    video_opens: int = 0
    video_seeks: int = 0

    @property
    def info_path(self) -> Path:
        return self.root / "meta" / "info.json"

    @property
    def camera_features(self) -> list[str]:
        return [name for name, spec in self.features.items() if spec.get("dtype") in CAMERA_DTYPES]

    def episode_length(self, episode: int) -> int:
        return self._episode(episode).length

    def tasks(self) -> dict[int, str]:
        return dict(self.task_names)

    def _episode(self, episode: int) -> _Episode:
        try:
            return self.episode_info[episode]
        except KeyError:
            raise dataset_error("no such episode in the dataset", file=self.info_path, episode=episode) from None

    def frames(
        self,
        episode: int,
        *,
        features: Sequence[str] | None = None,
        frame_indices: Container[int] | None = None,
    ) -> Iterator[dict[str, Any]]:
        """One dict per frame of `episode`, in frame order: every feature (or those in `features`, plus the
        columns in ALWAYS) by its dataset name, plus `task`, the task string. With `frame_indices`, only frames
        whose `frame_index` is in it are yielded; videos are still decoded forward in one pass."""
        info = self._episode(episode)
        names = self._selected(episode, features)
        return self._read(episode, info, names, frame_indices)

    def _selected(self, episode: int, features: Sequence[str] | None) -> list[str]:
        if features is None:
            wanted = set(self.features)
        else:
            if isinstance(features, str):
                features = [features]
            for name in features:
                if name not in self.features and name not in ALWAYS and name != "task":
                    raise dataset_error(
                        "not a feature of this dataset", file=self.info_path, episode=episode, feature=name
                    )
            wanted = set(features)
        wanted.update(ALWAYS)
        ordered = [name for name in self.features if name in wanted]
        return ordered + [name for name in ALWAYS if name not in ordered]

    def _read(
        self, episode: int, info: _Episode, names: list[str], frame_indices: Container[int] | None
    ) -> Iterator[dict[str, Any]]:
        table = self._episode_table(episode, info, names)
        frame_index = table.column("frame_index").to_numpy()
        if frame_indices is not None:
            keep = np.fromiter((int(i) in frame_indices for i in frame_index), dtype=bool, count=len(frame_index))
            if not keep.all():
                table = table.filter(pa.array(keep))
        n = table.num_rows
        if n == 0:
            return

        dtypes = {name: self.features.get(name, {}).get("dtype") for name in names}
        columns: dict[str, Any] = {}
        for name, dtype in dtypes.items():
            if dtype == "video":
                continue
            if dtype == "image":
                columns[name] = table.column(name).combine_chunks()
            else:
                columns[name] = _values(table.column(name), self.features.get(name), info.data_path, episode, name)
        task_index = table.column("task_index").to_numpy()
        unknown = sorted(set(task_index.tolist()) - set(self.task_names))
        if unknown:
            raise dataset_error(
                f"task_index {unknown[0]} has no task string",
                file=info.data_path,
                episode=episode,
                feature="task_index",
            )

        timestamps = table.column("timestamp").to_numpy().astype(np.float64)
        if np.any(np.diff(timestamps) < 0):
            raise dataset_error(
                "timestamps decrease with frame_index", file=info.data_path, episode=episode, feature="timestamp"
            )
        readers: dict[str, Generator[np.ndarray, None, None]] = {}
        for name in names:
            if dtypes[name] != "video":
                continue
            video = info.videos.get(name)
            if video is None:
                raise dataset_error(
                    "no video file recorded for this camera", file=self.info_path, episode=episode, feature=name
                )
            readers[name] = self._decode_video(video, timestamps + video.from_timestamp, episode, name)

        try:
            for row in range(n):
                frame: dict[str, Any] = {}
                for name in names:
                    if name in readers:
                        frame[name] = next(readers[name])
                    elif dtypes[name] == "image":
                        frame[name] = self._decode_image(columns[name], row, info.data_path, episode, name)
                    else:
                        frame[name] = columns[name][row]
                frame["task"] = self.task_names[int(task_index[row])]
                yield frame
        finally:
            for reader in readers.values():
                reader.close()  # closes its container now, not when collected

    def _episode_table(self, episode: int, info: _Episode, names: list[str]) -> pa.Table:
        """The episode's rows of its data file, sorted by frame_index, with the columns `names` need."""
        path = info.data_path
        if not path.is_file():
            raise dataset_error("data file missing", file=path, episode=episode)
        try:
            schema = pq.read_schema(path)
        except (pa.ArrowException, OSError) as e:
            raise dataset_error(f"unreadable parquet ({e})", file=path, episode=episode) from e
        wanted = [name for name in names if self.features.get(name, {}).get("dtype") != "video"]
        for name in wanted:
            if schema.get_field_index(name) < 0:
                raise dataset_error("column missing from the data file", file=path, episode=episode, feature=name)
        try:
            if self.version in V3_VERSIONS:
                # Several episodes share a v3.0 file; row groups whose statistics rule the episode out are skipped.
                table = pq.read_table(path, columns=wanted, filters=pc.field("episode_index") == episode)
            else:
                table = pq.read_table(path, columns=wanted)
        except (pa.ArrowException, OSError) as e:
            raise dataset_error(f"unreadable parquet ({e})", file=path, episode=episode) from e
        frame_index = table.column("frame_index").to_numpy()
        if np.any(np.diff(frame_index) < 0):
            table = table.take(pa.array(np.argsort(frame_index, kind="stable")))
        if table.num_rows != info.length:
            raise dataset_error(
                f"{table.num_rows} rows, the episode metadata says {info.length}", file=path, episode=episode
            )
        return table

    def _decode_image(self, column: pa.StructArray, row: int, path: Path, episode: int, name: str) -> np.ndarray:
        item = column[row].as_py()
        data = item.get("bytes") if isinstance(item, dict) else None
        try:
            if data is None:
                image_path = item.get("path") if isinstance(item, dict) else None
                if not image_path:
                    raise dataset_error(
                        f"frame row {row} holds neither image bytes nor a path",
                        file=path,
                        episode=episode,
                        feature=name,
                    )
                source: Any = Path(image_path) if Path(image_path).is_absolute() else self.root / image_path
            else:
                source = io.BytesIO(data)
            with Image.open(source) as image:
                return np.array(image.convert("RGB"))
        except (OSError, ValueError) as e:
            if isinstance(e, DatasetError):
                raise
            raise dataset_error(
                f"undecodable image in frame row {row} ({e})", file=path, episode=episode, feature=name
            ) from e

    def _decode_video(
        self, video: _Video, queries: np.ndarray, episode: int, name: str
    ) -> Generator[np.ndarray, None, None]:
        """The frame nearest to each query timestamp (seconds in the file, non-decreasing), decoding forward."""
        where: dict[str, Any] = {"file": video.path, "episode": episode, "feature": name}
        if not video.path.is_file():
            raise dataset_error("video file missing", **where)
        # A matched frame must lie in the episode's own segment of the file: frames sit one period apart, so half a
        # period inside each end keeps the neighbouring episodes' first and last frames out, whatever rounding the
        # stored timestamps carry.
        half = 0.5 / self.fps
        lowest = video.from_timestamp - half
        highest = math.inf if video.to_timestamp is None else video.to_timestamp - half
        segment = f"[{video.from_timestamp:.6f}s, " + (
            "end)" if video.to_timestamp is None else f"{video.to_timestamp:.6f}s)"
        )
        try:
            container = av.open(str(video.path))
        except (av.FFmpegError, OSError) as e:
            raise dataset_error(f"cannot open video ({e})", **where) from e
        self.video_opens += 1
        try:
            if not container.streams.video:
                raise dataset_error("no video stream in the file", **where)
            stream = container.streams.video[0]
            time_base = stream.time_base
            if time_base is None:
                raise dataset_error("video stream has no time base", **where)
            start = max(float(queries[0]) - self.tolerance_s, 0.0)
            try:
                container.seek(math.floor(start / time_base), stream=stream, backward=True, any_frame=False)
            except av.FFmpegError as e:
                raise dataset_error(f"cannot seek to {start:.6f}s ({e})", **where) from e
            self.video_seeks += 1
            decoded = _decoded(container, stream, where)
            before: tuple[float, Any] | None = None
            after = next(decoded, None)
            for query in queries.tolist():
                while after is not None and after[0] <= query:
                    before, after = after, next(decoded, None)
                candidates = [c for c in (before, after) if c is not None]
                if not candidates:
                    raise dataset_error(f"no frame decoded for timestamp {query:.6f}s", **where)
                pts, frame = min(candidates, key=lambda c: abs(c[0] - query))
                if abs(pts - query) >= self.tolerance_s:
                    raise dataset_error(
                        f"no frame within {self.tolerance_s:.6g}s of timestamp {query:.6f}s (nearest at {pts:.6f}s)",
                        **where,
                    )
                if not lowest <= pts < highest:
                    raise dataset_error(
                        f"timestamp {query:.6f}s falls outside the episode's segment of the video {segment}",
                        **where,
                    )
                yield frame.to_ndarray(format="rgb24")
        finally:
            container.close()


def _decoded(container: Any, stream: Any, where: dict[str, Any]) -> Iterator[tuple[float, Any]]:
    """(pts in seconds, frame) in decoding order, with PyAV's failures as DatasetError."""
    frames = container.decode(stream)
    while True:
        try:
            frame = next(frames)
        except StopIteration:
            return
        except av.FFmpegError as e:
            raise dataset_error(f"video decoding failed ({e})", **where) from e
        if frame.pts is None:
            raise dataset_error("decoded a frame without a timestamp", **where)
        yield float(frame.pts * stream.time_base), frame


def _values(column: pa.ChunkedArray, spec: dict | None, path: Path, episode: int, name: str) -> Any:
    """A column as one numpy array [rows, *shape] (a shape-[1] feature as [rows]), or a list for strings."""
    array = column.combine_chunks()
    if pa.types.is_string(array.type) or pa.types.is_large_string(array.type):
        return array.to_pylist()
    rows = len(array)
    flat = array
    while pa.types.is_list(flat.type) or pa.types.is_large_list(flat.type) or pa.types.is_fixed_size_list(flat.type):
        flat = flat.flatten()
    if flat.null_count:
        raise dataset_error("column holds nulls", file=path, episode=episode, feature=name)
    values = flat.to_numpy(zero_copy_only=False)
    shape = tuple(int(s) for s in spec["shape"]) if spec and spec.get("shape") else None
    if shape is None:
        shape = (values.size // rows,) if rows else (1,)
    if values.size != rows * math.prod(shape):
        raise dataset_error(
            f"{values.size} values for {rows} frames, info.json gives shape {list(shape)}",
            file=path,
            episode=episode,
            feature=name,
        )
    values = values.reshape((rows, *shape))
    if shape == (1,):
        values = values[:, 0]
    dtype = spec.get("dtype") if spec else None
    if dtype:
        # a dtype numpy does not name (one of LeRobot's own kinds) keeps what the parquet holds
        with contextlib.suppress(TypeError):
            values = values.astype(np.dtype(dtype), copy=False)
    return values


def parse_episodes(text: str | None) -> tuple[int, ...] | None:
    """An episode selection (`--episodes`): `0,3,7-9` -> (0, 3, 7, 8, 9); None or empty: every episode."""
    if text is None or not text.strip():
        return None
    out: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise ValueError(f"--episodes takes indices and ranges like 0,3,7-9, got {text!r}")
        out += range(int(lo), int(hi) + 1) if sep else [int(lo)]
    return tuple(dict.fromkeys(out))


def is_lerobot_dataset(root: str | Path) -> bool:
    """Whether `root` looks like a LeRobot dataset (a `meta/info.json` naming a `codebase_version`), whatever the
    version: an unsupported one is then refused by `open_dataset` with its name."""
    info_path = Path(root) / "meta" / "info.json"
    try:
        return info_path.is_file() and "codebase_version" in json.loads(info_path.read_text())
    except (OSError, ValueError):
        return False


def open_dataset(root: str | Path, *, tolerance_s: float | None = None) -> LeRobotDataset:
    """Open the dataset at `root` (the folder holding `meta/`) and read its metadata.

    `tolerance_s`: how far a frame's timestamp may be from the pts of the decoded video frame it takes. The default
    is half a frame period: the nearest frame is then the only candidate on the video's grid, and float32
    timestamps late in long episodes (whose rounding outgrows LeRobot's 1e-4 s) still match, while a frame missing
    from the video (a whole period away) is an error."""
    root = Path(root)
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise dataset_error("missing meta/info.json: not a LeRobot dataset root", file=info_path)
    try:
        info = load_json(info_path)
    except BadFile as e:
        raise DatasetError(str(e)) from e
    except OSError as e:
        raise dataset_error(f"unreadable info.json ({e})", file=info_path) from e
    version = info.get("codebase_version")
    if version not in V2_VERSIONS + V3_VERSIONS:
        raise dataset_error(
            f"unsupported codebase_version {version!r} (known: {', '.join(V2_VERSIONS + V3_VERSIONS)})", file=info_path
        )
    for key in ("fps", "features", "data_path"):
        if key not in info:
            raise dataset_error(f"no {key!r} entry", file=info_path)
    fps = int(info["fps"])
    features: dict[str, dict] = info["features"]
    videos = [name for name, spec in features.items() if spec.get("dtype") == "video"]
    if videos and not info.get("video_path"):
        raise dataset_error("video features but no 'video_path' template", file=info_path, feature=videos[0])
    if version in V3_VERSIONS:
        episode_info = _v3_episodes(root, info, videos)
        task_names = _v3_tasks(root / "meta" / "tasks.parquet")
    else:
        episode_info = _v2_episodes(root, info, videos)
        task_names = _v2_tasks(root / "meta" / "tasks.jsonl")
    return LeRobotDataset(
        root=root,
        version=version,
        fps=fps,
        features=features,
        episodes=sorted(episode_info),
        tolerance_s=0.5 / fps if tolerance_s is None else float(tolerance_s),
        episode_info=episode_info,
        task_names=task_names,
    )


def _template(info: dict, key: str, root: Path, feature: str | None = None, **fields: Any) -> Path:
    try:
        return root / info[key].format(**fields)
    except (KeyError, IndexError, ValueError, AttributeError) as e:
        raise dataset_error(
            f"cannot fill the {key!r} template ({e!r})", file=root / "meta" / "info.json", feature=feature
        ) from e


def _jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        raise dataset_error("metadata file missing", file=path)
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as e:
        raise dataset_error(f"unreadable JSON lines ({e})", file=path) from e


def _v2_episodes(root: Path, info: dict, videos: list[str]) -> dict[int, _Episode]:
    path = root / "meta" / "episodes.jsonl"
    chunks_size = int(info.get("chunks_size", 1000))
    episodes = {}
    for record in _jsonl(path):
        if "episode_index" not in record or "length" not in record:
            raise dataset_error("a line lacks episode_index or length", file=path)
        index = int(record["episode_index"])
        chunk = index // chunks_size
        episodes[index] = _Episode(
            length=int(record["length"]),
            data_path=_template(info, "data_path", root, episode_chunk=chunk, episode_index=index),
            videos={
                key: _Video(
                    _template(info, "video_path", root, key, episode_chunk=chunk, episode_index=index, video_key=key),
                    0.0,
                    None,
                )
                for key in videos
            },
        )
    return episodes


def _v2_tasks(path: Path) -> dict[int, str]:
    try:
        return {int(record["task_index"]): str(record["task"]) for record in _jsonl(path)}
    except KeyError as e:
        raise dataset_error(f"a line lacks {e}", file=path) from e


def _v3_episodes(root: Path, info: dict, videos: list[str]) -> dict[int, _Episode]:
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise dataset_error("no episode metadata files (meta/episodes/chunk-*/file-*.parquet)", file=root / "meta")
    required: list[tuple[str, str | None]] = [
        ("episode_index", None),
        ("length", None),
        ("data/chunk_index", None),
        ("data/file_index", None),
    ]
    for key in videos:
        required += [(f"videos/{key}/{part}", key) for part in ("chunk_index", "file_index", "from_timestamp")]
    optional = [f"videos/{key}/to_timestamp" for key in videos]
    episodes = {}
    for path in files:
        try:
            schema = pq.read_schema(path)
            for column, feature in required:
                if schema.get_field_index(column) < 0:
                    raise dataset_error(f"column {column!r} missing", file=path, feature=feature)
            present = [column for column in optional if schema.get_field_index(column) >= 0]
            table = pq.read_table(path, columns=[column for column, _ in required] + present).to_pydict()
        except (pa.ArrowException, OSError) as e:
            raise dataset_error(f"unreadable parquet ({e})", file=path) from e
        for row, index in enumerate(table["episode_index"]):
            video_files = {}
            for key in videos:
                prefix = f"videos/{key}/"
                to_column = table.get(prefix + "to_timestamp")
                video_files[key] = _Video(
                    _template(
                        info,
                        "video_path",
                        root,
                        key,
                        video_key=key,
                        chunk_index=int(table[prefix + "chunk_index"][row]),
                        file_index=int(table[prefix + "file_index"][row]),
                    ),
                    float(table[prefix + "from_timestamp"][row]),
                    None if to_column is None or to_column[row] is None else float(to_column[row]),
                )
            episodes[int(index)] = _Episode(
                length=int(table["length"][row]),
                data_path=_template(
                    info,
                    "data_path",
                    root,
                    chunk_index=int(table["data/chunk_index"][row]),
                    file_index=int(table["data/file_index"][row]),
                ),
                videos=video_files,
            )
    return episodes


def _v3_tasks(path: Path) -> dict[int, str]:
    if not path.is_file():
        raise dataset_error("metadata file missing", file=path)
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as e:
        raise dataset_error(f"unreadable parquet ({e})", file=path) from e
    names = table.column_names
    # pandas stores its index as a column: named `task` when LeRobot names the index, `__index_level_0__` if not.
    text = next((c for c in ("task", "__index_level_0__") if c in names), None)
    if text is None:
        pandas_meta = json.loads((table.schema.metadata or {}).get(b"pandas", b"{}"))
        text = next((c for c in pandas_meta.get("index_columns", []) if isinstance(c, str) and c in names), None)
    if text is None or "task_index" not in names:
        raise dataset_error("needs a task_index column and the task strings (column or pandas index)", file=path)
    return {
        int(i): str(t)
        for i, t in zip(table.column("task_index").to_pylist(), table.column(text).to_pylist(), strict=True)
    }
