"""The command line takes no flag it would ignore: `explain` routes SOURCE to the command that takes it, each explain
command refuses the other's flags, `serve` refuses side-channel flags with the side channel off, `render` refuses a
maps dataset's flag for a run, the viewers name a folder they cannot read in one line, and earlier spellings still
parse. All of it is refused before a model loads."""

from __future__ import annotations

import pytest
from paths import LEROBOT_DIR

from openpi_cam import cli
from openpi_cam.cli import explain

DATASET = LEROBOT_DIR / "demo_reach_v30_image"


def _exit_code(args: list[str]) -> int:
    with pytest.raises(SystemExit) as exited:
        cli.main(args)
    return int(exited.value.code or 0)


def test_explain_routes_a_dataset_and_a_run_folder_to_their_commands(tmp_path):
    assert explain.route([str(DATASET), "--keys", "a=b"]) == "explain-dataset"
    assert explain.route(["--out", "x", str(tmp_path)]) == "explain-run"
    assert explain.route(["--help"]) is None


@pytest.mark.parametrize(
    ("command", "flag"),
    [
        ("explain-run", ["--engine", "ray"]),  # a dataset's engine
        ("explain-run", ["--every-k", "2"]),
        ("explain-run", ["--keys", "a=b"]),
        ("explain-dataset", ["--resume", "x"]),  # a run's resume
        ("explain-dataset", ["--save-frames", "raw"]),
        ("explain-dataset", ["--rerun", "x.rrd"]),
    ],
)
def test_each_explain_command_refuses_the_others_flags(command, flag, tmp_path, capsys):
    source = str(DATASET if command == "explain-dataset" else tmp_path)
    assert _exit_code([command, source, *flag]) == 2
    assert flag[0] in capsys.readouterr().err
    assert _exit_code(["explain", source, *flag]) == 2  # the same through `explain`


def test_the_ray_engines_flags_need_the_ray_engine(capsys):
    assert _exit_code(["explain-dataset", str(DATASET), "--workers", "2", "--no-progress"]) == 1
    assert "--workers and --ray-address run the Ray engine: add --engine ray" in capsys.readouterr().err


def test_serve_refuses_side_channel_flags_with_the_side_channel_off(capsys):
    from openpi_cam.cli import serve

    assert serve.main(cam=serve.SideChannelFlags(maps=("ig",), queue_size=3), warm_up=False) == 2
    assert capsys.readouterr().err.strip() == (
        "openpi-cam serve: --cam.maps, --cam.queue-size given but the side channel is off: add --cam.every-k K"
    )


def test_render_refuses_episodes_for_a_run(tmp_path, capsys):
    assert _exit_code(["render", str(tmp_path), "--episodes", "0"]) == 2
    assert "--episodes selects a maps dataset's episodes" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["stats", "render"])
def test_the_viewers_name_a_folder_that_is_neither_a_run_nor_a_maps_dataset(command, tmp_path, capsys):
    assert _exit_code([command, str(tmp_path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line == f"openpi-cam {command}: {tmp_path} is not a CAM run directory (no run.json)"


@pytest.mark.parametrize(
    "args",
    [
        ["explain-run", "NO_SUCH_RUN", "--limit", "3"],
        ["explain-dataset", str(DATASET), "--every", "2", "--episodes", "99", "--no-progress"],
        ["faithfulness", "NO_SUCH_RUN", "--json-out", "x.json"],
        ["serve", "--cam-every-k", "1", "--checkpoint-dir", "NO_SUCH_CHECKPOINT", "--no-warm-up"],
        ["serve", "--cam.drain-timeout", "3", "--checkpoint-dir", "NO_SUCH_CHECKPOINT", "--no-warm-up"],
        ["cam-index", "NO_SUCH_RUN"],
        ["render", "NO_SUCH_RUN", "--map", "ig"],
        ["stats", "NO_SUCH_RUN", "--map", "ig"],
    ],
)
def test_earlier_spellings_still_parse(args, capsys):
    """`--limit`, `--every`, `--json-out`, `--cam-every-k`, `--cam.drain-timeout` (now `serve --drain-timeout`), `--map`
    and `cam-index` are kept for scripts: each parses and the command fails only later, on the missing input (not exit
    2, what a flag tyro refuses gives)."""
    with pytest.raises((SystemExit, FileNotFoundError)) as failed:
        cli.main(args)
    assert not (isinstance(failed.value, SystemExit) and failed.value.code == 2)
    err = capsys.readouterr().err
    assert isinstance(failed.value, FileNotFoundError) or "NO_SUCH" in err or "episodes [99]" in err, err
