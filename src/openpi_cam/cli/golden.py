"""`openpi-cam golden DIR`: the user-facing parity check against upstream's reference data."""

from __future__ import annotations

import pathlib

import tyro

from openpi_cam.golden import check_folder


def main(folder: tyro.conf.Positional[pathlib.Path]) -> int:
    """Check the model against an upstream golden folder (config.json, checkpoint/params, case_*.npz): one line per
    compared array, exit status 1 on any mismatch or unreadable input.

    Args:
        folder: a golden folder laid out like `shared/golden/tiny_pi0_fast`.
    """
    return check_folder(folder)
