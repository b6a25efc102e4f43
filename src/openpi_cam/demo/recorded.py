"""What the demo records beside a robot's own features, by name: each recorded frame's perturbation (its index into
the run's perturbations) and the file naming every episode's perturbation, seed and outcome, written beside the run's
steps and beside a dataset `openpi-cam demo --record` made. Plain names and JSON, no JAX: `stats` and `render` read
them to set a maps dataset's failed and successful episodes side by side per perturbation."""

from __future__ import annotations

import json
from pathlib import Path

PERTURBATION_FEATURE = "perturbation"  # a recorded frame's index into the run's perturbations
EPISODES_FILE = "demo_episodes.json"  # the demo's episode outcomes


def recorded_episodes_file(dataset: str | Path) -> Path:
    """Where `demo --record` names its episodes, beside the recorded LeRobot dataset's own metadata."""
    return Path(dataset) / "meta" / EPISODES_FILE


def perturbation_names(dataset: str | Path) -> list[str]:
    """The perturbations a recorded dataset's episodes ran under, by index (its `recorded_episodes_file`); none where
    the dataset has no such file."""
    try:
        listed = json.loads(recorded_episodes_file(dataset).read_text())
        return [str(name) for name in listed["perturbations"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []
