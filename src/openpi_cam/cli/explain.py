"""`openpi-cam explain SOURCE ...`: `explain-dataset` for a LeRobot dataset, `explain-run` for anything else (a CAM run
with raw frames, PolicyRecorder records). The arguments are parsed by the chosen command, so each flag is one that
command honours."""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

from openpi_cam.lerobot.dataset import is_lerobot_dataset

USAGE = """usage: openpi-cam explain SOURCE [ARGS...]

SOURCE is a LeRobot dataset: `openpi-cam explain-dataset SOURCE [ARGS...]` (a maps dataset).
SOURCE is a CAM run or PolicyRecorder folder: `openpi-cam explain-run SOURCE [ARGS...]` (a CAM run).
`openpi-cam explain-dataset --help` and `openpi-cam explain-run --help` list each command's flags."""


def route(argv: Sequence[str]) -> str | None:
    """The command that takes these arguments: `explain-dataset` when one of them is a LeRobot dataset folder,
    `explain-run` when one names another existing folder, None when there is none (the usage is printed)."""
    paths = [pathlib.Path(a) for a in argv if not a.startswith("-")]
    if any(is_lerobot_dataset(p) for p in paths):
        return "explain-dataset"
    return "explain-run" if any(p.is_dir() for p in paths) else None
