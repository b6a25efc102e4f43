"""Argument forms shared by several subcommands."""

from __future__ import annotations


def parse_action_index(text: str) -> tuple[int, int]:
    """`--cam-action-index`: "I" (pi0-FAST: the I-th action token; pi0 / pi0.5: horizon step I, dimension 0) or "H,D"
    (pi0 / pi0.5: dimension D at horizon step H) -> (index, dimension)."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) not in (1, 2) or not all(p.isdigit() for p in parts):
        raise ValueError(f"action index must be 'I' or 'H,D' with non-negative integers, got {text!r}")
    return int(parts[0]), int(parts[1]) if len(parts) == 2 else 0
