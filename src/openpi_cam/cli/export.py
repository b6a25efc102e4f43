"""`openpi-cam export --to lerobot CHECKPOINT_DIR --config NAME --out DIR`: an OpenPI pi0 / pi0.5 checkpoint as a
LeRobot policy folder, which LeRobot's `from_pretrained` and processor loaders read and `serve`, `explain` and
`golden` take like any LeRobot folder."""

from __future__ import annotations

import pathlib
import sys
from typing import Literal

import tyro

from openpi_cam.policies import demo_reach
from openpi_cam.policies.lerobot_export import export_lerobot

# The bundled demo's configs register themselves on import, so `--config demo_reach_pi05` names them here too.
DEMO_CONFIGS = demo_reach.DEMO_CONFIGS


def main(
    checkpoint_dir: tyro.conf.Positional[pathlib.Path],
    config: str,
    out: pathlib.Path,
    to: Literal["lerobot"] = "lerobot",
    paligemma_tokenizer: pathlib.Path | None = None,
) -> int:
    """Write an OpenPI orbax checkpoint in another framework's layout.

    Args:
        checkpoint_dir: an OpenPI orbax checkpoint (params/ and assets/<asset id>/norm_stats.json).
        config: the named policy config that serves it (its robot must map onto LeRobot features).
        out: the folder to write (new or empty).
        to: the layout: `lerobot` (a LeRobot 0.6 pi0 / pi0.5 policy folder, statistics from the checkpoint's own
            assets/).
        paligemma_tokenizer: a SentencePiece model to ship in the folder's tokenizer/ (default: the folder names
            PaliGemma's Hub tokenizer, as LeRobot's own folders do).
    """
    try:
        folder = export_lerobot(checkpoint_dir, config, out, paligemma_tokenizer=paligemma_tokenizer)
    except (ValueError, FileNotFoundError, FileExistsError, KeyError) as e:
        print(f"openpi-cam export: {e}", file=sys.stderr)
        return 2
    print(f"wrote the LeRobot {to} policy folder {folder}")
    return 0
