"""`openpi-cam head WORD ...`: the occlusion heads of the `occlusion-head` kind; `head fit` fits one."""

from __future__ import annotations

from collections.abc import Sequence

USAGE = """usage: openpi-cam head fit MAPS... --out FILE [ARGS...]

fit: an occlusion head fitted to a policy's own occlusion maps (maps datasets explained with the head's input kinds
and `occlusion`), saved as one file with its held-out figures. `openpi-cam head fit --help` lists its flags."""


def route(argv: Sequence[str]) -> str | None:
    """`head fit` for `fit ...`; None (the usage is printed) for anything else."""
    return "head fit" if argv[:1] == ["fit"] else None
