"""`openpi-cam serve`: load a pi0-FAST checkpoint and serve it like upstream's `scripts/serve_policy.py`.

With `--cam-every-k K > 0` every K-th request per connection also gets its maps written to `--cam-dir` (off the
request path; see docs/FORMAT.md).
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import Literal

from openpi_cam.cam.side_channel import CAMOptions, CAMPolicy, wrap_policy_with_cam
from openpi_cam.cam.spot_check import DEFAULT_PATCHES
from openpi_cam.cli.options import map_options, parse_action_index
from openpi_cam.model.config import MAX_DECODING_STEPS
from openpi_cam.policies import demo_reach
from openpi_cam.policies.policy import Policy, create_policy
from openpi_cam.serving.server import PolicyServer
from openpi_cam.vocabulary import DEFAULT_KINDS, MapKind, SaveFrames, Target

logger = logging.getLogger(__name__)


def main(
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
    max_connections: int = 64,
    max_buffered_mb: float = 256.0,
    debug: bool = False,
    stop_at_action_end: bool = False,
    cam_every_k: int = 0,
    cam_dir: Path = Path("cam_runs"),
    cam_save_frames: SaveFrames = "model",
    cam_target: Target = "action-token",
    cam_action_index: str = "0",
    cam_maps: tuple[MapKind, ...] = DEFAULT_KINDS,
    cam_baseline: Literal["mean", "blur"] = "mean",
    cam_occlusion_region: int = 1,
    cam_occlusion_masks: int = 0,
    cam_ig_space: Literal["tokens", "pixels"] = "tokens",
    cam_check_patches: int = DEFAULT_PATCHES,
    cam_queue_size: int = 8,
    cam_per_connection: int | None = None,
    cam_settle_ms: float = 10.0,
    cam_device: int | None = None,
    cam_max_steps: int | None = None,
    cam_max_mb: float | None = None,
    cam_drain_timeout: float = 5.0,
    cam_max_extra_value_kb: float = 16.0,
    cam_max_extra_kb: float = 64.0,
    warm_up: bool = True,
    batch_window_ms: float | None = None,
    max_batch: int = 8,
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
        max_connections: open connections at most; further ones are closed at once (code 1013, try again later).
        max_buffered_mb: request bytes being handled at once over all connections (decoding, waiting for the model,
            computing); a request that would pass it closes its connection (code 1013). At least --max-message-mb.
        debug: send tracebacks of unexpected errors to clients.
        stop_at_action_end: stop decoding at the end of the action string instead of running to EOS.
        cam_every_k: record Grad-CAM for every k-th request (0 = off).
        cam_dir: where Grad-CAM runs are written.
        cam_save_frames: which camera frames to store next to the maps.
        cam_target: which score the maps explain (a generation without action tokens is explained with
            `generated-tokens` whatever this says).
        cam_action_index: pi0-FAST: which action token (`action-token`); pi0 / pi0.5: `H,D`, dimension D at horizon
            step H (`action`).
        cam_maps: which kinds of map each explained step carries (README, "Which map to trust"): `gradcam` and
            `gradnorm` cost one backward pass together; `ig` (about 8x an inference on the demo model) and
            `occlusion` (one re-run per patch and camera) are opt-in live.
        cam_baseline: the frame `ig` starts from and `occlusion` paints with: the frame's mean colour or a blurred copy.
        cam_occlusion_region: side of an `occlusion` region in patches (1: every patch alone).
        cam_occlusion_masks: 0: every region once; M > 0: M random region masks per camera (ISS), for large grids.
        cam_ig_space: where the `ig` path runs: SigLIP tokens or the frames' pixels (README, "Map kinds").
        cam_check_patches: each explained step's spot check paints each map's top patch and this many random
            patches (a few re-runs per camera, in one call) and stores the score drops with the maps, so every map
            carries evidence of its own (README, "Looking at the maps"); 0: no check.
        cam_queue_size: pending Grad-CAM jobs in all; at the cap the busiest connection's oldest one is dropped.
        cam_per_connection: pending jobs per connection at most (a newer one supersedes the oldest); None: no limit.
        cam_settle_ms: the worker starts an explanation only this long after the last inference ended (the reply is
            still being sent then).
        cam_device: explain on this device (an index into `jax.devices()`, e.g. 1 for a second GPU), which holds a
            copy of the parameters; explanations then run while the served model infers. Default: share the served
            model's device, explaining only in pauses (`--cam-settle-ms`).
        cam_max_steps: stop recording after this many steps (None = no limit).
        cam_max_mb: stop recording once the run directory holds this many MB (None = no limit).
        cam_drain_timeout: on SIGTERM, seconds the side channel keeps explaining queued jobs (counted from the
            signal, while connections close) before the run's manifest is closed: SIGTERM exits within this, the
            in-flight inference and 2 s for unresponsive peers, inside a container's 10 s stop grace period.
        cam_max_extra_value_kb: largest `cam_extra/` value a step stores (an array's bytes, other values' JSON);
            larger ones are dropped and named in the step's `extra_dropped`.
        cam_max_extra_kb: all `cam_extra/` values a step stores together.
        warm_up: compile inference (and the side channel's explanation) on the robot's example observation before
            listening, so `/healthz` answers only once the first request will not wait for compilation.
        batch_window_ms: serve a fleet in batches: requests from all connections arriving within this many ms of the
            first share one model call, each row answered as if served alone (README, "Serving a fleet"). None: one
            request per model call, as upstream.
        max_batch: requests per batched call at most, a power of two (calls run at power-of-two batch sizes: one
            compiled program each, all compiled at warm-up).
    """
    # force: importing orbax has already put a handler on the root logger; ours gives every line a time stamp. INFO
    # for this package only (readiness, connections, shutdown); libraries stay at WARNING.
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True)
    logging.getLogger("openpi_cam").setLevel(logging.INFO)
    if max_message_mb <= 0 or max_buffered_mb < max_message_mb:
        print(
            "openpi-cam serve: need 0 < --max-message-mb <= --max-buffered-mb, "
            f"got {max_message_mb} and {max_buffered_mb}",
            file=sys.stderr,
        )
        return 2
    if cam_drain_timeout < 0:
        print(f"openpi-cam serve: --cam-drain-timeout must be >= 0, got {cam_drain_timeout}", file=sys.stderr)
        return 2
    if batch_window_ms is not None and (batch_window_ms < 0 or max_batch < 1 or max_batch & (max_batch - 1)):
        print(
            f"openpi-cam serve: need --batch-window-ms >= 0 and --max-batch a power of two, got {batch_window_ms} "
            f"and {max_batch}",
            file=sys.stderr,
        )
        return 2
    if cam_every_k < 0:
        print(f"openpi-cam serve: --cam-every-k must be >= 0, got {cam_every_k}", file=sys.stderr)
        return 2
    try:
        action_index, action_dim_index = parse_action_index(cam_action_index)
    except ValueError as e:
        print(f"openpi-cam serve: --cam-action-index: {e}", file=sys.stderr)
        return 2

    max_decoding_steps = MAX_DECODING_STEPS
    if checkpoint_dir is None:  # the bundled default: a tiny pi0-FAST trained on the demo task
        max_decoding_steps = demo_reach.MAX_DECODING_STEPS
        checkpoint_dir = demo_reach.CHECKPOINT
        config = config or demo_reach.DEMO_CONFIG.name
        paligemma_tokenizer = paligemma_tokenizer or demo_reach.PALIGEMMA_TOKENIZER
        fast_tokenizer = fast_tokenizer or demo_reach.FAST_TOKENIZER
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
    except (FileNotFoundError, ValueError) as e:
        # Missing files or a checkpoint that is not the config's family are operator problems, not bugs: the message
        # says what is wrong and where.
        print(f"openpi-cam serve: {e}", file=sys.stderr)
        return 1
    metadata = dict(policy.metadata)

    served: Policy | CAMPolicy = policy
    if cam_every_k > 0:
        options = CAMOptions(
            every_k=cam_every_k,
            cam_dir=cam_dir,
            save_frames=cam_save_frames,
            target=cam_target,
            action_index=action_index,
            action_dim_index=action_dim_index,
            maps=cam_maps,
            map_options=map_options(cam_baseline, cam_occlusion_region, cam_occlusion_masks, cam_ig_space),
            check_patches=cam_check_patches,
            queue_size=cam_queue_size,
            per_connection=cam_per_connection,
            settle_ms=cam_settle_ms,
            device=cam_device,
            max_steps=cam_max_steps,
            max_bytes=None if cam_max_mb is None else int(cam_max_mb * 1024 * 1024),
            max_extra_value_bytes=int(cam_max_extra_value_kb * 1024),
            max_extra_bytes=int(cam_max_extra_kb * 1024),
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
        try:
            served = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=str(checkpoint_dir))
        except ValueError as e:  # e.g. --cam-device names a device this machine does not have
            print(f"openpi-cam serve: {e}", file=sys.stderr)
            return 2
        logger.info("Grad-CAM on: every %d requests, target %s, writing to %s", cam_every_k, cam_target, cam_dir)

    if batch_window_ms is not None and policy.model.family != "pi0_fast":
        logger.warning(
            "batched %s serving: actions match serving each request alone only to floating-point rounding (batched "
            "matrix products round differently; README, 'Serving a fleet')",
            policy.model.family,
        )
    if warm_up:
        start = time.monotonic()
        sizes = (1,) if batch_window_ms is None else tuple(1 << i for i in range(max_batch.bit_length()))
        warmed = served.warm_up(sizes) if isinstance(served, CAMPolicy) else _warm_up_inference(policy, sizes)
        batches = "" if batch_window_ms is None else f" (batch sizes {list(sizes)})"
        logger.info("warmed up %s in %.1f s%s", warmed, time.monotonic() - start, batches)
    server = PolicyServer(
        served,
        host=host,
        port=port,
        metadata=metadata,
        api_key=api_key,
        max_message_bytes=int(max_message_mb * 1024 * 1024),
        max_connections=max_connections,
        max_buffered_bytes=int(max_buffered_mb * 1024 * 1024),
        debug=debug,
        close_timeout=cam_drain_timeout,
        batch_window_ms=batch_window_ms,
        max_batch=max_batch,
    )
    server.serve_forever()
    if isinstance(served, CAMPolicy) and served.computing:
        # The manifest is written; an explanation still runs in XLA on the worker thread, and interpreter shutdown
        # under a running XLA computation aborts the process. Exit without the interpreter's teardown instead.
        logger.warning("exiting with an explanation still computing past --cam-drain-timeout (its step is not written)")
        logging.shutdown()
        os._exit(0)
    return 0


def _warm_up_inference(policy: Policy, batch_sizes: tuple[int, ...]) -> str:
    return "inference" if policy.warm_up(batch_sizes) is not None else "nothing (the robot transform offers no example)"
