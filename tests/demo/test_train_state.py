"""A stopped training run continues with `--resume` to the params the unstopped run ends with (`demo.train_state`).

The slow tests stop real `python -m openpi_cam.demo.train` processes, by SIGTERM (the run saves and exits) and by
SIGKILL (nothing runs; the last `--save-every` state is what is left), in each of pi0-FAST's two phases, and compare
the resumed run's checkpoint with an unstopped run's, bit for bit: on one CPU a step is a deterministic function of
the state and the step's index, so any difference is a resume that lost or changed something. The fast ones show the
refusals: no state, another run's state, a corrupt file."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import tyro

from openpi_cam.cli import train_demo
from openpi_cam.demo import train, train_state
from openpi_cam.model.checkpoint import load_params

# A tiny pi0-FAST: enough steps in each phase that a signal sent on a logged step lands well before the phase ends.
TINY = ("--steps", "40", "--finetune-steps", "30", "--eval-episodes", "0", "--probe-every", "0", "--log-every", "1",
        "--width", "16", "--depth", "1", "--vit-width", "16", "--batch-size", "2")  # fmt: skip


def _command(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "openpi_cam.demo.train", "--out", str(out), *TINY, *extra]


def _train(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(_command(out, *extra), capture_output=True, text=True, timeout=600)


def _stopped(out: Path, at: str, signum: int, *extra: str, command: list[str] | None = None) -> tuple[int, str, str]:
    """Runs the tiny training (or `command`) and sends `signum` once it logs the line starting with `at`; (exit
    status, out, err)."""
    command = command or _command(out, *extra)
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = []
    for line in process.stdout:
        seen.append(line)
        if line.startswith(at):
            process.send_signal(signum)
            break
    rest, err = process.communicate(timeout=600)
    return process.returncode, "".join(seen) + rest, err


def _logged(text: str) -> dict[str, str]:
    """Logged step -> its loss line (the timing dropped)."""
    lines = [line.rsplit(" ", 1)[0] for line in text.splitlines() if " loss " in line]
    return {line.split(" loss ")[0]: line for line in lines}


def _leaves(out: Path) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(load_params(out / "checkpoint" / "params"))]


@pytest.fixture(scope="module")
def unstopped(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    out = tmp_path_factory.mktemp("unstopped")
    done = _train(out)
    assert done.returncode == 0, done.stderr
    return out, _logged(done.stdout)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("signum", "at", "save_every"),
    [
        (signal.SIGTERM, "main step 5/", None),  # the run saves after the step under way, then exits
        (signal.SIGKILL, "main step 12/", "5"),  # nothing runs: the state of step 5, 10 (or 15) is what is left
        (signal.SIGKILL, "finetune step 8/", "3"),  # the first phase done: the resumed run skips it
    ],
    ids=["sigterm-main", "sigkill-main", "sigkill-finetune"],
)
def test_a_stopped_run_resumes_to_the_unstopped_runs_params(tmp_path, unstopped, signum, at, save_every):
    reference, reference_log = unstopped
    extra = () if save_every is None else ("--save-every", save_every)
    code, out, err = _stopped(tmp_path, at, signum, *extra)
    assert code == (1 if signum == signal.SIGTERM else -signal.SIGKILL), err
    if signum == signal.SIGTERM:
        (line,) = [x for x in err.splitlines() if "stopped by SIGTERM" in x]
        assert "--resume continues" in line
    saves = [x for x in out.splitlines() if "state saved to" in x]
    assert saves and all(int(x.split()[2].split("/")[0]) % int(save_every or 1) == 0 for x in saves)
    assert train_state.path(tmp_path).exists() and not (tmp_path / "checkpoint" / "params").exists()

    resumed = _train(tmp_path, "--resume", *extra)
    assert resumed.returncode == 0, resumed.stderr
    (where,) = [x for x in resumed.stdout.splitlines() if "resumed after step" in x]
    assert where.startswith(at.split()[0])  # the phase the stop was in
    # Every step logged after the resumption equals the unstopped run's, and the checkpoints are the same bits.
    after = _logged(resumed.stdout)
    assert after and all(reference_log[step] == line for step, line in after.items())
    assert all(np.array_equal(a, b) for a, b in zip(_leaves(reference), _leaves(tmp_path), strict=True))
    assert not train_state.path(tmp_path).exists()  # a finished run leaves its checkpoint only


@pytest.mark.slow
def test_a_stopped_meta_world_run_resumes_on_its_own_frames_only(tmp_path):
    """`train_demo --sim metaworld` stopped, resumed on other recorded frames (refused, naming the data), then on its
    own (the unstopped run's checkpoint)."""
    pytest.importorskip("metaworld", reason='the Meta-World demo needs pip install -e ".[metaworld]"')
    # TINY for pi0.5 as `train_demo` spells it, without the reaching task's binding probe (refused on Meta-World).
    pairs = [p for p in zip(TINY[::2], TINY[1::2], strict=True) if p[0] != "--probe-every"]
    tiny = (*(x for flag, value in pairs for x in (f"--args.{flag[2:]}", value)), "--args.model", "pi05")

    def command(data: Path, out: Path, *extra: str) -> list[str]:
        module = [sys.executable, "-m", "openpi_cam.cli.train_demo", "--sim", "metaworld", "--data", str(data)]
        return [*module, *tiny, "--args.out", str(out), *extra]

    def run(data: Path, out: Path, extra: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
        return subprocess.run(command(data, out, *extra), capture_output=True, text=True, timeout=600)

    record = ("--record.episodes", "1", "--record.tasks", "reach-v3")
    unstopped = run(tmp_path / "expert", tmp_path / "unstopped", extra=record)
    assert unstopped.returncode == 0, unstopped.stdout + unstopped.stderr
    other = run(tmp_path / "other", tmp_path / "scratch", extra=(*record, "--record.seed", "7", "--args.steps", "0"))
    assert other.returncode == 0, other.stdout + other.stderr

    stopped = tmp_path / "stopped"
    code, _, _ = _stopped(stopped, "main step 5/", signal.SIGTERM, command=command(tmp_path / "expert", stopped))
    assert code == 1 and train_state.path(stopped).exists()
    refused = run(tmp_path / "other", stopped, extra=("--args.resume",))
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    (line,) = [x for x in refused.stdout.splitlines() if "--args.resume" in x]
    assert "was saved by another run (data: " in line
    resumed = run(tmp_path / "expert", stopped, extra=("--args.resume",))
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    leaves = zip(_leaves(tmp_path / "unstopped"), _leaves(stopped), strict=True)
    assert all(np.array_equal(a, b) for a, b in leaves)


def _main(out: Path, *extra: str) -> int:
    return train.main(["--out", str(out), *TINY, *extra])


def test_resume_without_a_state_is_refused_before_training(tmp_path, capsys):
    assert _main(tmp_path, "--resume") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("openpi_cam.demo.train: --resume: ") and str(train_state.path(tmp_path)) in line
    assert not (tmp_path / "fast_tokenizer").exists()  # refused before anything was built


def _saved(step: int = 3) -> train_state.Saved:
    return train_state.Saved("main", step, np.random.default_rng(0).bit_generator.state, [1.0] * step, [])


def _args(out: Path, *extra: str) -> train.TrainArgs:
    return tyro.cli(train.TrainArgs, args=["--out", str(out), *TINY, *extra])


def test_another_runs_state_is_refused_naming_what_differs(tmp_path, capsys):
    train_state.save(tmp_path, train.run_identity(_args(tmp_path, "--lr", "0.02"), None), _saved())
    assert _main(tmp_path, "--resume") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "was saved by another run (lr: 0.02 there, 0.002 here)" in line, line
    assert str(train_state.path(tmp_path)) in line


def test_the_free_flags_do_not_tell_runs_apart(tmp_path):
    """Moving the folder, or changing how often to log, save or evaluate, still resumes; the batch size does not."""
    args = train.TrainArgs(out=tmp_path, log_every=4)
    moved = train.TrainArgs(out=tmp_path / "moved", log_every=1, save_every=7, eval_episodes=0, resume=True)
    assert train_state.difference(train.run_identity(args, None), train.run_identity(moved, None)) is None
    bigger = train.run_identity(train.TrainArgs(batch_size=64), None)
    assert train_state.difference(train.run_identity(args, None), bigger) == "batch_size: 32 there, 64 here"
    # A state saved before a flag existed (here: batch_size) resumes while the flag keeps its default, and only then.
    older = {k: v for k, v in train.run_identity(args, None).items() if k != "batch_size"}
    defaults = train.run_identity(train.TrainArgs(), None)
    assert train_state.difference(older, train.run_identity(args, None), defaults) is None
    assert train_state.difference(older, bigger, defaults) == "batch_size: None there, 64 here"


@pytest.mark.parametrize("damage", ["truncated", "not-npz"])
def test_a_corrupt_state_is_named_in_one_line(tmp_path, capsys, damage):
    run = train.run_identity(_args(tmp_path), None)
    where = train_state.save(tmp_path, run, _saved())
    data = where.read_bytes()
    where.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"not a state at all")
    with pytest.raises(train_state.StateError, match="unreadable training state") as raised:
        train_state.read(tmp_path, run)
    assert str(where) in str(raised.value) and "\n" not in str(raised.value)


def test_restore_refuses_arrays_of_another_shape(tmp_path):
    params = {"w": np.zeros((2, 3), np.float32)}
    state = train_state.Saved("main", 1, {}, [0.5], [np.zeros((3, 2), np.float32)], tmp_path / train_state.FILE)
    with pytest.raises(train_state.StateError, match=r"array 0 is float32\[3, 2\], this model's float32\[2, 3\]"):
        state.restore(params, ())
    params_back, _ = train_state.Saved("main", 1, {}, [], [np.ones((2, 3), np.float32)]).restore(params, ())
    assert np.array_equal(params_back["w"], np.ones((2, 3)))


def test_train_demo_refuses_to_record_for_a_resumed_run(tmp_path, capsys):
    """An empty --data folder would be recorded into: a resumed run trains on the frames it started on."""
    args = train.TrainArgs(model="pi05", out=tmp_path / "model", resume=True)
    assert train_demo.main(args, sim="metaworld", data=(tmp_path / "empty",)) == 2
    (line,) = capsys.readouterr().out.strip().splitlines()
    assert line.startswith("train_demo: --args.resume: no LeRobot dataset in ") and "empty" in line
    assert not (tmp_path / "empty").exists()
