"""`openpi-cam export --to lerobot [--checkpoint-dir DIR] --config NAME --out DIR`: an OpenPI pi0 / pi0.5 checkpoint as
a LeRobot policy folder, which LeRobot's `from_pretrained` and processor loaders read and `serve`, `explain-dataset`
and `golden` take like any LeRobot folder."""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from typing import Literal

import tyro

from openpi_cam.checkpoints.model_spec import LeRobotFolder, ModelSpec
from openpi_cam.cli.options import BUNDLED_MODEL
from openpi_cam.lerobot.export import export_lerobot
from openpi_cam.policies.demo_reach import DEMO_PI05_CONFIG

# The model flags a LeRobot pi0 / pi0.5 folder has no place for: `ModelSpec` field -> why.
NOT_IN_A_LEROBOT_FOLDER = {
    "fast_tokenizer": "a LeRobot pi0 / pi0.5 folder has no FAST tokenizer (pi0-FAST has no LeRobot layout here)",
    "default_prompt": "a LeRobot pi0 / pi0.5 folder holds no default prompt: give it to the command that serves it",
}


def main(
    out: pathlib.Path,
    model: tyro.conf.OmitArgPrefixes[ModelSpec] = BUNDLED_MODEL,
    to: Literal["lerobot"] = "lerobot",
) -> int:
    """Write an OpenPI orbax checkpoint in another framework's layout.

    Args:
        out: the folder to write (new or empty).
        model: the checkpoint and the named config that serves it (its robot must map onto LeRobot features); the
            PaliGemma tokenizer given, or a demo model's own, is shipped in the folder's tokenizer/ (else the folder
            names PaliGemma's Hub tokenizer, as LeRobot's own folders do). No --checkpoint-dir: the bundled model of
            the config; neither flag: the bundled pi0.5 (`--config demo_reach_pi05`; the bundled default,
            pi0-FAST, has no LeRobot layout here). `--dtype`: the folder's (LeRobot's `dtype` field, the weights
            stored in it; default float32, LeRobot's default). A LeRobot pi0 / pi0.5 folder has no FAST tokenizer and
            no default prompt: `--fast-tokenizer` and `--default-prompt` are refused (give the prompt to the command
            that serves the folder).
        to: the layout: `lerobot` (a LeRobot 0.6 pi0 / pi0.5 policy folder, statistics from the checkpoint's own
            assets/).
    """
    for field, why in NOT_IN_A_LEROBOT_FOLDER.items():
        if getattr(model, field) is not None:
            print(f"openpi-cam export: --{field.replace('_', '-')}: {why}", file=sys.stderr)
            return 2
    if model.checkpoint_dir is None and model.config is None:
        model = dataclasses.replace(model, config=DEMO_PI05_CONFIG.name)
    try:
        source = model.source
        if isinstance(source, LeRobotFolder):
            raise ValueError(f"{source.checkpoint} is a LeRobot folder already")
        # The flag's dtype, else LeRobot's default: not the resolved one, which is an OpenPI checkpoint's serving dtype.
        dtype = model.dtype or "float32"
        folder = export_lerobot(
            source.checkpoint, source.config, out, paligemma_tokenizer=model.tokenizers()[0], dtype=dtype
        )
    except (ValueError, FileNotFoundError, FileExistsError, KeyError) as e:
        print(f"openpi-cam export: {e}", file=sys.stderr)
        return 2
    print(f"wrote the LeRobot {to} policy folder {folder} ({dtype})")
    return 0
