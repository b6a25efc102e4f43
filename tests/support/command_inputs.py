"""What the command-line tests feed the commands: a CAM run the side channel wrote for the bundled model, a maps
dataset `explain-dataset` wrote, and copies of reference folders with one file damaged (truncated, garbage bytes,
JSON of the wrong type) whose other files are links to the originals."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from demo_inputs import demo_observation
from paths import LEROBOT_DIR

# The dataset the maps datasets of these tests explain, and the feature its pointing figures use.
DEMO_DATASET = LEROBOT_DIR / "demo_reach_v30_video"
TARGET_BOX = "observation.target_box=target_box"
# The options of the dataset tests' jobs (tests/datasets): the same compiled programs, loaded from JAX's cache.
MAPS_FLAGS = ("--maps", "gradcam", "gradnorm", "--target", "action-token", "--check-patches", "2", "--batch-size", "4")


def served_run(cam_dir: Path, policy, seeds: tuple[int, ...] = (0, 1)) -> Path:
    """A run of the bundled pi0-FAST explaining each of `seeds`' observations with the side channel's defaults,
    frames raw and model-side (replayable by `explain-run`, re-scorable by `faithfulness`), recording the model as
    `serve` records it."""
    from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
    from openpi_cam.checkpoints.model_spec import ModelSpec

    options = CAMOptions(every_k=1, dir=cam_dir, save_frames="both", queue_size=16)
    run_config = {**ModelSpec().resolved().to_json(), "stop_at_action_end": False}
    wrapped = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=str(ModelSpec().checkpoint))
    try:
        for seed in seeds:
            wrapped.infer(demo_observation(seed))
    finally:
        wrapped.close(300)  # every step explained: a loaded machine may compile for minutes
    assert wrapped.run_dir is not None
    return wrapped.run_dir


def explained_dataset(out: Path, *flags: str) -> Path:
    """`openpi-cam explain-dataset` of the demo dataset's first two episodes with the bundled model into `out`."""
    from openpi_cam import cli

    args = ["explain-dataset", str(DEMO_DATASET), "--episodes", "0,1", "--extra", TARGET_BOX, "--out", str(out)]
    try:
        cli.main([*args, *MAPS_FLAGS, "--no-progress", *flags])
    except SystemExit as e:
        assert not e.code, f"explain-dataset exited with {e.code}"
    return out


def _garbage(data: bytes) -> bytes:
    # Deterministic bytes that no format here accepts: no JSON value, zip, parquet or MP4 starts with 0xFF 0xFE 0xFD.
    return bytes((0xFF - i * 7) % 256 for i in range(max(len(data), 64)))


def _middle(data: bytes) -> bytes:
    # The middle third overwritten: a zip's directory (at its end) and first member intact, a later member's not.
    third = len(data) // 3
    return data[:third] + _garbage(data)[third : len(data) - third] + data[len(data) - third :]


CORRUPTIONS: dict[str, Callable[[bytes], bytes]] = {
    "truncated": lambda data: data[: len(data) // 2],
    "head": lambda data: data[: len(data) // 10],  # an MP4's header, and too little of its frames for an episode
    "garbage": _garbage,
    "middle": _middle,
    "json-array": lambda data: b"[1, 2, 3]\n",  # valid JSON of the wrong type for a file that holds an object
}


def damaged_copy(source: Path, dst: Path, relative: str, corruption: str) -> Path:
    """`source` at `dst`, every file a link to the original except `relative`, written damaged by `corruption`
    (the folders on its path are real ones, so nothing under `source` is ever written)."""
    target = Path(relative)
    real = [Path(), *reversed(target.parents[:-1])]  # `dst` itself and the folders down to the damaged file
    for folder in real:
        (dst / folder).mkdir(parents=True, exist_ok=True)
        for entry in sorted((source / folder).iterdir()):
            inside = folder / entry.name
            if inside != target and inside not in real:
                (dst / inside).symlink_to(entry.resolve())
    (dst / target).write_bytes(CORRUPTIONS[corruption]((source / target).read_bytes()))
    return dst
