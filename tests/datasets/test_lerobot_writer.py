"""The LeRobot v3.0 writer: LeRobot's own recording written again must give LeRobot's files, and what we write must
read back through our reader (`data.lerobot.open_dataset`) exactly, cameras in video within the codec's loss.

LeRobot itself opening what we write is checked outside CI (no torch here): benchmarks/check_lerobot_reads.py."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from one_line import assert_one_line
from paths import LEROBOT_DIR
from PIL import Image

from openpi_cam.lerobot import writer as lerobot_writer
from openpi_cam.lerobot.dataset import DatasetError, LeRobotDataset, open_dataset
from openpi_cam.lerobot.video import VideoOptions
from openpi_cam.lerobot.writer import OUTCOME_FEATURES, DatasetWriter, Feature, create_dataset

RECORDED = LEROBOT_DIR / "demo_reach_v30_image"  # LeRobot 0.6.1's recording, cameras as lossless PNG
RECORDED_VIDEO = LEROBOT_DIR / "demo_reach_v30_video"  # the same frames recorded as AV1 video
DEFAULTS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
# Per-frame mean |decoded - original| of 255. LeRobot's own AV1 encoding (libsvtav1, crf 30, yuv420p) of the
# recorded demo frames reaches 5.6 (base) and 5.8 (wrist), ours 5.4 and 6.1: colour edges at 64 px lose most to the
# halved chroma. 8 leaves room for another SVT-AV1 build; a frame from the wrong episode or a channel swap is off by
# tens.
VIDEO_MEAN_ERROR = 8.0


def _features_of(root: Path, *, video: bool) -> dict[str, Feature]:
    """The recorded features of a LeRobot dataset as the writer declares them, cameras as video or image."""
    features = json.loads((root / "meta" / "info.json").read_text())["features"]
    out = {}
    for name, spec in features.items():
        if name in DEFAULTS:
            continue
        dtype = ("video" if video else "image") if spec["dtype"] in ("video", "image") else spec["dtype"]
        out[name] = Feature(dtype, tuple(spec["shape"]), tuple(spec["names"]))
    return out


def _rewrite(source: LeRobotDataset, root: Path, *, video: bool, **limits) -> Path:
    """`source`'s episodes written again with our writer, frame by frame as a recorder would."""
    info = json.loads(source.info_path.read_text())
    features = _features_of(source.root, video=video)
    with create_dataset(root, fps=source.fps, features=features, robot_type=info["robot_type"], **limits) as writer:
        for episode in source.episodes:
            for frame in source.frames(episode):
                writer.add_frame({name: frame[name] for name in features}, task=frame["task"])
            writer.save_episode()
    return root


def _columns(path: Path) -> dict:
    return pq.read_table(path).to_pydict()


def _pixels(item: dict) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(item["bytes"])))


# --- LeRobot's recording, written again ------------------------------------------------------------------------


def test_rewriting_lerobots_recording_gives_lerobots_files(tmp_path):
    """Same frames, same tasks, same order: info.json, tasks, every data column (PNG bytes included), the episode
    metadata with its statistics and stats.json come out as LeRobot 0.6.1 wrote them."""
    ours = _rewrite(open_dataset(RECORDED), tmp_path / "ours", video=False)
    assert sorted(p.relative_to(ours).as_posix() for p in ours.rglob("*") if p.is_file()) == sorted(
        p.relative_to(RECORDED).as_posix() for p in RECORDED.rglob("*") if p.is_file()
    )
    for name in ("info.json", "stats.json"):
        assert json.loads((ours / "meta" / name).read_text()) == json.loads((RECORDED / "meta" / name).read_text())
    for relative in (
        "meta/tasks.parquet",
        "meta/episodes/chunk-000/file-000.parquet",
        "data/chunk-000/file-000.parquet",
    ):
        a, b = pq.read_table(ours / relative), pq.read_table(RECORDED / relative)
        assert a.schema.equals(b.schema, check_metadata=False), relative
        assert a.to_pydict() == b.to_pydict(), relative
        # one row group per episode, so that a reader filtering on episode_index skips the others
        assert pq.ParquetFile(ours / relative).num_row_groups == pq.ParquetFile(RECORDED / relative).num_row_groups


def test_rewriting_lerobots_recording_as_video_gives_its_metadata_and_frames_within_the_codec_loss(tmp_path):
    source = open_dataset(RECORDED)
    ours = _rewrite(source, tmp_path / "ours", video=True)
    # info.json (with the encoder's settings as LeRobot records them), the episodes' video segments and statistics
    # (computed from the frames before encoding) are LeRobot's
    for name in ("info.json", "stats.json"):
        assert json.loads((ours / "meta" / name).read_text()) == json.loads(
            (RECORDED_VIDEO / "meta" / name).read_text()
        )
    episodes = "meta/episodes/chunk-000/file-000.parquet"
    assert _columns(ours / episodes) == _columns(RECORDED_VIDEO / episodes)
    data = "data/chunk-000/file-000.parquet"
    assert _columns(ours / data) == _columns(RECORDED_VIDEO / data)

    written = open_dataset(ours)
    for episode in source.episodes:
        originals, decoded = list(source.frames(episode)), list(written.frames(episode))
        assert len(decoded) == len(originals)
        for a, b in zip(decoded, originals, strict=True):
            for camera in source.camera_features:
                error = np.abs(a[camera].astype(np.int16) - b[camera]).mean()
                assert error <= VIDEO_MEAN_ERROR, (episode, int(a["frame_index"]), camera, error)
        # The wrist view changes from frame to frame by more than the codec's loss: each decoded frame is nearest to
        # its own original, so no frame is shifted or taken from a neighbour.
        camera = "observation.images.wrist"
        for i, frame in enumerate(decoded):
            errors = [np.abs(frame[camera].astype(np.int16) - b[camera]).mean() for b in originals]
            assert int(np.argmin(errors)) == i, (episode, i, errors)


# --- our own datasets read back ---------------------------------------------------------------------------------

MIXED = {
    "observation.images.top": Feature.camera(48, 64, video=True),
    "observation.images.wrist": Feature.camera(32, 40, video=False),
    "observation.state": Feature("float32", (3,), ("x", "y", "z")),
    "action": Feature("float32", (2,), ("dx", "dy")),
    "observation.count": Feature("int64", (1,)),
    "observation.contacts": Feature("bool", (2,), ("left", "right")),
    "observation.energy": Feature("float64", (1,)),
    **OUTCOME_FEATURES,
}
# (length, task or per-frame tasks, success): tasks repeat across episodes, one episode changes task midway, and
# success comes on an episode's last frame, as lerobot-eval records it (failures run to the step limit)
EPISODES = [
    (6, "pick the cube", True),
    (9, "open the drawer", False),
    (3, "pick the cube", True),
    (7, ["pick the cube"] * 3 + ["place the cube"] * 4, False),
    (5, "place the cube", True),
]
FPS = 15


def _picture(height: int, width: int, episode: int, step: int) -> np.ndarray:
    """A smooth background tinted by the episode and a bright square that moves each step, so that every frame of
    an episode differs from the others by far more than the codec's loss."""
    y, x = np.mgrid[0:height, 0:width]
    image = np.stack(
        [x * 255 // (width - 1), y * 255 // (height - 1), np.full_like(x, 40 + 40 * episode)], axis=-1
    ).astype(np.uint8)
    top, left = (3 * step) % (height - 10), (5 * step) % (width - 10)
    image[top : top + 10, left : left + 10] = (250, 250, 250)
    return image


def _frame(episode: int, step: int, length: int, success: bool) -> dict:
    rng = np.random.default_rng(1000 * episode + step)
    last = step == length - 1
    return {
        "observation.images.top": _picture(48, 64, episode, step),
        "observation.images.wrist": rng.integers(0, 256, (32, 40, 3), dtype=np.uint8),  # noise: PNG must keep it
        "observation.state": rng.standard_normal(3).astype(np.float32),
        "action": rng.standard_normal(2).astype(np.float32),
        "observation.count": np.array([7 * episode + step], np.int64),
        "observation.contacts": rng.random(2) < 0.5,
        "observation.energy": float(rng.standard_normal()),  # a Python float for a float64 [1] feature
        "next.reward": np.array([1.0 if success and last else 0.0], np.float32),
        "next.success": np.array([success and last]),
        "next.done": np.array([last]),
    }


def _write_mixed(root: Path, **limits) -> list[list[dict]]:
    """The mixed dataset at `root`; returns the frames given to the writer, per episode."""
    given = []
    with create_dataset(root, fps=FPS, features=MIXED, robot_type="test_arm", **limits) as writer:
        for e, (length, tasks, success) in enumerate(EPISODES):
            frames = []
            for step in range(length):
                frame = _frame(e, step, length, success)
                writer.add_frame(frame, task=tasks[step] if isinstance(tasks, list) else None)
                frames.append(frame)
            assert writer.save_episode(task=None if isinstance(tasks, list) else tasks) == e
            given.append(frames)
    return given


def _check_mixed(ds: LeRobotDataset, given: list[list[dict]]) -> None:
    assert ds.version == "v3.0" and ds.fps == FPS
    assert ds.episodes == list(range(len(EPISODES)))
    assert ds.tasks() == {0: "pick the cube", 1: "open the drawer", 2: "place the cube"}
    index = 0
    for e, (length, tasks, _) in enumerate(EPISODES):
        frames = list(ds.frames(e))
        assert len(frames) == ds.episode_length(e) == length
        for step, (frame, original) in enumerate(zip(frames, given[e], strict=True)):
            assert frame["task"] == (tasks[step] if isinstance(tasks, list) else tasks)
            assert (frame["index"], frame["episode_index"], frame["frame_index"]) == (index, e, step)
            assert frame["timestamp"] == np.float32(step / FPS) and frame["timestamp"].dtype == np.float32
            index += 1
            for name, feature in MIXED.items():
                value = frame[name]
                if feature.dtype == "video":
                    assert value.dtype == np.uint8 and value.shape == feature.shape
                    error = np.abs(value.astype(np.int16) - original[name]).mean()
                    assert error <= VIDEO_MEAN_ERROR, (e, step, name, error)
                    # nearest to its own original among the episode's frames: in place, not shifted
                    errors = [np.abs(value.astype(np.int16) - g[name]).mean() for g in given[e]]
                    assert int(np.argmin(errors)) == step, (e, step, errors)
                    continue
                expected = np.asarray(original[name], feature.dtype if not feature.is_camera else np.uint8)
                if feature.shape == (1,) and not feature.is_camera:
                    expected = expected.reshape(())  # shape-[1] features come out as numpy scalars
                assert value.dtype == expected.dtype and np.shape(value) == expected.shape, name
                np.testing.assert_array_equal(value, expected, err_msg=f"{name} episode {e} frame {step}")


def test_a_mixed_dataset_reads_back_exactly_but_for_video_loss(tmp_path):
    given = _write_mixed(tmp_path / "mixed")
    ds = open_dataset(tmp_path / "mixed")
    assert ds.camera_features == ["observation.images.top", "observation.images.wrist"]
    _check_mixed(ds, given)

    info = json.loads(ds.info_path.read_text())
    n = sum(length for length, _, _ in EPISODES)
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (len(EPISODES), n, 3)
    assert info["splits"] == {"train": f"0:{len(EPISODES)}"} and info["robot_type"] == "test_arm"
    for name in OUTCOME_FEATURES:  # as lerobot-eval declares them
        assert info["features"][name] == {"dtype": MIXED[name].dtype, "shape": [1], "names": None}
    video = info["features"]["observation.images.top"]["info"]
    assert (video["video.codec"], video["video.pix_fmt"], video["video.fps"]) == ("av1", "yuv420p", FPS)
    assert (video["video.height"], video["video.width"]) == (48, 64)
    assert "info" not in info["features"]["observation.images.wrist"]

    meta = _columns(tmp_path / "mixed" / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    assert meta["tasks"][3] == ["pick the cube", "place the cube"]
    assert meta["length"] == [length for length, _, _ in EPISODES]
    ends = np.cumsum([0] + meta["length"])
    assert meta["dataset_from_index"] == ends[:-1].tolist() and meta["dataset_to_index"] == ends[1:].tolist()
    # each episode's segment of the shared video is as long as the episode
    start, end = (
        meta["videos/observation.images.top/from_timestamp"],
        meta["videos/observation.images.top/to_timestamp"],
    )
    assert start[0] == 0 and start[1:] == end[:-1]
    np.testing.assert_allclose(np.subtract(end, start), np.array(meta["length"]) / FPS, rtol=0, atol=1e-9)

    # statistics: an outcome's mean is the share of frames where it holds, per episode and over the dataset
    successes = [np.mean([f["next.success"][0] for f in frames]) for frames in given]
    np.testing.assert_allclose(np.array(meta["stats/next.success/mean"])[:, 0], successes, rtol=0, atol=1e-7)
    stats = json.loads((tmp_path / "mixed" / "meta" / "stats.json").read_text())
    assert stats["next.success"]["mean"][0] == pytest.approx(3 / n, abs=1e-7)
    assert stats["next.done"]["count"] == [n] and stats["next.done"]["max"] == [1.0]
    everything = np.concatenate([[f["observation.state"] for f in frames] for frames in given])
    np.testing.assert_allclose(stats["observation.state"]["min"], everything.min(axis=0), rtol=0, atol=0)
    np.testing.assert_allclose(stats["observation.state"]["mean"], everything.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(stats["observation.state"]["std"], everything.std(axis=0), rtol=1e-5)


def test_episodes_over_several_files_and_chunks_read_the_same(tmp_path):
    """File limits far below one episode put every episode in a file of its own, two files a chunk; the dataset
    reads as the one-file dataset does, video frames included (each episode is encoded alone in both)."""
    given = _write_mixed(tmp_path / "one")
    _write_mixed(tmp_path / "split", chunks_size=2, data_files_size_in_mb=1e-4, video_files_size_in_mb=1e-4)
    split, one = open_dataset(tmp_path / "split"), open_dataset(tmp_path / "one")
    data_files = sorted({info.data_path.relative_to(split.root).as_posix() for info in split.episode_info.values()})
    assert data_files[-1] == "data/chunk-002/file-000.parquet" and len(data_files) == len(EPISODES)
    assert len({info.videos["observation.images.top"].path for info in split.episode_info.values()}) == len(EPISODES)
    assert all(info.videos["observation.images.top"].from_timestamp == 0 for info in split.episode_info.values())
    _check_mixed(split, given)
    for episode in one.episodes:
        for a, b in zip(split.frames(episode), one.frames(episode), strict=True):
            assert a.keys() == b.keys()
            for key in a:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_small_files_take_several_episodes_until_the_limit(tmp_path):
    """A data limit of about two episodes' rows: episodes share files, and a file is closed once the next episode
    would pass the limit."""
    probe = tmp_path / "probe"
    _write_mixed(probe)
    size_mb = (probe / "data" / "chunk-000" / "file-000.parquet").stat().st_size / 1024**2
    per_frame = size_mb / sum(length for length, _, _ in EPISODES)
    limit = per_frame * 16
    given = _write_mixed(tmp_path / "shared", data_files_size_in_mb=limit)
    ds = open_dataset(tmp_path / "shared")
    files = [ds.episode_info[e].data_path.name for e in ds.episodes]
    assert len(set(files)) < len(files) and len(set(files)) > 1, files
    for path in set(ds.episode_info[e].data_path for e in ds.episodes):
        # a file holds episodes whose rows stay under the limit, or a single episode
        table = pq.read_table(path, columns=["episode_index"])
        episodes = set(table.column("episode_index").to_pylist())
        assert len(episodes) == 1 or table.num_rows * per_frame < limit * 1.5, (path, episodes)
    _check_mixed(ds, given)


# --- crashes ---------------------------------------------------------------------------------------------------


def _frames_of(ds: LeRobotDataset) -> dict[int, list[dict]]:
    return {episode: list(ds.frames(episode)) for episode in ds.episodes}


def _same(a: dict[int, list[dict]], b: dict[int, list[dict]]) -> None:
    assert a.keys() == b.keys()
    for episode in a:
        for x, y in zip(a[episode], b[episode], strict=True):
            assert x.keys() == y.keys()
            for key in x:
                np.testing.assert_array_equal(x[key], y[key], err_msg=f"episode {episode} {key}")


def _two_episodes(root: Path) -> DatasetWriter:
    writer = create_dataset(root, fps=FPS, features=MIXED)
    for e, (length, task, success) in enumerate(EPISODES[:2]):
        for step in range(length):
            writer.add_frame(_frame(e, step, length, success))
        writer.save_episode(task=task)
    return writer


def test_a_crash_while_an_episode_is_recorded_leaves_the_saved_ones_readable(tmp_path):
    writer = _two_episodes(tmp_path / "a")
    saved = _frames_of(open_dataset(tmp_path / "a"))
    for step in range(4):
        writer.add_frame(_frame(2, step, 9, False))
    # the process dies here: nothing after the second save_episode ran
    ds = open_dataset(tmp_path / "a")
    assert ds.episodes == [0, 1]
    _same(_frames_of(ds), saved)


def test_a_crash_while_an_episode_is_saved_leaves_the_saved_ones_readable(tmp_path, monkeypatch):
    """The third save dies after each of its file moves in turn: the first two episodes always read as before, the
    dataset holds two episodes or three, never a broken one, and saving again (the frames are still there) gives the
    dataset an uninterrupted save gives."""
    moves = []
    real_replace = lerobot_writer.os.replace

    def count(src, dst):
        moves.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(lerobot_writer.os, "replace", count)
    full = _two_episodes(tmp_path / "full")
    before = len(moves)
    for step in range(5):
        full.add_frame(_frame(2, step, 5, True))
    full.save_episode(task="pick the cube")
    # the task is not new, so tasks.parquet stays; the episode metadata and info.json move last
    assert [Path(p).relative_to(tmp_path / "full").as_posix() for p in moves[before:]] == [
        "data/chunk-000/file-000.parquet",
        "videos/observation.images.top/chunk-000/file-000.mp4",
        "meta/episodes/chunk-000/file-000.parquet",
        "meta/stats.json",
        "meta/info.json",
    ]
    total = len(moves) - before
    complete = _frames_of(open_dataset(tmp_path / "full"))

    for dies_after in range(total):
        root = tmp_path / f"crash{dies_after}"
        writer = _two_episodes(root)
        saved = _frames_of(open_dataset(root))
        done = []

        def crash(src, dst, done=done, dies_after=dies_after):
            if len(done) == dies_after:
                raise KeyboardInterrupt  # what a kill looks like from inside: nothing after this runs
            done.append(dst)
            real_replace(src, dst)

        monkeypatch.setattr(lerobot_writer.os, "replace", crash)
        for step in range(5):
            writer.add_frame(_frame(2, step, 5, True))
        with pytest.raises(KeyboardInterrupt):
            writer.save_episode(task="pick the cube")
        monkeypatch.setattr(lerobot_writer.os, "replace", real_replace)
        ds = open_dataset(root)
        frames = _frames_of(ds)
        assert ds.episodes in ([0, 1], [0, 1, 2]), (dies_after, ds.episodes)
        _same({e: frames[e] for e in (0, 1)}, saved)
        if ds.episodes == [0, 1, 2]:
            _same(frames, complete)
        assert writer.pending_frames == 5
        writer.save_episode(task="pick the cube")
        _same(_frames_of(open_dataset(root)), complete)
        for relative in ("data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet"):
            assert _columns(root / relative) == _columns(tmp_path / "full" / relative), (dies_after, relative)


# --- bad input -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "feature", "problem"),
    [
        (lambda f: f.pop("action"), "action", "missing"),
        (lambda f: f.update(action=np.zeros(3, np.float32)), "action", "shape [3], the feature is [2]"),
        (lambda f: f.update(action=np.zeros(2, np.float64)), "action", "dtype float64, the feature is float32"),
        (lambda f: f.update({"next.success": np.array([1.0], np.float32)}), "next.success", "dtype float32"),
        (lambda f: f.update({"next.success": 1.0}), "next.success", "a float where the feature is bool"),
        (lambda f: f.update({"observation.count": 2.5}), "observation.count", "a float where the feature is int64"),
        (
            lambda f: f.update({"observation.images.top": np.zeros((64, 48, 3), np.uint8)}),
            "observation.images.top",
            "uint8 [48, 64, 3], got uint8 [64, 48, 3]",
        ),
        (
            lambda f: f.update({"observation.images.wrist": np.zeros((32, 40, 3), np.float32)}),
            "observation.images.wrist",
            "got float32 [32, 40, 3]",
        ),
        (lambda f: f.update(gripper=np.zeros(1, np.float32)), "gripper", "not a declared feature"),
        (lambda f: f.update(timestamp=0.5), "timestamp", "set by the writer"),
    ],
)
def test_a_bad_frame_is_one_line_naming_root_episode_frame_and_feature(change, feature, problem, tmp_path):
    writer = create_dataset(tmp_path / "d", fps=FPS, features=MIXED)
    writer.add_frame(_frame(0, 0, 2, False), task="t")
    frame = _frame(0, 1, 2, False)
    change(frame)
    with pytest.raises(DatasetError) as error:
        writer.add_frame(frame, task="t")
    assert_one_line(error.value, str(tmp_path / "d"), "episode 0", f"'{feature}'", "frame 1", problem)
    assert writer.pending_frames == 1  # the bad frame was not taken


def test_episodes_and_writers_refuse_what_they_cannot_write(tmp_path):
    root = tmp_path / "d"
    writer = create_dataset(root, fps=FPS, features=MIXED)
    with pytest.raises(DatasetError) as error:
        writer.save_episode(task="t")
    assert_one_line(error.value, str(root), "episode 0", "no frames")
    writer.add_frame(_frame(0, 0, 1, False))
    with pytest.raises(DatasetError) as error:
        writer.save_episode()
    assert_one_line(error.value, str(root), "episode 0", "frame 0 has no task")
    with pytest.raises(DatasetError) as error:
        writer.finalize()
    assert_one_line(error.value, str(root), "1 frames added but not saved")
    writer.clear_episode()
    writer.finalize()
    with pytest.raises(DatasetError) as error:
        writer.add_frame(_frame(0, 0, 1, False), task="t")
    assert_one_line(error.value, str(root), "finalized")

    with pytest.raises(DatasetError) as error:
        create_dataset(root, fps=FPS, features=MIXED)
    assert_one_line(error.value, str(root), "not an empty folder")
    bad = [
        ({"a/b": Feature("float32", (1,))}, "'a/b'", "no '/'"),
        ({"index": Feature("int64", (1,))}, "'index'", "written by the writer"),
        ({"cam": Feature("video", (48, 64))}, "'cam'", "[height, width, 3]"),
        ({"x": Feature("float16x", (1,))}, "'x'", "dtype 'float16x'"),
        ({"x": Feature("float32", (2, 2))}, "'x'", "shape [n]"),
    ]
    for i, (features, *parts) in enumerate(bad):
        with pytest.raises(DatasetError) as error:
            create_dataset(tmp_path / f"bad{i}", fps=FPS, features=features)
        assert_one_line(error.value, str(tmp_path / f"bad{i}"), *parts)
    with pytest.raises(DatasetError) as error:
        create_dataset(tmp_path / "codec", fps=FPS, features=MIXED, video=VideoOptions(codec="no-such-codec"))
    assert_one_line(error.value, "'no-such-codec'")
