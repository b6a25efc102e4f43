"""Which kind of checkpoint folder a path is: OpenPI's orbax checkpoint, a LeRobot pi0 / pi0.5 policy folder, or
OpenPI's PyTorch export. Every command that loads a model asks here, so a folder is recognised the same way
everywhere and a folder that is none of them is refused in one line naming what is missing. A PyTorch-layout folder
(LeRobot's or OpenPI's export) of sizes LeRobot's configs lack also carries a sizes record, read and written here."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from openpi_cam.errors import load_json
from openpi_cam.model.config import Pi0Config
from openpi_cam.model.safetensors_weights import LEROBOT_HEADS, HeadCounts

CheckpointFormat = Literal["orbax", "lerobot", "openpi_pytorch"]

PARAMS_DIR = "params"  # orbax: <checkpoint>/params and <checkpoint>/assets/<asset id>/norm_stats.json
ASSETS_DIR = "assets"
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
PREPROCESSOR_FILE = "policy_preprocessor.json"
POSTPROCESSOR_FILE = "policy_postprocessor.json"
LEROBOT_FILES = (CONFIG_FILE, WEIGHTS_FILE, PREPROCESSOR_FILE, POSTPROCESSOR_FILE)
# The shared LeRobot goldens record there, under "tiny", the sizes they substituted into LeRobot at run time; the only
# ones the weights cannot show are the attention head counts (`HeadCounts`). `export --to lerobot` writes the same.
SIZES_RECORD = "golden_meta.json"
LEROBOT_SIZES = Pi0Config()  # gemma_2b, gemma_300m and PaliGemma's SigLIP: the sizes LeRobot's configs know


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


def read_head_counts(folder: Path) -> HeadCounts:
    """The attention head counts of a folder's weights: its sizes record where it has one (tiny models), else
    LeRobot's defaults."""
    path = folder / SIZES_RECORD
    if not path.is_file():
        return LEROBOT_HEADS
    record = load_json(path)
    try:
        tiny = record["tiny"]
        gemma = {int(tiny[stack]["num_heads"]) for stack in ("vlm", "expert")}
        siglip = int(tiny["siglip"]["num_attention_heads"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: no readable 'tiny' sizes ({type(e).__name__}: {e})") from e
    if len(gemma) != 1:
        raise ValueError(f"{path}: the language model and the expert attend jointly, but their head counts differ")
    return HeadCounts(gemma=gemma.pop(), siglip=siglip)


_GEMMA_SIZES = ("width", "depth", "mlp_dim", "num_heads", "num_kv_heads", "head_dim")
_SIGLIP_SIZES = {  # Hugging Face's SiglipVisionConfig names of ours
    "hidden_size": "width",
    "num_hidden_layers": "depth",
    "num_attention_heads": "num_heads",
    "intermediate_size": "mlp_dim",
    "patch_size": "patch_size",
    "image_size": "image_size",
    "projection_dim": "out_dim",
}


def sizes_record(cfg: Pi0Config) -> dict[str, Any]:
    """The sizes of a pi0 / pi0.5 architecture in the shared LeRobot goldens' record layout."""
    return {
        "tiny": {
            "vlm": {name: getattr(cfg.gemma, name) for name in _GEMMA_SIZES},
            "expert": {name: getattr(cfg.expert, name) for name in _GEMMA_SIZES},
            "siglip": {hf: getattr(cfg.siglip, ours) for hf, ours in _SIGLIP_SIZES.items()},
        },
        "vocab_size": cfg.gemma.vocab_size,
    }


def write_sizes_record(folder: Path, cfg: Pi0Config) -> Path | None:
    """Writes the sizes record of a model whose sizes LeRobot's variant table lacks (what `read_head_counts` reads,
    and what LeRobot needs substituted at run time to build the model); None, and nothing written, for LeRobot's own
    sizes."""
    record = sizes_record(cfg)
    if record == sizes_record(LEROBOT_SIZES):
        return None
    path = folder / SIZES_RECORD
    path.write_text(json.dumps(record, indent=1))
    return path
