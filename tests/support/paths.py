"""Where the repository and the reference data beside it are (`../shared`, read-only, never copied here)."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_DIR = REPO_ROOT.parent / "shared"
GOLDEN_DIR = SHARED_DIR / "golden"
LEROBOT_DIR = SHARED_DIR / "lerobot"  # datasets written by LeRobot itself, with its own frames beside them
