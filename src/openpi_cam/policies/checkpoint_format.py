"""Which kind of checkpoint folder a path is: OpenPI's orbax checkpoint, a LeRobot pi0 / pi0.5 policy folder, or
OpenPI's PyTorch export. Every command that loads a model asks here, so a folder is recognised the same way
everywhere and a folder that is none of them is refused in one line naming what is missing."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from openpi_cam.errors import load_json

CheckpointFormat = Literal["orbax", "lerobot", "openpi_pytorch"]

PARAMS_DIR = "params"  # orbax: <checkpoint>/params and <checkpoint>/assets/<asset id>/norm_stats.json
ASSETS_DIR = "assets"
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
PREPROCESSOR_FILE = "policy_preprocessor.json"
POSTPROCESSOR_FILE = "policy_postprocessor.json"
LEROBOT_FILES = (CONFIG_FILE, WEIGHTS_FILE, PREPROCESSOR_FILE, POSTPROCESSOR_FILE)


def _lerobot_type(config: Path) -> str | None:
    """A LeRobot policy config's `type`; None for another JSON file (OpenPI's export writes a config without one)."""
    kind = load_json(config).get("type")
    return kind if isinstance(kind, str) else None


def checkpoint_format(folder: str | Path) -> CheckpointFormat:
    """ "orbax" (`params/`), "lerobot" (`config.json` with a policy `type`, `model.safetensors` and the two processor
    pipelines) or "openpi_pytorch" (`model.safetensors` and `assets/`, served with a named OpenPI config); the state
    files a LeRobot pipeline names are checked when it is read."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"checkpoint folder not found: {folder}")
    if (folder / PARAMS_DIR).is_dir():
        return "orbax"
    config = folder / CONFIG_FILE
    if config.is_file() and _lerobot_type(config) is not None:
        if missing := [name for name in LEROBOT_FILES if not (folder / name).is_file()]:
            raise FileNotFoundError(f"{folder} is a LeRobot policy folder without {', '.join(missing)}")
        return "lerobot"
    if (folder / WEIGHTS_FILE).is_file():
        if not (folder / ASSETS_DIR).is_dir():
            raise FileNotFoundError(
                f"{folder} holds {WEIGHTS_FILE} but no {ASSETS_DIR}/ (OpenPI's PyTorch export keeps its norm stats "
                f"there) and no LeRobot {CONFIG_FILE}"
            )
        return "openpi_pytorch"
    raise FileNotFoundError(
        f"no checkpoint at {folder}: expected {folder / PARAMS_DIR} (OpenPI orbax), {', '.join(LEROBOT_FILES)} "
        f"(LeRobot policy) or {WEIGHTS_FILE} + {ASSETS_DIR}/ (OpenPI PyTorch export)"
    )
