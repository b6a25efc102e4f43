"""Train a bundled demo model, its data going through a LeRobot dataset as a user's would:
`python -m openpi_cam.cli.train_demo --sim metaworld --data DIR --out DIR`.

`--sim reach` is `python -m openpi_cam.demo.train` (procedural samples, nothing recorded). `--sim metaworld` records
the scripted expert's episodes as a LeRobot v3.0 dataset in `--data` (unless it already holds one), reads them back
through the project's LeRobot reader and trains the tiny pi0.5 on them with `demo.train` (the command line composes
the two: the demo room records through the sink it is handed and reads no dataset).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Literal

import numpy as np

from openpi_cam.demo import metaworld_data, metaworld_sim, train
from openpi_cam.lerobot.dataset import is_lerobot_dataset, open_dataset
from openpi_cam.lerobot.writer import Feature, create_dataset
from openpi_cam.policies import demo_metaworld


@dataclasses.dataclass(frozen=True)
class RecordArgs:
    """How many expert episodes, and how noisy."""

    episodes: int = 200
    seed: int = 100_000  # episode i's scene is seed + i (the demo's evaluation episodes start at 0)
    noise: float = 0.3  # std of the noise added to executed actions (DART)
    clean_every: int = 4  # every this many episodes runs without noise (the expert's own path)


def record_expert(root: Path, args: RecordArgs) -> None:
    """The expert's episodes as a LeRobot v3.0 dataset (PNG cameras: the frames the model trains on, losslessly)."""
    size = metaworld_sim.IMAGE_SIZE
    features = {
        metaworld_data.BASE_FEATURE: Feature.camera(size, size, video=False),
        metaworld_data.WRIST_FEATURE: Feature.camera(size, size, video=False),
        metaworld_data.STATE_FEATURE: Feature("float32", (metaworld_sim.STATE_DIM,)),
        metaworld_data.ACTION_FEATURE: Feature("float32", (metaworld_sim.ACTION_DIM,)),
    }
    t0 = time.time()
    with create_dataset(root, fps=metaworld_data.FPS, features=features, robot_type="sawyer") as writer:
        wins = 0
        for e in range(args.episodes):
            noise = 0.0 if e % args.clean_every == 0 else args.noise
            success = False
            for step in metaworld_data.expert_episode(args.seed + e, noise):
                writer.add_frame(step.frame, task=step.prompt)
                success = step.success
            writer.save_episode()
            wins += success
            print(f"episode {e + 1}/{args.episodes}: {wins} successes, {time.time() - t0:.0f}s", flush=True)


def read_demonstrations(root: Path) -> metaworld_data.Demonstrations:
    dataset = open_dataset(root)
    frames = [frame for episode in dataset.episodes for frame in dataset.frames(episode)]
    return metaworld_data.Demonstrations.from_frames(frames, [frame["task"] for frame in frames])


DEFAULT_TRAIN = train.TrainArgs()
DEFAULT_RECORD = RecordArgs()


def main(
    args: train.TrainArgs = DEFAULT_TRAIN,
    sim: Literal["reach", "metaworld"] = "reach",
    data: Path | None = None,
    record: RecordArgs = DEFAULT_RECORD,
) -> int:
    """Train a demo model.

    Args:
        args: the training run (as `python -m openpi_cam.demo.train`).
        sim: which simulator's task: the synthetic reaching task or Meta-World's button press.
        data: metaworld: the LeRobot dataset of expert episodes, recorded there first if the folder is absent or empty.
        record: metaworld: the expert episodes to record.
    """
    if sim == "reach":
        train.train(args)
        return 0
    if data is None:
        print("train_demo: --sim metaworld needs --data DIR (the expert episodes' LeRobot dataset)")
        return 2
    if not is_lerobot_dataset(data):
        record_expert(data, record)
    demos = read_demonstrations(data)
    print(f"{len(demos)} frames in {len(np.unique(demos.episode_index))} episodes from {data}", flush=True)
    train.train(
        dataclasses.replace(args, model="pi05"), demonstrations=demos, config=demo_metaworld.DEMO_METAWORLD_CONFIG
    )
    return 0


if __name__ == "__main__":
    import tyro

    raise SystemExit(tyro.cli(main))
