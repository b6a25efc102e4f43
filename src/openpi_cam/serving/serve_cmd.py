"""`openpi-cam serve`: load a pi0-FAST checkpoint and serve it like upstream's `scripts/serve_policy.py`.

With `--cam-every-k K > 0` every K-th request per connection also gets a Grad-CAM record written to `--cam-dir`
(off the request path; see docs/FORMAT.md).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Literal

from openpi_cam.serving.server import PolicyServer, RunningServer, start_server_in_thread

__all__ = ["RunningServer", "serve", "start_server_in_thread"]

logger = logging.getLogger(__name__)


def serve(
    checkpoint_dir: Path | None = None,
    config: str | None = None,
    paligemma_tokenizer: Path | None = None,
    fast_tokenizer: Path | None = None,
    port: int = 8000,
    host: str = "0.0.0.0",
    default_prompt: str | None = None,
    api_key: str | None = None,
    dtype: Literal["bfloat16", "float32"] | None = None,
    max_message_mb: float = 64.0,
    debug: bool = False,
    stop_at_action_end: bool = False,
    cam_every_k: int = 0,
    cam_dir: Path = Path("cam_runs"),
    cam_save_frames: Literal["none", "raw", "model", "both"] = "model",
    cam_target: Literal["action-token", "all-action-tokens", "chunk"] = "action-token",
    cam_action_index: int = 0,
    cam_queue_size: int = 8,
    cam_max_steps: int | None = None,
    cam_max_mb: float | None = None,
) -> int:
    """Serve a pi0-FAST checkpoint over websockets (openpi-client compatible), optionally logging Grad-CAM.

    Args:
        checkpoint_dir: checkpoint folder with `params/` and `assets/<asset_id>/norm_stats.json`; default: the
            bundled demo model (config `demo_reach`, its own tokenizers, float32).
        config: named policy config (e.g. pi0_fast_droid, pi0_fast_libero); default pi0_fast_droid for a checkpoint.
        paligemma_tokenizer: PaliGemma SentencePiece model; default: the policy factory's standard location.
        fast_tokenizer: FAST action tokenizer folder; default: the policy factory's standard location.
        port: TCP port.
        host: interface to listen on (0.0.0.0 = all, like upstream).
        default_prompt: prompt used when a request has none.
        api_key: if set, clients must send `Authorization: Api-Key <key>` (openpi-client's `api_key=`).
        dtype: parameter and compute dtype; default bfloat16 for a checkpoint, as upstream serves.
        max_message_mb: largest accepted request frame; larger ones close the connection (code 1009).
        debug: send tracebacks of unexpected errors to clients.
        stop_at_action_end: stop decoding at the end of the action string instead of running to EOS.
        cam_every_k: record Grad-CAM for every k-th request (0 = off).
        cam_dir: where Grad-CAM runs are written.
        cam_save_frames: which camera frames to store next to the maps.
        cam_target: which score Grad-CAM explains.
        cam_action_index: which action token for `action-token`.
        cam_queue_size: pending Grad-CAM jobs before new ones are dropped (inference never waits).
        cam_max_steps: stop recording after this many steps (None = no limit).
        cam_max_mb: stop recording once the run directory holds this many MB (None = no limit).
    """
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if max_message_mb <= 0:
        print(f"openpi-cam serve: --max-message-mb must be positive, got {max_message_mb}", file=sys.stderr)
        return 2
    if cam_every_k < 0:
        print(f"openpi-cam serve: --cam-every-k must be >= 0, got {cam_every_k}", file=sys.stderr)
        return 2
    from openpi_cam.policies.policy import create_policy

    max_decoding_steps = 256  # upstream's default
    if checkpoint_dir is None:  # the bundled default: a tiny pi0-FAST trained on the demo task
        from openpi_cam.demo import bundled

        max_decoding_steps = bundled.MAX_DECODING_STEPS
        checkpoint_dir = bundled.CHECKPOINT
        config = config or bundled.DEMO_CONFIG.name
        paligemma_tokenizer = paligemma_tokenizer or bundled.PALIGEMMA_TOKENIZER
        fast_tokenizer = fast_tokenizer or bundled.FAST_TOKENIZER
        dtype = dtype or "float32"
    config = config or "pi0_fast_droid"
    dtype = dtype or "bfloat16"
    try:
        policy = create_policy(
            config,
            checkpoint_dir,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            default_prompt=default_prompt,
            stop_at_action_end=stop_at_action_end,
            max_decoding_steps=max_decoding_steps,
        )
    except FileNotFoundError as e:
        # Missing files are an operator problem, not a bug: the message says what is missing and where.
        print(f"openpi-cam serve: {e}", file=sys.stderr)
        return 1
    metadata = dict(getattr(policy, "metadata", None) or {})

    if cam_every_k > 0:
        from openpi_cam.cam.wrapper import CAMOptions, wrap_policy_with_cam

        options = CAMOptions(
            every_k=cam_every_k,
            cam_dir=cam_dir,
            save_frames=cam_save_frames,
            target=cam_target,
            action_index=cam_action_index,
            queue_size=cam_queue_size,
            max_steps=cam_max_steps,
            max_bytes=None if cam_max_mb is None else int(cam_max_mb * 1024 * 1024),
        )
        run_config = {
            "config": config,
            "checkpoint_dir": str(checkpoint_dir),
            "paligemma_tokenizer": None if paligemma_tokenizer is None else str(paligemma_tokenizer),
            "fast_tokenizer": None if fast_tokenizer is None else str(fast_tokenizer),
            "dtype": dtype,
            "default_prompt": default_prompt,
            "stop_at_action_end": stop_at_action_end,
        }
        policy = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=str(checkpoint_dir))
        logger.info("Grad-CAM on: every %d requests, target %s, writing to %s", cam_every_k, cam_target, cam_dir)

    server = PolicyServer(
        policy,
        host=host,
        port=port,
        metadata=metadata,
        api_key=api_key,
        max_message_bytes=int(max_message_mb * 1024 * 1024),
        debug=debug,
    )
    server.serve_forever()
    return 0
