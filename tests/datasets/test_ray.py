"""`explain --engine ray`: the Ray engine writes the local engine's maps dataset, frame for frame; a worker killed
mid-job costs nothing but time (its episode is retried, every frame still written once); a bad episode reaches the
caller as the reader's one-line error, or is skipped and counted with `keep_going`.

The tests share one local Ray instance (2 CPUs; pools of 2 actors, 1 for a bad episode) and one local-engine
reference run. The actors use this session's JAX compilation cache (`tests/conftest.py`, passed on through the
instance's runtime env), which the reference run fills first: an actor then loads the programs this process compiled
instead of compiling them again, and a program an actor builds differently (another shape, mesh or flag) has another
cache key and is compiled there. The comparison is of what each engine feeds those programs and writes: frames, noise
seeds, batching, rows and shards.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import os
import signal
import time

import numpy as np
import psutil
import pytest
from datasets_support import model_job, truncated_video_copy
from paths import LEROBOT_DIR

from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.lerobot.dataset import DatasetError, open_dataset
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import DatasetJob, run_local
from openpi_cam.vocabulary import ExplainOptions

ray = pytest.importorskip("ray")  # the `ray` extra, in `dev`: under CI=true a skip fails
from openpi_cam.maps.ray_engine import EPISODE_RECORD, run_ray  # noqa: E402

SOURCE = LEROBOT_DIR / "demo_reach_v30_video"
# Five episodes of 4 to 8 frames (27 frames): when the first shard appears, four are still to do, so that there is an
# actor in the middle of one to kill.
EPISODES = (0, 1, 2, 3, 6)
KINDS = ("gradcam", "gradnorm")
# No target: the family's default, as the README's command leaves it (the driver must plan the target the actors
# resolve).
OPTIONS = ExplainOptions(maps=KINDS, check_patches=2)
BOX = {"observation.target_box": "target_box"}
WORKERS = 2
# The maps, scores and spot checks of a frame come from the same float32 programs on the same CPU in either engine,
# so they should agree to the last bit; the tolerance only leaves room for a reduction order that another XLA thread
# count could change, far below any difference between two frames' maps.
RTOL = 1e-6
JOB_TIMEOUT_S = 900
ENGINE_LOG = "openpi_cam.maps.ray_engine"


def _job(out, source=SOURCE, episodes=EPISODES) -> DatasetJob:
    return model_job(source, out, OPTIONS, batch_size=4, extra=BOX, episodes=episodes)


@pytest.fixture(scope="module")
def ray_instance():
    # Named explicitly: whether Ray's workers inherit the driver's environment is Ray's choice, not ours.
    names = (
        "JAX_COMPILATION_CACHE_DIR",
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
        "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES",
    )
    env = {name: os.environ[name] for name in names}
    ray.init(num_cpus=WORKERS, include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": env})
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def reference(tmp_path_factory, demo_policy):
    """The local engine's maps dataset of the selected episodes."""
    root = tmp_path_factory.mktemp("local") / "maps"
    run_local(_job(root), policy=demo_policy)
    return fmt.open_maps_dataset(root)


def _assert_same_rows(got: fmt.MapsDataset, want: fmt.MapsDataset) -> None:
    assert got.info == want.info
    assert got.episodes == want.episodes == sorted(EPISODES)
    a, b = got.table().to_pydict(), want.table().to_pydict()
    assert len(a["index"]) == len(set(a["index"])), "a frame was written twice"
    assert a["index"] == b["index"]
    for column in ("episode_index", "frame_index", "task", "target", "malformed", "extra/target_box"):
        assert a[column] == b[column], column
    np.testing.assert_allclose(a["score"], b["score"], rtol=RTOL)
    np.testing.assert_allclose(np.asarray(a["actions"]), np.asarray(b["actions"]), rtol=RTOL)
    for kind in KINDS:
        for camera in want.cameras:
            m, ref = got.maps(kind, camera), want.maps(kind, camera)
            # Relative to the largest value of the kind and camera: a Grad-CAM map can be all zero on a frame.
            scale = float(np.abs(ref).max())
            assert scale > 0, f"{kind}/{camera}: all-zero reference maps cannot catch a difference"
            np.testing.assert_allclose(m, ref, rtol=0, atol=RTOL * scale, err_msg=f"{kind}/{camera}")
            column = fmt.check_column(kind, camera)
            np.testing.assert_allclose(np.asarray(a[column], float), np.asarray(b[column], float), rtol=RTOL)
        random = fmt.check_column(fmt.CHECK_RANDOM, camera)
        np.testing.assert_allclose(np.asarray(a[random], float), np.asarray(b[random], float), rtol=RTOL)


def test_the_ray_engine_writes_the_local_engines_rows(ray_instance, reference, tmp_path):
    root = tmp_path / "maps"
    summary = run_ray(_job(root), workers=WORKERS)
    got = fmt.open_maps_dataset(root)
    _assert_same_rows(got, reference)
    local = reference.summary()
    assert (summary.engine, summary.workers) == ("ray", WORKERS)
    assert summary.episodes_written == len(EPISODES) and not summary.episodes_skipped
    assert summary.counts["explained"] == local["explained"] == len(got.table())
    assert got.summary()["engine"] == "ray"


def _map_workers() -> list[psutil.Process]:
    """The Ray Data actors of this test's Ray instance (descendants of this process)."""
    out = []
    for proc in psutil.Process().children(recursive=True):
        try:
            if "MapWorker" in " ".join(proc.cmdline()):
                out.append(proc)
        except psutil.NoSuchProcess:
            pass
    return out


def _decoding(proc: psutil.Process) -> bool:
    """Whether an actor has one of the source's videos open (it is decoding an episode)."""
    try:
        return any(f.path.endswith(".mp4") and f.path.startswith(str(SOURCE.resolve())) for f in proc.open_files())
    except psutil.Error:
        return False


@pytest.mark.slow
def test_a_killed_worker_is_retried_and_every_frame_written_once(ray_instance, reference, tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger=ENGINE_LOG)
    root = tmp_path / "maps"
    data = root / fmt.DATA_DIR
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        job = pool.submit(run_ray, _job(root), workers=WORKERS)
        deadline = time.monotonic() + JOB_TIMEOUT_S
        # Once the first shard is written, kill the first actor seen in the middle of an episode: the source's video
        # files are open only while an episode is decoded, so the killed actor holds an episode not yet written.
        while True:
            assert not job.done(), f"the job ended before a worker could be killed mid-episode: {job.exception()}"
            assert time.monotonic() < deadline, "no worker was seen mid-episode after the first shard"
            if fmt.written_episodes(root):  # the process table is read only from then on: it costs this process CPU
                workers = _map_workers()
                victim = next((w for w in workers if _decoding(w)), None)
                if victim is not None:
                    break
            time.sleep(0.02)
        shards_before = fmt.written_episodes(root)
        victim.send_signal(signal.SIGKILL)
        victim.wait(timeout=30)
        assert len(workers) == WORKERS and 0 < len(shards_before) < len(EPISODES), (workers, shards_before)
        # What a writer killed between its temporary file and the rename leaves behind: never read as a shard.
        leftover = data / "chunk-000" / f".episode_{EPISODES[-1]:06d}.parquet.{victim.pid}-00000000.tmp"
        leftover.write_bytes(b"PAR1 truncated")
        summary = job.result(timeout=JOB_TIMEOUT_S)

    assert summary.episodes_written == len(EPISODES) and not summary.episodes_skipped
    assert summary.counts["explained"] == len(reference.table())
    got = fmt.open_maps_dataset(root)
    _assert_same_rows(got, reference)  # every expected index present, none twice, the same maps
    assert leftover.exists() and got.episodes == sorted(EPISODES)
    # The killed actor was restarted (a new process) and did work: the episode it held was retried on it.
    records = [getattr(r, EPISODE_RECORD) for r in caplog.records if hasattr(r, EPISODE_RECORD)]
    done_by = [r["worker"].rsplit(":", 1)[1] for r in records]
    assert len(done_by) == len(EPISODES)
    old = {str(w.pid) for w in workers}
    assert set(done_by) - old, f"no episode was done by a restarted actor: {done_by} (actors before: {sorted(old)})"
    assert got.summary()["episodes_written"] == len(EPISODES)


@pytest.mark.slow
def test_a_bad_episode_stops_the_job_or_is_skipped_with_keep_going(ray_instance, tmp_path):
    source = truncated_video_copy(tmp_path / "source")
    job = _job(tmp_path / "maps", source, episodes=(1, 2))
    # One actor per job: where an error goes does not depend on the pool's size, and each actor loads a model.
    # The worker's error reaches the caller as the reader's one line, not as a Ray traceback.
    with pytest.raises(DatasetError, match=r"episode_000002\.mp4.*episode 2|episode 2.*episode_000002\.mp4"):
        run_ray(dataclasses.replace(job, episodes=(2,)), workers=1)
    summary = run_ray(dataclasses.replace(job, keep_going=True), workers=1)
    assert list(summary.episodes_skipped) == [2] and "episode_000002.mp4" in summary.episodes_skipped[2]
    assert summary.episodes_written == 1
    maps = fmt.open_maps_dataset(job.out)
    assert maps.episodes == [1] and maps.summary()["episodes_skipped"].keys() == {"2"}
    assert maps.table().column("frame_index").to_pylist() == list(range(open_dataset(source).episode_length(1)))


@pytest.mark.slow
def test_the_ray_engine_runs_a_lerobot_policy_folder(ray_instance, demo_pi05_lerobot, tmp_path):
    """A LeRobot folder on the Ray engine: the driver plans info.json from the folder's files alone (no config, its
    own feature names), the actors load the folder, and the shards are the local engine's."""
    model = ModelSpec(demo_pi05_lerobot)
    options = ExplainOptions(maps=("gradnorm",), check_patches=0)

    def job(out):
        return model_job(SOURCE, out, options, model, batch_size=4, episodes=(0, 1))

    run_local(job(tmp_path / "local"))
    run_ray(job(tmp_path / "ray"), workers=1)
    local, remote = fmt.open_maps_dataset(tmp_path / "local"), fmt.open_maps_dataset(tmp_path / "ray")
    assert remote.info == local.info and remote.info.model["config"] is None
    ours, theirs = remote.maps("gradnorm", "observation.images.base"), local.maps("gradnorm", "observation.images.base")
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=RTOL * float(np.abs(theirs).max()))
