"""Dataset-level views of a maps dataset: `stats` and `render` on a real maps dataset, explained by the bundled demo
model from a LeRobot-written dataset (`../shared/lerobot/demo_reach_v30_video`), and the hot-patch rule on arrays.

One maps dataset (2 episodes, Grad-CAM and gradient norm, 2 random patches per spot check) is built once for the
module: the model run is the expensive part."""

from __future__ import annotations

import fractions
import json
import shutil

import av
import numpy as np
import pyarrow as pa
import pyarrow.compute
import pyarrow.parquet as pq
import pytest
from datasets_support import model_job
from paths import LEROBOT_DIR

from openpi_cam import cli
from openpi_cam.lerobot.dataset import open_dataset
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.dataset import open_maps_dataset
from openpi_cam.maps.explain import run_local
from openpi_cam.maps.frames import aligned_frames, episode_rows, video_fps
from openpi_cam.maps.render import DatasetRenderOptions, episode_frame
from openpi_cam.maps.views import compute_views, flag_hot, hot_rates, in_top_k, prior_fit, top_k
from openpi_cam.viz.colormap import colorize
from openpi_cam.viz.overlay import upsample
from openpi_cam.vocabulary import ExplainOptions

SOURCE = LEROBOT_DIR / "demo_reach_v30_video"
EPISODES = (0, 1)
KINDS = ("gradcam", "gradnorm")
CAMERA_FEATURES = {"base_0_rgb": "observation.images.base", "wrist_0_rgb": "observation.images.wrist"}


@pytest.fixture(scope="module")
def maps_root(tmp_path_factory):
    out = tmp_path_factory.mktemp("maps") / "demo_maps"
    # The options of tests/cam's dataset jobs (batches of 4 included): the same compiled programs, which a process of
    # the test run may then load from JAX's compilation cache instead of compiling.
    options = ExplainOptions(target="action-token", maps=KINDS, check_patches=2)
    summary = run_local(model_job(SOURCE, out, options, batch_size=4, episodes=EPISODES))
    assert summary.as_json()["episodes_written"] == len(EPISODES)
    return out


def _parquet(root) -> pa.Table:
    """Every shard of a maps dataset, read with pyarrow alone, sorted by index."""
    return pa.concat_tables([pq.read_table(p) for p in sorted((root / "data").rglob("*.parquet"))]).sort_by("index")


def _maps(table: pa.Table, kind: str, camera: str) -> np.ndarray:
    """The table's raw maps of one kind and camera as the renderers see them: [N, 4, 4], negatives and NaN as 0."""
    m = np.array(table.column(f"{kind}/{camera}").to_pylist(), np.float64).reshape(table.num_rows, 4, 4)
    return np.clip(np.nan_to_num(m), 0.0, None)


def test_stats_rows_one_per_frame_with_the_run_statistics_of_each_map(maps_root, tmp_path):
    table = _parquet(maps_root)
    out = tmp_path / "stats.json"
    cli.main(["stats", str(maps_root), "--format", "json", "--out", str(out), "--map", "gradnorm"])
    data = json.loads(out.read_text())
    frames = data["frames"]
    assert [r["index"] for r in frames] == table.column("index").to_pylist()
    assert data["summary"]["frames"] == table.num_rows == len(frames)
    for camera in CAMERA_FEATURES:
        maps = _maps(table, "gradnorm", camera)
        for row, m in zip(frames, maps, strict=True):
            # The frame's peak is the map's argmax (gradient norms are positive, so ties are not expected).
            assert (row[f"{camera}/peak_row"], row[f"{camera}/peak_col"]) == np.unravel_index(np.argmax(m), m.shape)
    totals = {c: _maps(table, "gradnorm", c).sum(axis=(1, 2)) for c in CAMERA_FEATURES}
    for i, row in enumerate(frames):
        expected = totals["base_0_rgb"][i] / (totals["base_0_rgb"][i] + totals["wrist_0_rgb"][i])
        assert row["base_0_rgb/share"] == pytest.approx(expected, rel=1e-9)
        assert row["base_0_rgb/share"] + row["wrist_0_rgb/share"] == pytest.approx(1.0)
    # CSV: the same rows, a header and one line per frame.
    csv_out = tmp_path / "stats.csv"
    cli.main(["stats", str(maps_root), "--out", str(csv_out)])
    lines = csv_out.read_text().splitlines()
    assert len(lines) == 1 + table.num_rows and "base_0_rgb/prior_cosine" in lines[0].split(",")
    # A kind the dataset does not hold is refused with a message, not a traceback.
    with pytest.raises(SystemExit) as e:
        cli.main(["stats", str(maps_root), "--map", "ig"])
    assert e.value.code == 2


def test_prior_is_the_mean_normalised_map_and_fits_each_frame(maps_root):
    """The prior recomputed from the parquet alone: per camera, the mean over frames of each map divided by its sum."""
    table = _parquet(maps_root)
    for kind in KINDS:
        views = compute_views(open_maps_dataset(maps_root), kind)
        for camera in CAMERA_FEATURES:
            maps = _maps(table, kind, camera)
            total = maps.sum(axis=(1, 2))
            p = maps[total > 0] / total[total > 0, None, None]
            # float64 sums of the same float32 values in another order: equal to rounding.
            np.testing.assert_allclose(views.prior[camera], p.mean(axis=0), rtol=1e-12, atol=1e-15)
            assert views.fit[camera]["frames"] == len(p)
            with_mass = [r for r in views.rows if r[f"{camera}/prior_cosine"] is not None]
            for row, q in zip(with_mass, p, strict=True):
                prior = p.mean(axis=0)
                cosine = float((q * prior).sum() / np.linalg.norm(q) / np.linalg.norm(prior))
                assert row[f"{camera}/prior_cosine"] == pytest.approx(cosine, rel=1e-9)
                assert row[f"{camera}/prior_distance"] == pytest.approx(0.5 * np.abs(q - prior).sum(), rel=1e-9)


def test_the_fit_gives_the_rate_of_frames_whose_peak_sits_on_a_hot_patch(maps_root):
    """`fit[c]["peak_on_hot"]` is the mean of the per-frame flags (a mean that skipped bools left it None)."""
    for kind in KINDS:
        views = compute_views(open_maps_dataset(maps_root), kind)
        for camera in CAMERA_FEATURES:
            flags = [r[f"{camera}/peak_on_hot"] for r in views.rows if r[f"{camera}/peak_on_hot"] is not None]
            assert flags and all(isinstance(f, bool) for f in flags)
            # a mean of 0s and 1s: exact but for the last bit of the division
            assert views.fit[camera]["peak_on_hot"] == pytest.approx(np.mean(flags), rel=1e-12)


def test_hot_patch_rule_flags_a_patch_hot_in_every_frame_and_nothing_else():
    rng = np.random.default_rng(0)
    maps = rng.random((400, 16, 16))
    maps[:, 3, 5] = 2.0  # the frame's largest value, whatever else the frame holds
    some = rng.random(400) < 0.4
    maps[some, 0, 0] = 2.0  # top of 40% of frames: more than chance, less than the threshold
    k = top_k(256, 0.05)
    assert k == 13
    rates = hot_rates(maps, k)
    assert rates[3, 5] == 1.0
    assert rates[0, 0] == pytest.approx(some.mean() + (1 - some.mean()) * 11 / 254, abs=0.05)
    # Elsewhere each patch is in the top-13 of about 11 / 254 of the frames (4.3%); 0.15 is > 5 sigma above it.
    others = np.delete(rates.reshape(-1), [0, 3 * 16 + 5])
    assert others.max() < 0.15
    assert [(h.row, h.col) for h in flag_hot("cam", rates, 0.5)] == [(3, 5)]
    # Maps without mass are left out; ties at the k-th value all count.
    assert hot_rates(np.zeros((5, 4, 4)), 1).sum() == 0
    assert in_top_k(np.ones((1, 4, 4)), 1).all()
    # A camera the model masked in every frame (pi0.5's blank right wrist) leaves no frame: nothing hot, no error.
    assert (
        in_top_k(np.zeros((0, 4, 4)), 1).shape == (0, 4, 4)
        and prior_fit(np.zeros((0, 4, 4)), np.ones((4, 4)))[2].size == 0
    )


def _write_episode(root, source_episode: int, episode: int, spread: bool) -> None:
    """A copy of `source_episode`'s shard as `episode`, each frame's maps replaced by maps nothing like the model's:
    the same value on every patch (`spread`: entropy 1), or a single hot patch at a pseudo-random place (entropy 0)."""
    info = open_maps_dataset(root).info
    rows = pq.read_table(root / fmt.shard_path(source_episode)).to_pylist()
    rng = np.random.default_rng(7)
    for r in rows:
        r["episode_index"] = episode
        r["index"] += 10_000 * episode
        for kind in KINDS:
            for camera in CAMERA_FEATURES:
                m = np.ones(16, np.float32) if spread else np.eye(16, dtype=np.float32)[rng.integers(16)]
                r[f"{kind}/{camera}"] = m.tolist()
    fmt.write_shard(root, info, episode, rows)


def test_episode_ranking_puts_the_most_diffuse_maps_first(maps_root, tmp_path):
    root = tmp_path / "maps"
    shutil.copytree(maps_root, root)
    _write_episode(root, 0, 9, spread=True)
    _write_episode(root, 1, 10, spread=False)
    views = compute_views(open_maps_dataset(root), "gradnorm")
    ranking = views.episodes
    assert ranking[0]["episode_index"] == 9 and ranking[0]["entropy"] == pytest.approx(1.0)
    assert ranking[-1]["episode_index"] == 10 and ranking[-1]["entropy"] == 0.0
    assert sorted(e["episode_index"] for e in ranking) == [*EPISODES, 9, 10]
    assert ranking[0]["z"] > 0 > ranking[-1]["z"]
    # The z-scores are those of the episodes' mean entropies; the entropy is the frames' mean over cameras.
    h = np.array([e["entropy"] for e in ranking])
    np.testing.assert_allclose([e["z"] for e in ranking], (h - h.mean()) / h.std(), rtol=1e-9)
    for e in ranking:
        rows = [r for r in views.rows if r["episode_index"] == e["episode_index"]]
        frames = [np.mean([r[f"{c}/entropy_norm"] for c in CAMERA_FEATURES]) for r in rows]
        assert e["entropy"] == pytest.approx(np.mean(frames), rel=1e-12)


def test_render_writes_an_aligned_video_per_episode_a_report_and_a_lerobot_shaped_recording(maps_root, tmp_path):
    out, rrd = tmp_path / "render", tmp_path / "maps.rrd"
    cli.main(["render", str(maps_root), "--out", str(out), "--no-progress", "--rerun", str(rrd)])
    ds = open_maps_dataset(maps_root)
    lr = open_dataset(SOURCE)
    views = compute_views(ds, "gradnorm")
    stats = {r["index"]: r for r in views.rows}
    opts = DatasetRenderOptions()
    html = (out / "index.html").read_text()
    for episode in EPISODES:
        rows = episode_rows(ds, episode, "gradnorm")
        # The video: one frame per row, at the source's rate.
        with av.open(str(out / "videos" / f"episode_{episode:06d}.mp4")) as container:
            stream = container.streams.video[0]
            assert stream.average_rate == lr.fps
            got = [f.to_ndarray(format="rgb24").astype(int) for f in container.decode(stream)]
        assert len(got) == len(rows)
        # Each decoded frame matches the overlay of its own source frame: H.264 (crf 18, yuv420p) leaves a mean
        # error near 1.3 of 255 on these panels; any other frame of the episode is further away (>= 3).
        want = [
            episode_frame(rows, i, im, stats[rows.index[i]], views, opts, 0.0)
            for i, im in enumerate(aligned_frames(ds, lr, rows))
        ]
        for i, frame in enumerate(got):
            errors = [np.abs(frame - w).mean() for w in want]
            assert errors[i] < 2.5 and int(np.argmin(errors)) == i, (episode, i, errors)
        assert f"id='episode-{episode}'" in html and f"data-frames='{len(rows)}'" in html
    assert "positional prior" in html and "episodes, most diffuse maps first" in html and "per task" in html
    assert "top patch beats the median random patch" in html
    for camera in CAMERA_FEATURES:
        assert (out / "prior" / f"{camera}-prior.png").is_file()
    _check_recording(rrd, ds, lr)


def test_render_norm_run_scales_every_frame_by_the_rendered_episodes_largest_value(maps_root, tmp_path):
    """`--norm run`: one scale, the largest value of any valid camera's map in the rendered episodes (computed here
    from the parquet alone), instead of each frame's own."""
    episode, out = EPISODES[1], tmp_path / "render"
    cli.main(
        ["render", str(maps_root), "--out", str(out), "--no-progress", "--norm", "run", "--episodes", str(episode)]
    )
    table = _parquet(maps_root)
    table = table.filter(pa.compute.equal(table.column("episode_index"), episode))
    valid = [json.loads(text or "{}") for text in table.column("cameras").to_pylist()]
    top = max(
        float(m.max())
        for camera in CAMERA_FEATURES
        for m, v in zip(_maps(table, "gradnorm", camera), valid, strict=True)
        if v.get(camera, {}).get("valid", True)
    )
    ds, lr = open_maps_dataset(maps_root), open_dataset(SOURCE)
    views = compute_views(ds, "gradnorm")
    stats = {r["index"]: r for r in views.rows}
    rows = episode_rows(ds, episode, "gradnorm")
    images = list(aligned_frames(ds, lr, rows))
    with av.open(str(out / "videos" / f"episode_{episode:06d}.mp4")) as container:
        got = [f.to_ndarray(format="rgb24").astype(int) for f in container.decode(container.streams.video[0])]
    step_errors = []
    for i, frame in enumerate(got):
        run = episode_frame(rows, i, images[i], stats[rows.index[i]], views, DatasetRenderOptions(norm="run"), top)
        step = episode_frame(rows, i, images[i], stats[rows.index[i]], views, DatasetRenderOptions(), 0.0)
        # H.264's error on these panels: mean near 1.3 of 255 (the test above)
        assert np.abs(frame - run).mean() < 2.5, i
        step_errors.append(np.abs(frame - step).mean())
    assert max(step_errors) > 2.5  # some frame's own maximum is below the episode's: the flag changed the video
    assert "over the rendered episodes" in (out / "index.html").read_text()


def test_default_video_rate_and_stats_file_of_a_maps_dataset(maps_root, tmp_path):
    """Defaults: a video frame per explained frame (the source's rate divided by the job's `every`), and `stats
    --format parquet` without --out writes `stats-<kind>.parquet` in the maps dataset."""
    copy = tmp_path / "maps"
    shutil.copytree(maps_root, copy)
    lr = open_dataset(SOURCE)
    assert video_fps(open_maps_dataset(copy), lr) == lr.fps
    info = json.loads((copy / fmt.INFO_JSON).read_text())
    (copy / fmt.INFO_JSON).write_text(json.dumps(info | {"every": 2}))
    assert video_fps(open_maps_dataset(copy), lr) == fractions.Fraction(lr.fps, 2)
    cli.main(["stats", str(copy), "--format", "parquet"])
    written = pq.read_table(copy / "stats-gradnorm.parquet")
    assert written.num_rows == _parquet(maps_root).num_rows


def _check_recording(rrd, ds, lr) -> None:
    """LeRobot's entity paths and timelines: the frame under the camera's feature name, the map as its child layer,
    `frame_index` / `timestamp` / `episode_index` / `index` as the maps dataset holds them."""
    from rerun.chunk import RrdReader

    logged: dict[str, dict[int, tuple]] = {}  # entity -> index -> (frame_index, episode_index, ns, image)
    for chunk in RrdReader(str(rrd)).store().stream():
        batch = chunk.to_record_batch()
        if "Image:buffer" not in batch.schema.names:
            continue
        entity = logged.setdefault(chunk.entity_path, {})
        columns = zip(
            batch.column("index").to_pylist(),
            batch.column("frame_index").to_pylist(),
            batch.column("episode_index").to_pylist(),
            batch.column("timestamp").cast(pa.int64()).to_pylist(),
            batch.column("Image:buffer").to_pylist(),
            batch.column("Image:format").to_pylist(),
            strict=True,
        )
        for index, frame_index, episode, ns, buf, f in columns:
            image = np.asarray(buf[0], np.uint8).reshape(f[0]["height"], f[0]["width"], -1)
            entity[index] = (frame_index, episode, ns, image)
    expected = {f"/{f}" for f in CAMERA_FEATURES.values()} | {f"/{f}/gradnorm" for f in CAMERA_FEATURES.values()}
    assert set(logged) == expected
    table = _parquet(ds.root)
    timelines = {
        i: (f, e, t)
        for i, f, e, t in zip(
            *(table.column(k).to_pylist() for k in ("index", "frame_index", "episode_index", "timestamp")), strict=True
        )
    }
    for entity in logged.values():
        assert sorted(entity) == sorted(timelines)
        for index, (frame_index, episode, ns, _) in entity.items():
            assert (frame_index, episode) == timelines[index][:2]
            assert ns / 1e9 == pytest.approx(timelines[index][2], abs=2e-9)  # Rerun keeps whole nanoseconds
    for episode in EPISODES:
        rows = episode_rows(ds, episode, "gradnorm")
        for i, images in enumerate(aligned_frames(ds, lr, rows)):
            maps = rows.frame_maps(i)
            scale = max(float(m.max()) for m in maps.values())  # per frame, over its cameras (the default)
            for camera, feature in CAMERA_FEATURES.items():
                frame = images[camera]
                np.testing.assert_array_equal(logged[f"/{feature}"][rows.index[i]][3], frame)
                heat = colorize(upsample(maps[camera], *frame.shape[:2]) / scale)
                np.testing.assert_array_equal(logged[f"/{feature}/gradnorm"][rows.index[i]][3], heat)
