"""The LeRobot reader against datasets LeRobot wrote and the frames LeRobot's own `__getitem__` returned for them
(`../shared/lerobot`), against the same datasets spread over several files and chunks, and on broken copies."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from one_line import assert_one_line
from paths import LEROBOT_DIR
from shared_copies import edit_json, writable_copy

from openpi_cam.lerobot.dataset import DatasetError, LeRobotDataset, open_dataset

DATASETS = ("demo_reach_v30_video", "demo_reach_v30_image", "demo_reach_v21_video")
V30_VIDEO, V30_IMAGE, V21_VIDEO = DATASETS
# Both readers decode the same AV1 bitstream and convert yuv420p to RGB with FFmpeg's swscale; 2 of 255 leaves room
# for a conversion that rounds differently, while a wrong frame differs by far more (checked below).
PIXEL_TOLERANCE = 2
NUMERIC = ("observation.state", "observation.target_box")
TASKS = {0: "reach the yellow block", 1: "reach the blue block", 2: "reach the green block", 3: "reach the red block"}


def _copy(name: str, tmp_path: Path) -> Path:
    return writable_copy(LEROBOT_DIR / name, tmp_path / name)


def _same_frames(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            assert a[key].dtype == b[key].dtype and a[key].shape == b[key].shape, key
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        else:
            assert a[key] == b[key] and type(a[key]) is type(b[key]), key


def _assert_same_dataset(ds: LeRobotDataset, reference: LeRobotDataset) -> None:
    assert ds.episodes == reference.episodes
    for episode in reference.episodes:
        ours, theirs = list(ds.frames(episode)), list(reference.frames(episode))
        assert len(ours) == len(theirs) == reference.episode_length(episode)
        for a, b in zip(ours, theirs, strict=True):
            _same_frames(a, b)


# --- every frame against LeRobot's own -------------------------------------------------------------------------


@pytest.mark.parametrize("name", DATASETS)
def test_every_frame_matches_what_lerobot_returns(name):
    ds = open_dataset(LEROBOT_DIR / name)
    reference = np.load(LEROBOT_DIR / f"{name}.lerobot_frames.npz")
    reference_indices = sorted({int(key.rsplit("/", 1)[1]) for key in reference.files})
    assert ds.camera_features == ["observation.images.base", "observation.images.wrist"]
    assert ds.tasks() == TASKS

    seen, worst = [], dict.fromkeys(ds.camera_features, 0)
    for episode in ds.episodes:
        frames = list(ds.frames(episode))
        assert len(frames) == ds.episode_length(episode)
        assert [int(f["frame_index"]) for f in frames] == list(range(len(frames)))
        for frame in frames:
            index = int(frame["index"])
            seen.append(index)
            for camera in ds.camera_features:
                ours, theirs = frame[camera], reference[f"{camera}/{index}"]
                assert ours.dtype == np.uint8 and ours.shape == theirs.shape == (64, 64, 3)
                worst[camera] = max(worst[camera], int(np.abs(ours.astype(np.int16) - theirs).max()))
            for key in NUMERIC:
                assert frame[key].dtype == np.float32 and frame[key].shape == tuple(ds.features[key]["shape"])
                # the same float32 values read from the same parquet: exact
                np.testing.assert_array_equal(frame[key], reference[f"{key}/{index}"], err_msg=f"{key} {index}")
            assert frame["episode_index"] == reference[f"episode_index/{index}"] == episode
            assert frame["frame_index"] == reference[f"frame_index/{index}"]
            assert frame["task"] == str(reference[f"task/{index}"]) == TASKS[int(frame["task_index"])]
            for key, dtype in (("index", np.int64), ("frame_index", np.int64), ("timestamp", np.float32)):
                assert type(frame[key]) is dtype, key  # shape-[1] features come out as numpy scalars
    assert seen == reference_indices
    assert max(worst.values()) <= PIXEL_TOLERANCE, f"max |diff| per camera, of 255: {worst}"

    # The tolerance tells frames apart: neighbouring reference frames of an episode differ by far more than it.
    for camera in ds.camera_features:
        gaps = [
            int(np.abs(reference[f"{camera}/{i}"].astype(np.int16) - reference[f"{camera}/{i + 1}"]).max())
            for i in reference_indices[:-1]
            if reference[f"episode_index/{i}"] == reference[f"episode_index/{i + 1}"]
        ]
        assert min(gaps) > 10 * PIXEL_TOLERANCE, (camera, min(gaps))


def test_v2_and_v3_layouts_read_the_same_recording():
    """The v2.1 and v3.0 video datasets hold the same episodes: everything but pixels agrees exactly."""
    v21, v30 = open_dataset(LEROBOT_DIR / V21_VIDEO), open_dataset(LEROBOT_DIR / V30_VIDEO)
    assert (v21.version, v30.version) == ("v2.1", "v3.0")
    assert v21.episodes == v30.episodes == list(range(8))
    for episode in v30.episodes:
        for a, b in zip(v21.frames(episode), v30.frames(episode), strict=True):
            for key in ("action", *NUMERIC, "index", "frame_index", "timestamp", "task"):
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)


# --- the same datasets over several files and chunks -----------------------------------------------------------


def _remux(src: Path, dst: Path, start_s: float, end_s: float) -> None:
    """Stream-copy the packets of [start_s, end_s) of `src` into `dst`, their timestamps moved to start at 0."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(src)) as source, av.open(str(dst), "w", format="mp4") as out:
        stream = source.streams.video[0]
        copy = out.add_stream_from_template(stream, opaque=True)
        start, end = round(start_s / stream.time_base), round(end_s / stream.time_base)
        first = True
        for packet in source.demux(stream):
            if packet.pts is None or not start <= packet.pts < end:
                continue
            assert not first or packet.is_keyframe, "a cut must fall on a keyframe for a stream copy"
            first = False
            packet.pts -= start
            packet.dts -= start
            packet.stream = copy
            out.mux(packet)


def _split_v30(src: Path, dst: Path) -> None:
    """`src` (all episodes in one data file and one mp4 per camera) rewritten with episodes spread over several
    data and video files in two chunks, and the episode metadata in two files."""
    info = json.loads((src / "meta" / "info.json").read_text())
    info["chunks_size"] = 2  # at most two files per chunk: file 2 goes to chunk-001
    (dst / "meta").mkdir(parents=True)
    (dst / "meta" / "info.json").write_text(json.dumps(info, indent=2))
    shutil.copyfile(src / "meta" / "tasks.parquet", dst / "meta" / "tasks.parquet")
    episodes = pq.read_table(src / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    data = pq.read_table(src / "data" / "chunk-000" / "file-000.parquet")
    columns = episodes.to_pydict()
    cameras = [key for key, spec in info["features"].items() if spec["dtype"] == "video"]

    def place(groups: list[list[int]], prefix: str) -> Iterator[tuple[int, int, list[int]]]:
        """(chunk, file, episodes) per group, the episodes' metadata pointed at that file."""
        for number, group in enumerate(groups):
            chunk, file = divmod(number, info["chunks_size"])
            for episode in group:
                columns[f"{prefix}chunk_index"][episode] = chunk
                columns[f"{prefix}file_index"][episode] = file
            yield chunk, file, group

    for chunk, file, group in place([[0, 1, 2], [3, 4], [5, 6, 7]], "data/"):
        path = dst / info["data_path"].format(chunk_index=chunk, file_index=file)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(data.filter(pc.is_in(data["episode_index"], pa.array(group))), path)

    for camera in cameras:
        prefix = f"videos/{camera}/"
        source = src / info["video_path"].format(video_key=camera, chunk_index=0, file_index=0)
        for chunk, file, group in place([[0, 1], [2, 3, 4], [5], [6, 7]], prefix):
            start = columns[prefix + "from_timestamp"][group[0]]
            end = columns[prefix + "to_timestamp"][group[-1]]
            _remux(
                source,
                dst / info["video_path"].format(video_key=camera, chunk_index=chunk, file_index=file),
                start,
                end,
            )
            for episode in group:
                columns[prefix + "from_timestamp"][episode] -= start
                columns[prefix + "to_timestamp"][episode] -= start

    rewritten = pa.table(columns, schema=episodes.schema)
    for file, rows in enumerate(((0, 4), (4, 8))):
        part = rewritten.slice(rows[0], rows[1] - rows[0])
        part = part.set_column(
            part.schema.get_field_index("meta/episodes/file_index"),
            "meta/episodes/file_index",
            pa.array([file] * part.num_rows, pa.int64()),
        )
        path = dst / "meta" / "episodes" / "chunk-000" / f"file-{file:03d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(part, path)


@pytest.mark.parametrize("name", [V30_VIDEO, V30_IMAGE])
def test_v30_over_several_files_and_chunks_reads_the_same(name, tmp_path):
    _split_v30(LEROBOT_DIR / name, tmp_path / name)
    split = open_dataset(tmp_path / name)
    data_files = {info.data_path for info in split.episode_info.values()}
    video_files = {video.path for info in split.episode_info.values() for video in info.videos.values()}
    assert len(data_files) == 3 and any("chunk-001" in str(path) for path in data_files)
    assert len(video_files) == (8 if name == V30_VIDEO else 0)
    _assert_same_dataset(split, open_dataset(LEROBOT_DIR / name))


def test_v21_over_several_chunks_reads_the_same(tmp_path):
    src, dst = LEROBOT_DIR / V21_VIDEO, tmp_path / V21_VIDEO
    info = json.loads((src / "meta" / "info.json").read_text())
    writable_copy(src / "meta", dst / "meta")
    old_size, info["chunks_size"] = info["chunks_size"], 3
    (dst / "meta" / "info.json").write_text(json.dumps(info, indent=2))
    cameras = [key for key, spec in info["features"].items() if spec["dtype"] == "video"]
    for episode in range(info["total_episodes"]):
        pairs = [(info["data_path"], {})] + [(info["video_path"], {"video_key": key}) for key in cameras]
        for template, extra in pairs:
            old = src / template.format(episode_chunk=episode // old_size, episode_index=episode, **extra)
            new = dst / template.format(episode_chunk=episode // 3, episode_index=episode, **extra)
            new.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(old, new)
    assert sorted(p.name for p in (dst / "data").iterdir()) == ["chunk-000", "chunk-001", "chunk-002"]
    _assert_same_dataset(open_dataset(dst), open_dataset(src))


# --- forward decoding ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", [V30_VIDEO, V21_VIDEO])
def test_each_video_is_opened_and_sought_once_per_episode(name):
    ds = open_dataset(LEROBOT_DIR / name)
    full = list(ds.frames(5))
    assert len(full) == 10 and (ds.video_opens, ds.video_seeks) == (2, 2)

    some = list(ds.frames(5, frame_indices={1, 4, 9}))
    assert [int(f["frame_index"]) for f in some] == [1, 4, 9]
    for frame in some:
        _same_frames(frame, full[int(frame["frame_index"])])
    assert (ds.video_opens, ds.video_seeks) == (4, 4)

    only = list(ds.frames(5, features=["observation.images.wrist"]))
    assert set(only[0]) == {
        "observation.images.wrist",
        "index",
        "episode_index",
        "frame_index",
        "timestamp",
        "task_index",
        "task",
    }
    assert (ds.video_opens, ds.video_seeks) == (5, 5)
    assert list(ds.frames(5, frame_indices=())) == [] and ds.video_opens == 5


# --- broken datasets -------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "video"),
    [
        (V30_VIDEO, "videos/observation.images.wrist/chunk-000/file-000.mp4"),
        (V21_VIDEO, "videos/chunk-000/observation.images.wrist/episode_000003.mp4"),
    ],
)
def test_missing_and_truncated_videos_name_file_episode_and_feature(name, video, tmp_path):
    root = _copy(name, tmp_path)
    path = root / video
    data = path.read_bytes()
    with av.open(str(path)) as container:
        packets = [p for p in container.demux(video=0) if p.pts is not None]
        start = open_dataset(root).episode_info[3].videos["observation.images.wrist"].from_timestamp
        third = next(p for p in packets if p.pts * p.time_base > start + 0.15)
        cut = third.pos + third.size // 2
    path.unlink()
    ds = open_dataset(root)
    with pytest.raises(DatasetError) as error:
        list(ds.frames(3))
    assert_one_line(error.value, path.name, "episode 3", "'observation.images.wrist'", "missing")

    path.write_bytes(data[:cut])  # in the middle of the episode's third frame
    with pytest.raises(DatasetError) as error:
        list(ds.frames(3))
    assert_one_line(error.value, path.name, "episode 3", "'observation.images.wrist'")
    assert len(list(ds.frames(3, features=["observation.images.base"]))) == 8


def test_a_missing_column_names_file_episode_and_feature(tmp_path):
    root = _copy(V30_VIDEO, tmp_path)
    path = root / "data" / "chunk-000" / "file-000.parquet"
    table = pq.read_table(path)
    pq.write_table(table.drop_columns(["observation.state"]), path)
    ds = open_dataset(root)
    with pytest.raises(DatasetError) as error:
        list(ds.frames(2))
    assert_one_line(error.value, "file-000.parquet", "episode 2", "'observation.state'")
    assert len(list(ds.frames(2, features=["action"]))) == 4  # a column nobody asked for is not needed

    path = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    pq.write_table(pq.read_table(path).drop_columns(["videos/observation.images.base/from_timestamp"]), path)
    with pytest.raises(DatasetError) as error:
        open_dataset(root)
    assert_one_line(error.value, str(path), "'observation.images.base'", "from_timestamp")


def _edit_column(path: Path, name: str, edit) -> None:
    table = pq.read_table(path)
    values = table.column(name).to_pylist()
    edit(values)
    index = table.schema.get_field_index(name)
    pq.write_table(
        table.set_column(index, table.schema.field(index), pa.array(values, table.schema.field(index).type)), path
    )


def test_a_timestamp_outside_its_video_names_file_episode_feature_and_timestamp(tmp_path):
    # v3.0: episode 7's segment moved past the end of the file (last frame at 5.4 s)
    root = _copy(V30_VIDEO, tmp_path)
    episodes = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    _edit_column(episodes, "videos/observation.images.base/from_timestamp", lambda v: v.__setitem__(7, 5.0))
    with pytest.raises(DatasetError) as error:
        list(open_dataset(root).frames(7))
    assert_one_line(error.value, "file-000.mp4", "episode 7", "'observation.images.base'", "5.500000")

    # v3.0: episode 0's last frame stamped where episode 1's first frame sits in the shared file
    root = _copy(V30_VIDEO, tmp_path / "second")
    data = root / "data" / "chunk-000" / "file-000.parquet"
    _edit_column(data, "timestamp", lambda v: v.__setitem__(4, 0.5))
    with pytest.raises(DatasetError) as error:
        list(open_dataset(root).frames(0))
    assert_one_line(error.value, "file-000.mp4", "episode 0", "'observation.images.", "0.500000", "segment")
    assert len(list(open_dataset(root).frames(1))) == 4

    # v2.1: a timestamp beyond the episode's own video
    root = _copy(V21_VIDEO, tmp_path)
    data = root / "data" / "chunk-000" / "episode_000000.parquet"
    _edit_column(data, "timestamp", lambda v: v.__setitem__(4, 9.0))
    with pytest.raises(DatasetError) as error:
        list(open_dataset(root).frames(0))
    assert_one_line(error.value, "episode_000000.mp4", "episode 0", "'observation.images.", "9.000000")


def test_unknown_features_episodes_versions_and_roots_are_named():
    ds = open_dataset(LEROBOT_DIR / V30_IMAGE)
    with pytest.raises(DatasetError) as error:
        ds.frames(0, features=["observation.images.top"])
    assert_one_line(error.value, "info.json", "episode 0", "'observation.images.top'")
    with pytest.raises(DatasetError) as error:
        ds.frames(99)
    assert_one_line(error.value, "info.json", "episode 99")
    with pytest.raises(DatasetError) as error:
        open_dataset(LEROBOT_DIR)
    assert_one_line(error.value, str(LEROBOT_DIR / "meta" / "info.json"), "missing")


def test_v20_reads_as_the_v2_layout(tmp_path):
    root = _copy(V21_VIDEO, tmp_path)
    edit_json(root / "meta" / "info.json", lambda info: info.update(codebase_version="v2.0"))
    ds = open_dataset(root)
    assert ds.version == "v2.0"
    for a, b in zip(ds.frames(2), open_dataset(LEROBOT_DIR / V21_VIDEO).frames(2), strict=True):
        _same_frames(a, b)


@pytest.mark.parametrize("version", ["v1.6", "v4.0", None])
def test_an_unknown_codebase_version_is_named(version, tmp_path):
    root = tmp_path / "dataset"
    (root / "meta").mkdir(parents=True)
    info = json.loads((LEROBOT_DIR / V30_VIDEO / "meta" / "info.json").read_text())
    info["codebase_version"] = version
    (root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError) as error:
        open_dataset(root)
    assert_one_line(error.value, str(root / "meta" / "info.json"), repr(version))
