"""`openpi-cam golden DIR`: the user-facing parity check against upstream's reference data."""

from __future__ import annotations

import pathlib

import tyro

from openpi_cam.golden import check_folder
from openpi_cam.lerobot.golden import is_lerobot_golden, run_lerobot_golden
from openpi_cam.policies.golden_policy import is_policy_folder, run_policy_golden


def main(folder: tyro.conf.Positional[pathlib.Path]) -> int:
    """Check against an upstream golden folder: one line per compared array (max |ours - ref| against a bound
    relative to max |ref|), exit status 1 on any mismatch or unreadable input.

    Args:
        folder: a model-level golden folder (config.json, checkpoint/params, case_*.npz: `tiny_pi0_fast`, `tiny_pi0`,
            `tiny_pi05`), a policy-level one (case.json: `tiny_policy_pi05_droid`, `tiny_policy_pi0_libero`), a
            LeRobot policy folder with LeRobot's reference arrays (cases.npz: `lerobot_pi05_tiny`,
            `lerobot_pi0_tiny`), or `param_trees/` (full-size parameter trees).
    """
    if is_lerobot_golden(folder):
        return check_folder(folder, run_lerobot_golden)
    return check_folder(folder, run_policy_golden if is_policy_folder(folder) else None)
