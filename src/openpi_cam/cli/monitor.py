"""`openpi-cam monitor WORD ...`: the failure monitor's commands; `monitor fit` fits one."""

from __future__ import annotations

from collections.abc import Sequence

USAGE = """usage: openpi-cam monitor fit MAPS... --out FILE [ARGS...]

fit: a failure monitor fitted on labelled rollouts' maps datasets (`explain-dataset` of `next.success` recordings),
saved as one file that `serve --monitor` and `explain-dataset --monitor` score with. `openpi-cam monitor fit --help`
lists its flags."""


def route(argv: Sequence[str]) -> str | None:
    """`monitor fit` for `fit ...`; None (the usage is printed) for anything else."""
    return "monitor fit" if argv[:1] == ["fit"] else None
