"""`serve --cam.rerun ADDRESS`: each explained step streamed, as it is written, to a real Rerun viewer process started
here (`rerun --serve-grpc`, headless, saving what it receives to an .rrd), on the entity paths `render --rerun`
gives a run (`viz.rerun_sink`); served through the real server to the real openpi-client. A viewer that is not
there stops the stream, never serving nor the run."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cam_support import demo_obs
from client_env import collect
from real_clients import send_observations
from serve_process import free_port

from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.cam.run_format import load_run
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli import serve
from openpi_cam.cli.serve import SideChannelFlags
from openpi_cam.monitor.fit import Episode, FitOptions, fit_monitor
from openpi_cam.monitor.signals import STAC
from openpi_cam.policies import demo_reach
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.viz.stats import mean_score

KINDS = ("gradnorm", "gradcam")
CALLS = 3
VIEWER_START_S = 60  # a cold start of the viewer's binary on a loaded 2-core machine


def _viewer(tmp_path: Path) -> tuple[subprocess.Popen, str, Path]:
    """`rerun --serve-grpc` on a free port, saving what it receives: (process, its address, the .rrd)."""
    port, rrd, log = free_port(), tmp_path / "viewer.rrd", tmp_path / "viewer.log"
    binary = Path(sys.executable).parent / "rerun"  # rerun-sdk's own launcher, beside the interpreter
    cmd = [str(binary), "--serve-grpc", "--port", str(port), "--save", str(rrd)]
    # A session of its own: the launcher starts the viewer binary as a child, which must go when the test ends too.
    proc = subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + VIEWER_START_S
    while "Listening for gRPC" not in log.read_text():
        assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
        time.sleep(0.1)
    return proc, f"rerun+http://127.0.0.1:{port}/proxy", rrd


def _received(rrd: Path) -> dict[str, dict[str, list]]:
    """entity path -> {"seq": [...], "value": [...]} of what the viewer saved (rerun-sdk's reader)."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(str(rrd)).stream().collect().stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        value = next((n for n in names if n.endswith((":scalars", ":buffer", ":data"))), None)
        if value is None or "seq" not in names:
            continue
        logged = out.setdefault(chunk.entity_path, {"seq": [], "value": []})
        logged["seq"] += batch.column("seq").to_pylist()
        logged["value"] += batch.column(value).to_pylist()
    return out


def _stac_monitor() -> LiveMonitor:
    """A STAC monitor (any model gives its input) with its threshold set on made-up successful episodes: with it
    every call carries its normalised chunk, and explained steps their score and flag."""
    episodes = [Episode({STAC: np.array([np.nan, 0.1 * k, 0.2 * k])}, True) for k in range(1, 5)]
    return LiveMonitor(fit_monitor(episodes, FitOptions(kind="stac")), "stac.json")


def _serve(policy, tmp_path: Path, address: str) -> Path:
    """`serve --monitor STAC --cam.every-k 1 --cam.rerun ADDRESS` (the serve command's own side-channel wiring) with
    CALLS requests of one real client; returns the run directory once the side channel drained."""
    flags = SideChannelFlags(every_k=1, dir=tmp_path / "runs", maps=KINDS, check_patches=0, rerun=address)
    model = ModelSpec(checkpoint_dir=demo_reach.ASSETS / "checkpoint", config="demo_reach")
    served = serve._with_side_channel(policy, flags, model, {}, _stac_monitor())
    server = start_server_in_thread(served, metadata=policy.metadata)
    try:
        collect(send_observations(server.port, tmp_path / "client", [demo_obs(900 + i) for i in range(CALLS)]))
    finally:
        server.stop()
        served.close()
    return served.run_dir


def test_each_explained_step_reaches_a_running_viewer_on_the_renderers_paths(demo_policy, tmp_path):
    import rerun as rr

    viewer, address, rrd = _viewer(tmp_path)
    try:
        run_dir = _serve(demo_policy, tmp_path, address)
        steps = load_run(run_dir).steps
        assert len(steps) == CALLS
        conn = "/" + rr.escape_entity_path_part(steps[0].meta.connection)
        cameras = list(steps[0].meta.cameras)
        wanted = {f"{conn}/score", f"{conn}/chunk", f"{conn}/monitor/score", f"{conn}/monitor/flag"}
        wanted |= {f"{conn}/{c}/{what}" for c in cameras for what in ("frame", "overlay", *KINDS)}
        wanted |= {f"{conn}/share/{c}" for c in cameras}
        deadline = time.monotonic() + 30
        while not (rrd.exists() and all(len(_received(rrd).get(p, {"seq": []})["seq"]) == CALLS for p in wanted)):
            assert time.monotonic() < deadline, sorted(_received(rrd)) if rrd.exists() else "no recording"
            time.sleep(0.2)
    finally:
        os.killpg(viewer.pid, signal.SIGTERM)
        viewer.wait(30)
    got = _received(rrd)
    for step in steps:
        at = got[f"{conn}/score"]["seq"].index(step.seq)
        assert got[f"{conn}/score"]["value"][at][0] == pytest.approx(mean_score(step.meta.score), rel=1e-12)
        for c in cameras:
            frame = step.frames.get(c, step.model_frames.get(c))
            logged = got[f"{conn}/{c}/frame"]
            np.testing.assert_array_equal(np.asarray(logged["value"][logged["seq"].index(step.seq)][0]), frame.ravel())
        score = got[f"{conn}/monitor/score"]["value"][got[f"{conn}/monitor/score"]["seq"].index(step.seq)][0]
        np.testing.assert_equal(score, float(step.monitor["score"]))  # NaN on the connection's first call


def test_a_viewer_that_is_not_there_is_logged_once_and_serving_and_the_run_go_on(demo_policy, tmp_path, caplog):
    address = f"rerun+http://127.0.0.1:{free_port()}/proxy"  # nothing listens there
    with caplog.at_level(logging.WARNING, logger="openpi_cam.viz.rerun_sink"):
        run_dir = _serve(demo_policy, tmp_path, address)
    assert len(load_run(run_dir).steps) == CALLS  # every request answered (collect checks) and explained
    stopped = [r for r in caplog.records if "Rerun stream to" in r.getMessage()]
    assert len(stopped) == 1 and address in stopped[0].getMessage()
