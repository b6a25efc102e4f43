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
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from openpi_cam.demo import metaworld_data, metaworld_sim, train, train_state
from openpi_cam.lerobot.dataset import is_lerobot_dataset, open_dataset
from openpi_cam.lerobot.writer import Feature, create_dataset
from openpi_cam.policies import demo_metaworld
from openpi_cam.policies.config import PolicyConfig


@dataclasses.dataclass(frozen=True)
class RecordArgs:
    """Which tasks, how many expert episodes of each, and how noisy; None: the simulator choice's own (`SIMS`)."""

    episodes: int | None = None  # per task
    tasks: tuple[str, ...] | None = None  # Meta-World task names, e.g. reach-v3 push-v3
    seed: int = 100_000  # episode i of a task is scene seed + i (the demo's evaluation episodes start at 0)
    noise: float = 0.3  # std of the noise added to executed actions (DART)
    clean_every: int = 4  # every this many episodes runs without noise (the expert's own path)
    image_size: int | None = None  # both cameras, square
    phrasings: int | None = None  # how many of each task's instructions the episodes cycle through
    wrist_camera: str = metaworld_sim.WRIST_CAMERA  # the scene's camera recorded as the wrist view


@dataclasses.dataclass(frozen=True)
class MetaWorldModels:
    """What `--sim` trains on Meta-World: the expert episodes' defaults and the bundled model per family."""

    tasks: tuple[str, ...]
    episodes: int
    image_size: int
    configs: dict[str, PolicyConfig]  # family -> the bundled model's config
    phrasings: int  # how many of each task's instructions the episodes cycle through
    vocabulary: tuple[str, ...] = ()  # prompts the tokenizer learns beyond the recorded ones


SIMS = {
    "metaworld": MetaWorldModels(
        metaworld_sim.TRAINED_TASKS,
        120,
        demo_metaworld.MT_IMAGE_SIZE,
        {
            "pi05": demo_metaworld.DEMO_METAWORLD_MT_PI05_CONFIG,
            "pi0_fast": demo_metaworld.DEMO_METAWORLD_MT_PI0_FAST_CONFIG,
        },
        phrasings=3,
        vocabulary=metaworld_sim.all_prompts(),
    ),
    "metaworld-button": MetaWorldModels(
        (metaworld_sim.TASK,),
        200,
        metaworld_sim.IMAGE_SIZE,
        {"pi05": demo_metaworld.DEMO_METAWORLD_CONFIG},
        phrasings=1,
    ),
}


def with_defaults(record: RecordArgs, models: MetaWorldModels) -> RecordArgs:
    return dataclasses.replace(
        record,
        episodes=models.episodes if record.episodes is None else record.episodes,
        tasks=models.tasks if record.tasks is None else record.tasks,
        image_size=models.image_size if record.image_size is None else record.image_size,
        phrasings=models.phrasings if record.phrasings is None else record.phrasings,
    )


def record_expert(root: Path, args: RecordArgs) -> None:
    """The expert's episodes as a LeRobot v3.0 dataset (PNG cameras: the frames the model trains on, losslessly),
    the tasks interleaved episode by episode; episode i of a task is instructed by the task's phrasing i modulo their
    number."""
    assert args.tasks is not None and args.episodes is not None and args.image_size is not None  # `with_defaults`
    unknown = [t for t in args.tasks if t not in metaworld_sim.TASKS]
    if unknown:
        raise ValueError(f"unknown Meta-World tasks {unknown}: one of {', '.join(metaworld_sim.TASKS)}")
    size = args.image_size
    features = {
        metaworld_data.BASE_FEATURE: Feature.camera(size, size, video=False),
        metaworld_data.WRIST_FEATURE: Feature.camera(size, size, video=False),
        metaworld_data.STATE_FEATURE: Feature("float32", (metaworld_sim.STATE_DIM,)),
        metaworld_data.ACTION_FEATURE: Feature("float32", (metaworld_sim.ACTION_DIM,)),
    }
    t0 = time.time()
    with create_dataset(root, fps=metaworld_data.FPS, features=features, robot_type="sawyer") as writer:
        wins, total = 0, args.episodes * len(args.tasks)
        for e in range(args.episodes):
            noise = 0.0 if e % args.clean_every == 0 else args.noise
            for task in args.tasks:
                prompts = metaworld_sim.TASKS[task].prompts[: args.phrasings]
                prompt = prompts[e % len(prompts)]
                episode = metaworld_data.expert_episode(
                    args.seed + e, noise, task=task, prompt=prompt, image_size=size, wrist_camera=args.wrist_camera
                )
                success = False
                for step in episode:
                    writer.add_frame(step.frame, task=step.prompt)
                    success = step.success
                writer.save_episode()
                wins += success
                done = e * len(args.tasks) + args.tasks.index(task) + 1
                print(f"episode {done}/{total} ({task}): {wins} successes, {time.time() - t0:.0f}s", flush=True)


def read_demonstrations(roots: Sequence[Path]) -> metaworld_data.Demonstrations:
    """The expert frames of every dataset in `roots`, in that order; episodes numbered on across datasets (each
    dataset counts its own from 0, and a chunk must not run from one dataset's episode into another's)."""
    frames: list[dict] = []
    for root in roots:
        offset = frames[-1]["episode_index"] + 1 if frames else 0
        dataset = open_dataset(root)
        for episode in dataset.episodes:
            frames += [{**f, "episode_index": offset + int(f["episode_index"])} for f in dataset.frames(episode)]
    return metaworld_data.Demonstrations.from_frames(frames, [frame["task"] for frame in frames])


def parse_task_weights(given: Sequence[str]) -> dict[str, float]:
    """`TASK=WEIGHT` pairs -> {task: weight}; a ValueError in one line names a malformed pair, an unknown task or a
    weight that is not a positive number."""
    weights: dict[str, float] = {}
    for pair in given:
        name, sep, value = pair.partition("=")
        if not sep or name not in metaworld_sim.TASKS:
            raise ValueError(f"{pair!r}: TASK=WEIGHT with TASK one of {', '.join(metaworld_sim.TASKS)}")
        try:
            weight = float(value)
        except ValueError:
            weight = float("nan")
        if not (np.isfinite(weight) and weight > 0):
            raise ValueError(f"{pair!r}: the weight must be a positive number")
        weights[name] = weight
    return weights


DEFAULT_TRAIN = train.TrainArgs()
DEFAULT_RECORD = RecordArgs()


def _unused(
    args: train.TrainArgs, sim: str, data: tuple[Path, ...], record: RecordArgs, task_weights: tuple[str, ...]
) -> str | None:
    """What the flags given leave without effect or cannot use (and the command refuses), or None."""
    recording = [f"--record.{f.name.replace('_', '-')}" for f in dataclasses.fields(record)
                 if getattr(record, f.name) != getattr(DEFAULT_RECORD, f.name)]  # fmt: skip
    if sim == "reach" and (data or recording or task_weights):
        given = ", ".join((["--data"] if data else []) + recording + (["--task-weights"] if task_weights else []))
        return f"{given}: Meta-World's expert episodes: add --sim metaworld"
    # The reaching task's alone: Meta-World trains on its recorded frames, where the binding probe has no scenes.
    fixed = [f"--args.{n.replace('_', '-')}" for n in ("probe_every", "contrast_pairs")
             if getattr(args, n) != getattr(DEFAULT_TRAIN, n)]  # fmt: skip
    if sim != "reach" and fixed:
        return f"{', '.join(fixed)}: the reaching task's; --sim {sim} trains on its recorded frames"
    if refused := args.unused():
        return refused.replace("--", "--args.")
    if record.wrist_camera != DEFAULT_RECORD.wrist_camera:
        try:
            metaworld_sim.require_camera(record.wrist_camera, (record.tasks or (metaworld_sim.TASK,))[0])
        except ValueError as e:
            return f"--record.wrist-camera {e}"
    if sim != "reach" and recording and data and is_lerobot_dataset(data[0]):
        return f"{', '.join(recording)}: {data[0]} holds its expert episodes already (a new folder records them)"
    if args.resume and data and not is_lerobot_dataset(data[0]):
        return f"--args.resume: no LeRobot dataset in {data[0]} (a resumed run trains on the frames it started on)"
    if missing := [str(d) for d in data[1:] if not is_lerobot_dataset(d)]:
        return f"--data {' '.join(missing)}: no LeRobot dataset there (only the first folder is recorded into)"
    try:
        parse_task_weights(task_weights)
    except ValueError as e:
        return f"--task-weights {e}"
    return None


def main(
    args: train.TrainArgs = DEFAULT_TRAIN,
    sim: Literal["reach", "metaworld", "metaworld-button"] = "reach",
    data: tuple[Path, ...] = (),
    record: RecordArgs = DEFAULT_RECORD,
    task_weights: tuple[str, ...] = (),
) -> int:
    """Train a demo model.

    Args:
        args: the training run (as `python -m openpi_cam.demo.train`); `--args.model` picks the family.
        sim: which simulator's task: the synthetic reaching task, Meta-World's six tasks (the multi-task pi0.5 or
            pi0-FAST) or Meta-World's button press alone (the one-task pi0.5).
        data: metaworld: the LeRobot datasets of expert episodes, trained on together; the first is recorded first
            if its folder is absent or empty (`--record.*`), the others must hold datasets.
        record: metaworld: the expert episodes to record.
        task_weights: metaworld: TASK=WEIGHT pairs (e.g. push-v3=3): the named tasks' frames are drawn for training
            WEIGHT times as often as the others' (whose weight is 1); the shares printed before training.
    """
    if refused := _unused(args, sim, data, record, task_weights):
        print(f"train_demo: {refused}")
        return 2
    models = SIMS.get(sim)
    if models is not None and args.model not in models.configs:
        print(f"train_demo: --sim {sim} trains {', '.join(models.configs)}, not --args.model {args.model}")
        return 2
    config = None if models is None else models.configs[args.model]
    if refused := train.resume_refused(args, config):
        print(f"train_demo: {refused.replace('--', '--args.', 1)}")
        return 2
    if models is not None and not data:
        print(f"train_demo: --sim {sim} needs --data DIR (the expert episodes' LeRobot dataset)")
        return 2
    try:
        if models is None:
            train.train(args)
            return 0
        return _train_metaworld(args, models, config, data, record, task_weights)
    except train_state.StateError as e:
        print(f"train_demo: --args.resume: {e}")
        return 2
    except train_state.Stopped as e:
        print(f"train_demo: {e}")
        return 1


def _train_metaworld(
    args: train.TrainArgs,
    models: MetaWorldModels,
    config: PolicyConfig,
    data: tuple[Path, ...],
    record: RecordArgs,
    task_weights: tuple[str, ...],
) -> int:
    record = with_defaults(record, models)
    if not is_lerobot_dataset(data[0]):
        record_expert(data[0], record)
    demos = read_demonstrations(data)
    print(f"{len(demos)} frames in {len(np.unique(demos.episode_index))} episodes from {', '.join(map(str, data))}")
    if task_weights:
        try:
            demos = demos.weighted(parse_task_weights(task_weights))
        except ValueError as e:
            print(f"train_demo: --task-weights: {e} ({', '.join(map(str, data))})")
            return 2
    shares = ", ".join(f"{t or 'other'} {share:.0%}" for t, share in demos.task_shares().items())
    print(f"training draws by task: {shares}", flush=True)
    train.train(args, demonstrations=demos, config=config, vocabulary=models.vocabulary, eval_tasks=record.tasks)
    return 0


if __name__ == "__main__":
    import tyro

    raise SystemExit(tyro.cli(main))
