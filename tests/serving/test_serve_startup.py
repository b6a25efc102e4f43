"""`openpi-cam serve` with default flags starts on every family, and `--cam.every-k 1` explains each request with the
family's own target (pi0-FAST `action-token`, pi0 / pi0.5 `chunk`), driven by the real openpi-client. A target the
family cannot explain, and the other start-up mistakes an operator makes (an unknown config, a checkpoint of another
family, a bad flag, a port in use), end with one line on stderr and no traceback. In process: the side channel's
flags are one dataclass, checked as they are parsed, and build the options they name."""

from __future__ import annotations

import dataclasses
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import tyro
from client_env import collect
from demo_inputs import demo_observation
from paths import GOLDEN_DIR, REPO_ROOT
from real_clients import round_trip, send_observations
from serve_process import serve_cmd, serve_subprocess, stop

from openpi_cam.cam.run_format import RUN_JSON, load_run, read_json
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints import model_spec
from openpi_cam.cli import serve
from openpi_cam.cli.options import ExplainFlags
from openpi_cam.policies import demo_reach
from openpi_cam.vocabulary import DEFAULT_KINDS, MapOptions

PI05_DEMO = demo_reach.ASSETS_PI05
PI0_LIBERO = GOLDEN_DIR / "tiny_policy_pi0_libero"

# family -> (the flags naming its checkpoint, the client's robot, the family's default target, what it explains)
FAMILIES = {
    "pi0_fast": ((), "demo", "action-token", "action-token, all-action-tokens, chunk, generated-tokens"),
    "pi05": (
        (
            "--checkpoint-dir", str(PI05_DEMO / "checkpoint"), "--config", demo_reach.DEMO_PI05_CONFIG.name,
            "--paligemma-tokenizer", str(PI05_DEMO / "paligemma_tokenizer.model"), "--dtype", "float32",
        ),
        "demo",
        "chunk",
        "action, chunk",
    ),
    "pi0": (
        (
            "--checkpoint-dir", str(PI0_LIBERO / "checkpoint"), "--config", "pi0_libero",
            "--paligemma-tokenizer", str(PI0_LIBERO / "paligemma_tokenizer_tiny.model"), "--dtype", "float32",
        ),
        "libero",
        "chunk",
        "action, chunk",
    ),
}  # fmt: skip
WRONG_TARGET = {"pi0_fast": "action", "pi05": "action-token"}
LABELS = {"pi0_fast": "pi0-FAST", "pi05": "pi0.5", "pi0": "pi0"}
STEP_WAIT_S = 300  # the first explanation compiles in the background (minutes on a loaded 2-core machine)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(serve_cmd(*args), capture_output=True, text=True, timeout=300, cwd=REPO_ROOT)


def _one_line(proc: subprocess.CompletedProcess) -> str:
    """The only line of stderr (the command's refusal), with no traceback."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


def _wait_for_step(cam_dir: Path) -> None:
    deadline = time.monotonic() + STEP_WAIT_S
    while not list(cam_dir.glob("*/steps/*.npz")):
        assert time.monotonic() < deadline, f"no step written under {cam_dir} within {STEP_WAIT_S} s"
        time.sleep(0.5)


# pi0 and pi0.5 share the flow-matching default: the fast tier starts pi0.5, the slow tier pi0 too.
@pytest.mark.parametrize("family", [pytest.param(f, marks=[pytest.mark.slow] if f == "pi0" else []) for f in FAMILIES])
def test_serve_with_default_flags_explains_with_the_familys_target(family, tmp_path):
    """Warm-up on (it compiles the configured explanation: with another family's target it would fail there), one
    request from the real client, and its step holds the default kinds' maps of the family's default target."""
    flags, robot, target, _ = FAMILIES[family]
    cam_dir = tmp_path / "cam"
    # `--cam-every-k`, the spelling of earlier releases, is an alias of `--cam.every-k`.
    on = "--cam-every-k" if family == "pi0_fast" else "--cam.every-k"
    with serve_subprocess(tmp_path, *flags, on, "1", "--cam.dir", str(cam_dir)) as (proc, port, log):
        assert f"explaining every 1 request(s) of each connection, target {target}," in log.read_text()
        if robot == "demo":
            client = send_observations(port, tmp_path / "client", [demo_observation(7)])
        else:
            client = round_trip(port, tmp_path / "client", env=robot)
        collect(client)
        _wait_for_step(cam_dir)
        stop(proc, log)
    (run_json,) = cam_dir.glob(f"*/{RUN_JSON}")
    run = load_run(run_json.parent)
    assert run.run_info["options"]["target"] == target  # the run records the resolved target, not "default"
    (step,) = run.steps
    assert step.meta.target == target
    assert step.map_kinds == DEFAULT_KINDS == ("occlusion",)  # the kind the maps bench chose
    occlusion = step.maps_of("occlusion")
    assert occlusion and any(np.abs(m).max() > 0 for m in occlusion.values())  # a real map, not an empty placeholder


@pytest.mark.parametrize("family", list(WRONG_TARGET))
def test_a_target_the_family_cannot_explain_is_refused_in_one_line(family, tmp_path):
    flags, _, _, explains = FAMILIES[family]
    wrong = WRONG_TARGET[family]
    cam_dir = tmp_path / "cam"
    proc = _run(*flags, "--cam.every-k", "1", "--cam.dir", str(cam_dir), "--cam.target", wrong, "--no-warm-up")
    assert proc.returncode == 2, proc.stderr
    assert _one_line(proc) == f"openpi-cam serve: --cam.target {wrong}: {LABELS[family]} explains {explains}"
    assert not cam_dir.exists()  # refused before a run directory was created


def test_startup_mistakes_end_in_one_line_without_a_traceback(tmp_path):
    pi05_checkpoint = str(PI05_DEMO / "checkpoint")
    unknown = _run("--checkpoint-dir", pi05_checkpoint, "--config", "no_such_config", "--no-warm-up")
    assert unknown.returncode == 1
    line = _one_line(unknown)
    assert "unknown policy config 'no_such_config'" in line and "pi05_droid" in line  # it lists the known ones

    other_family = _run("--checkpoint-dir", pi05_checkpoint, "--config", demo_reach.DEMO_CONFIG.name, "--no-warm-up")
    assert other_family.returncode == 1
    assert _one_line(other_family).endswith(f"serves pi0_fast, the checkpoint at {pi05_checkpoint}/params is pi05")

    bad_flag = _run("--cam.every-k", "-1")
    assert bad_flag.returncode == 2 and "Traceback" not in bad_flag.stderr, bad_flag.stderr
    assert "every_k >= 0" in bad_flag.stderr

    with socket.socket() as taken:  # a port another process listens on
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        busy = _run("--host", "127.0.0.1", "--port", str(port), "--no-warm-up")
    assert busy.returncode == 1
    assert f"openpi-cam serve: cannot listen on 127.0.0.1:{port}:" in busy.stderr, busy.stderr
    assert "Traceback" not in busy.stderr, busy.stderr


# ---------------------------------------------------------------- the flags, in process


def test_serve_help_lists_every_side_channel_flag_from_its_one_dataclass(capsys):
    with pytest.raises(SystemExit) as exit_:
        tyro.cli(serve.main, args=["--help"])
    assert exit_.value.code == 0
    shown = capsys.readouterr().out
    for field in dataclasses.fields(serve.SideChannelFlags):
        assert f"--cam.{field.name.replace('_', '-')}" in shown, field.name


def test_side_channel_flags_build_the_options_they_name(tmp_path):
    flags = serve.SideChannelFlags(
        every_k=2, dir=tmp_path, save_frames="both", target="action", action_index="3,1", maps=("ig", "gradnorm"),
        baseline="blur", occlusion_region=2, occlusion_masks=16, ig_space="pixels", check_patches=0, queue_size=3,
        per_connection=1, settle_ms=2.5, device=0, max_steps=9, max_mb=1.5, max_extra_value_kb=2.0, max_extra_kb=4.0,
        stats_window=50,
    )  # fmt: skip
    options = flags.options()
    assert (options.every_k, options.dir, options.save_frames, options.target) == (2, tmp_path, "both", "action")
    assert (options.action_index, options.action_dim_index, options.maps) == (3, 1, ("ig", "gradnorm"))
    assert options.map_options == MapOptions(
        baseline="blur", occlusion_region=2, occlusion_mode="random", random_masks=16, ig_space="pixels"
    )
    assert (options.check_patches, options.queue_size, options.per_connection, options.settle_ms) == (0, 3, 1, 2.5)
    assert (options.device, options.max_steps, options.max_mb, options.stats_window) == (0, 9, 1.5, 50)
    assert (options.max_extra_value_kb, options.max_extra_kb) == (2.0, 4.0)
    # Left alone, the flags give the library's own options: one name, unit and default each.
    assert serve.SIDE_CHANNEL_OFF.options() == CAMOptions()
    assert flags.options(target="chunk").target == "chunk"  # the served family's resolved target stands in


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--cam.every-k", "-1"], "every_k >= 0"),
        (["--cam.action-index", "1,x"], "action index must be 'I' or 'H,D'"),
        (["--cam.occlusion-masks", "-3"], "occlusion_masks must be >= 0"),
        (["--cam.check-patches", "-1"], "check_patches must be >= 0"),
        (["--cam.queue-size", "0"], "queue_size >= 1"),
        (["--cam.maps"], "map kinds must be a non-empty selection"),
    ],
)
def test_bad_side_channel_flags_are_refused_as_the_command_line_is_parsed(flags, needle, capsys):
    """Checked once, by the dataclasses the flags build, before any model is loaded (exit status 2)."""
    with pytest.raises(SystemExit) as exit_:
        tyro.cli(serve.main, args=flags)
    assert exit_.value.code == 2
    assert needle in " ".join(capsys.readouterr().err.replace("│", " ").split())


def test_the_side_channel_explains_the_familys_target_unless_told_and_refuses_one_it_cannot(demo_policy, tmp_path):
    """`wrap_policy_with_cam` resolves no target to the family's default (recorded in the run) and refuses a target
    the family cannot explain before creating anything."""
    wrapped = wrap_policy_with_cam(demo_policy, CAMOptions(every_k=1, dir=tmp_path / "runs"))
    try:
        assert read_json(wrapped.run_dir / RUN_JSON)["options"]["target"] == "action-token"
    finally:
        wrapped.close(0)
    pi05 = model_spec.create_demo_policy(model="pi05")
    assert pi05.explainer.targets == ("action", "chunk") and pi05.explainer.default_target == "chunk"
    with pytest.raises(ValueError, match=r"^action-token: pi0\.5 explains action, chunk$"):
        wrap_policy_with_cam(pi05, CAMOptions(every_k=1, dir=tmp_path / "refused", target="action-token"))
    assert not (tmp_path / "refused").exists()


def test_explain_refuses_a_target_the_family_cannot_explain(tmp_path, capsys):
    from openpi_cam.cli import explain_run

    records = tmp_path / "records"
    records.mkdir()  # an empty PolicyRecorder folder: the refusal comes before any observation is read
    status = explain_run.main(records, out=tmp_path / "runs", explanation=ExplainFlags(target="action"), progress=False)
    assert status == 2
    assert capsys.readouterr().err.strip() == (
        "openpi-cam explain-run: --target action: pi0-FAST explains action-token, all-action-tokens, chunk, "
        "generated-tokens"
    )
    assert not (tmp_path / "runs").exists()


def test_serve_refuses_server_limits_it_cannot_serve_with(capsys):
    assert serve.main(max_message_mb=8.0, max_buffered_mb=4.0, warm_up=False) == 2
    err = capsys.readouterr().err
    assert "openpi-cam serve: server limits" in err and "max_buffered_bytes >= max_message_bytes" in err


def test_serve_refuses_a_negative_drain_timeout_before_loading_a_model(capsys):
    """`--drain-timeout` is the server's own flag (it bounds the recorder's drain too, with the side channel off),
    checked with the other start-up flags, before the model loads (the server's own check would name the server
    limits)."""
    assert serve.main(drain_timeout=-1.0, warm_up=False) == 2
    assert "openpi-cam serve: --drain-timeout must be >= 0, got -1.0" in capsys.readouterr().err
