"""Checks that LeRobot 0.6.1's own `LeRobotDataset` opens datasets written by `openpi_cam.lerobot.writer` and
returns, frame by frame, what was written. Not a test: LeRobot needs torch, which neither the project nor CI has.

Two steps, two environments:

    .venv/bin/python benchmarks/check_lerobot_reads.py write /tmp/lerobot_check [--sim metaworld]
    HF_HUB_OFFLINE=1 /work/lerobot-env/bin/python benchmarks/check_lerobot_reads.py check /tmp/lerobot_check

`write` (the project's environment) records rollouts of the demo reaching task, the way `lerobot-eval
--eval.recording=true` records evaluation episodes (per frame the observation, the action taken and the step's
`next.reward` / `next.success` / `next.done`). It writes three datasets: `rollouts`, the bundled pi0-FAST driven
closed loop through the websocket server under perturbations (`openpi-cam demo --record`'s recorder), and two written
frame by frame with a scripted controller, every other episode of which heads for the wrong block (so those episodes
fail and run to the step limit): `mixed` (base camera as AV1 video, wrist camera as PNG images, one file each) and
`split` (both cameras as video, file limits so small that every episode has its own files, two files a chunk). Beside
each it stores `<name>.expected.npz`: every column as given to the writer, the camera frames as given, and the video
frames as our reader decodes them. With `--sim metaworld` (the `metaworld` extra) it writes one dataset instead,
`metaworld`: the bundled Meta-World pi0.5 driven closed loop through the server under perturbations, recorded as
`openpi-cam demo --sim metaworld --record` records it (80 fps, the button box's bounding box, the perturbation's
index).

`check` (a LeRobot 0.6.1 environment, e.g. /work/lerobot-env, see its README.txt; it imports nothing of openpi_cam)
opens each dataset with `LeRobotDataset(repo_id, root=..., video_backend="pyav")`, reads every frame through
`__getitem__` and compares: every non-camera column and the task string exactly (a float64 column as the float32
LeRobot's torch conversion returns; its loaded table is compared in float64), image cameras exactly, video frames
against our reader's decoding of the same file and against the frames given. It prints one JSON line per dataset
and exits 1 if anything differs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

FPS = 10
MAX_STEPS = 12
EPISODES = 8
# LeRobot and our reader decode the same AV1 packets with dav1d; only the yuv420p -> RGB conversion may round
# differently between their FFmpeg builds.
DECODER_TOLERANCE = 2
# per-frame mean |decoded - given| of 255: AV1 at crf 30 on these 64 px frames loses 1.5 to 6 (LeRobot's own
# recording of the demo task included)
CODEC_MEAN_ERROR = 8.0


def _record(root: Path, *, base: str, wrist: str, **limits) -> dict[str, np.ndarray]:
    from openpi_cam.demo import sim, task
    from openpi_cam.lerobot.dataset import open_dataset
    from openpi_cam.lerobot.writer import OUTCOME_FEATURES, Feature, create_dataset

    cameras = {"observation.images.base": base, "observation.images.wrist": wrist}
    features = {
        **{name: Feature.camera(64, 64, video=kind == "video") for name, kind in cameras.items()},
        "observation.state": Feature("float32", (2,), ("x", "y")),
        "action": Feature("float32", (2,), ("dx", "dy")),
        "observation.target_box": Feature("float32", (4,), ("x0", "y0", "x1", "y1")),
        # extras of other dtypes: how many blocks, how far the named one is, whether it / another one is within reach
        "observation.blocks": Feature("int64", (1,)),
        "observation.distance": Feature("float64", (1,)),
        "observation.near": Feature("bool", (2,), ("named", "other")),
        **OUTCOME_FEATURES,
    }
    expected: dict[str, list] = {}
    with create_dataset(root, fps=FPS, features=features, robot_type="demo_reach", **limits) as writer:
        for episode in range(EPISODES):
            env = sim.new_episode(seed=100 + episode)
            scene = env.scene
            if episode % 2:  # a controller that misreads the prompt: it reaches for another block
                scene = scene.with_target(scene.blocks[task.other_block(np.random.default_rng(episode), scene)].color)
            for step in range(MAX_STEPS):
                seen = env.observe()
                centres = [task.block_center(b, env.cfg.image_size) for b in env.scene.blocks]
                distances = np.array([np.linalg.norm(env.state - c) for c in centres])
                named = distances[env.scene.target]
                others = np.delete(distances, env.scene.target)
                action = task.expert_chunk(env.state, task.block_center(scene.target_block, env.cfg.image_size))[0]
                success = env.execute(action[None])
                done = success or step == MAX_STEPS - 1
                frame = {
                    "observation.images.base": seen.base_image,
                    "observation.images.wrist": seen.wrist_image,
                    "observation.state": seen.state,
                    "action": action,
                    "observation.target_box": np.array(seen.target_box, np.float32),
                    "observation.blocks": np.array([len(centres)], np.int64),
                    "observation.distance": np.array([named], np.float64),
                    "observation.near": np.array([named, others.min()]) <= 2 * env.cfg.success_radius,
                    "next.reward": np.array([float(success)], np.float32),
                    "next.success": np.array([success]),
                    "next.done": np.array([done]),
                }
                writer.add_frame(frame)
                for name, value in {**frame, "task": np.array(seen.prompt)}.items():
                    expected.setdefault(name, []).append(value)
                if done:
                    break
            writer.save_episode(task=seen.prompt)
    ours = open_dataset(root)
    for name, kind in cameras.items():
        if kind == "video":
            expected[f"decoded/{name}"] = [f[name] for e in ours.episodes for f in ours.frames(e, features=[name])]
    return {name: np.stack(values) for name, values in expected.items()}


class _Capture:
    """A rollout sink that keeps every step it passes on to the recorder: what the dataset must give back."""

    def __init__(self, recorder) -> None:
        self.recorder = recorder
        self.expected: dict[str, list] = {}

    def step(self, frame, *, task: str, reward: float, success: bool, done: bool) -> None:
        self.recorder.step(frame, task=task, reward=reward, success=success, done=done)
        outcome = {"next.reward": np.float32([reward]), "next.success": np.array([success]), "next.done": [done]}
        for name, value in {**frame, **outcome, "task": np.array(task)}.items():
            self.expected.setdefault(name, []).append(np.asarray(value))

    def end_episode(self):
        return self.recorder.end_episode()


def _record_rollouts(root: Path, sim: str = "reach") -> dict[str, np.ndarray]:
    """Closed-loop demo rollouts under perturbations, served through the real websocket server and client and
    recorded as `openpi-cam demo --record` records them."""
    from openpi_cam.demo.run import ROLLOUT_FPS, ROLLOUT_FPS_METAWORLD, DemoOptions, run_demo
    from openpi_cam.lerobot.dataset import open_dataset
    from openpi_cam.lerobot.rollouts import RolloutRecorder

    assert ROLLOUT_FPS == FPS
    if sim == "metaworld":
        perturb, episodes, fps = ("clean", "hue=45", "dim=0.75", "distractors=5"), 4, ROLLOUT_FPS_METAWORLD
    else:
        perturb, episodes, fps = ("clean", "hue=45", "shift=32", "absent"), EPISODES, ROLLOUT_FPS
    options = DemoOptions(sim=sim, num_episodes=episodes, perturb=perturb, explain=False)
    with RolloutRecorder(root, fps=fps, robot_type=f"demo_{sim}") as recorder:
        capture = _Capture(recorder)
        run_demo(options, sink=capture)
    expected = {name: np.stack(values) for name, values in capture.expected.items()}
    ours = open_dataset(root)
    for name in ours.camera_features:
        expected[f"decoded/{name}"] = np.stack(
            [f[name] for e in ours.episodes for f in ours.frames(e, features=[name])]
        )
    return expected


def write(out: Path, sim: str = "reach") -> None:
    out.mkdir(parents=True, exist_ok=True)
    name = "metaworld" if sim == "metaworld" else "rollouts"
    expected = _record_rollouts(out / name, sim)
    np.savez_compressed(out / f"{name}.expected.npz", **expected)
    ends = expected["next.done"][:, 0]
    summary = {
        "frames": len(ends),
        "successes": int(expected["next.success"][ends, 0].sum()),
        "episodes": int(ends.sum()),
    }
    print(json.dumps({"dataset": str(out / name), **summary}))
    if sim == "metaworld":
        return
    datasets = {
        "mixed": {"base": "video", "wrist": "image"},
        "split": {
            "base": "video",
            "wrist": "video",
            "chunks_size": 2,
            "data_files_size_in_mb": 1e-4,
            "video_files_size_in_mb": 1e-4,
        },
    }
    for name, options in datasets.items():
        expected = _record(out / name, **options)
        np.savez_compressed(out / f"{name}.expected.npz", **expected)
        outcomes = expected["next.success"][expected["next.done"][:, 0], 0]
        print(
            json.dumps(
                {
                    "dataset": str(out / name),
                    "frames": len(expected["action"]),
                    "successes": int(outcomes.sum()),
                    "episodes": len(outcomes),
                }
            )
        )


def expect(out: Path, roots: list[Path], frames: int | None) -> None:
    """Datasets written elsewhere (a training recording, `demo --record`'s rollouts): each linked into `out` with
    what our reader returns for its first `frames` frames (all when None) as the expected values, video frames as
    both the frames given and our decoding (so the codec figure compares LeRobot's decoding with ours again)."""
    from openpi_cam.lerobot.dataset import open_dataset

    out.mkdir(parents=True, exist_ok=True)
    for root in roots:
        ours = open_dataset(root)
        total = sum(info.length for info in ours.episode_info.values())
        rows: list[dict] = []
        for episode in ours.episodes:  # only the episodes that hold the first `frames` frames are decoded
            if frames is not None and len(rows) >= frames:
                break
            rows += list(ours.frames(episode))
        rows = rows[:frames]
        names = [k for k in rows[0] if k in ours.features or k == "task"]
        expected = {k: np.stack([np.asarray(f[k]) for f in rows]) for k in names}
        for name in ours.camera_features:
            expected[f"decoded/{name}"] = expected[name]
        (out / root.name).symlink_to(root.resolve())
        np.savez_compressed(out / f"{root.name}.expected.npz", **expected, total_frames=np.int64(total))
        print(json.dumps({"dataset": str(root), "frames": total, "expected_frames": len(rows)}))


def _uint8(image) -> np.ndarray:
    """LeRobot's float [C, H, W] in [0, 1] as uint8 [H, W, C]."""
    return (image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def check(out: Path) -> bool:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ok = True
    for path in sorted(p for p in out.iterdir() if p.is_dir()):
        expected = np.load(out / f"{path.name}.expected.npz")
        ds = LeRobotDataset(f"local/{path.name}", root=path, video_backend="pyav")
        features = ds.meta.features
        videos = [k for k, f in features.items() if f["dtype"] == "video"]
        images = [k for k, f in features.items() if f["dtype"] == "image"]
        columns = [k for k in expected.files if k in features and k not in videos + images]
        n = len(expected["action"])
        total = int(expected["total_frames"]) if "total_frames" in expected.files else n  # `expect`'s first frames
        report = {
            "dataset": str(path),
            "lerobot_frames": len(ds),
            "written_frames": total,
            "compared_frames": n,
            "episodes": ds.meta.total_episodes,
            "tasks": ds.meta.total_tasks,
            "data_files": len({str(ds.meta.get_data_file_path(e)) for e in range(ds.meta.total_episodes)}),
            "mismatched_columns": {},
            "image_max_diff": dict.fromkeys(images, 0),
            "video_max_diff_vs_our_reader": dict.fromkeys(videos, 0),
            "video_worst_frame_mean_error_vs_given": dict.fromkeys(videos, 0.0),
        }
        ok &= len(ds) == total
        # the columns as LeRobot's loaded table holds them, before its torch conversion: exact, in their own dtype
        table = ds.hf_dataset.data
        for key in columns:
            held = np.array(table.column(key).slice(0, n).to_pylist(), expected[key].dtype).reshape(expected[key].shape)
            if not np.array_equal(held, expected[key]):
                report["mismatched_columns"][f"table/{key}"] = int((held != expected[key]).any(axis=-1).sum())
        last_episode, frame_index = -1, 0
        for i in range(min(len(ds), n)):
            item = ds[i]
            episode = int(item["episode_index"])
            frame_index = frame_index + 1 if episode == last_episode else 0
            last_episode = episode
            derived = {"index": i, "frame_index": frame_index, "timestamp": np.float32(frame_index / ds.meta.fps)}
            for key, value in derived.items():
                if item[key].numpy() != value:
                    report["mismatched_columns"][key] = report["mismatched_columns"].get(key, 0) + 1
            for key in columns:
                theirs, ours = item[key].numpy(), expected[key][i]
                if ours.dtype == np.float64:  # LeRobot's torch.tensor(a Python float) gives torch's default float32
                    ours = ours.astype(np.float32)
                if theirs.dtype != ours.dtype or not np.array_equal(theirs.reshape(ours.shape), ours):
                    report["mismatched_columns"][key] = report["mismatched_columns"].get(key, 0) + 1
            if item["task"] != str(expected["task"][i]):
                report["mismatched_columns"]["task"] = report["mismatched_columns"].get("task", 0) + 1
            for key in images:
                diff = int(np.abs(_uint8(item[key]).astype(np.int16) - expected[key][i]).max())
                report["image_max_diff"][key] = max(report["image_max_diff"][key], diff)
            for key in videos:
                frame = _uint8(item[key]).astype(np.int16)
                diff = int(np.abs(frame - expected[f"decoded/{key}"][i]).max())
                report["video_max_diff_vs_our_reader"][key] = max(report["video_max_diff_vs_our_reader"][key], diff)
                error = float(np.abs(frame - expected[key][i]).mean())
                worst = report["video_worst_frame_mean_error_vs_given"]
                worst[key] = round(max(worst[key], error), 3)
        ok &= not report["mismatched_columns"]
        ok &= all(v == 0 for v in report["image_max_diff"].values())
        ok &= all(v <= DECODER_TOLERANCE for v in report["video_max_diff_vs_our_reader"].values())
        ok &= all(v <= CODEC_MEAN_ERROR for v in report["video_worst_frame_mean_error_vs_given"].values())
        print(json.dumps(report))
    return ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("step", choices=["write", "expect", "check"])
    parser.add_argument("out", type=Path)
    parser.add_argument("datasets", type=Path, nargs="*", help="expect: LeRobot datasets written elsewhere")
    parser.add_argument("--sim", choices=["reach", "metaworld"], default="reach", help="write: which demo's rollouts")
    parser.add_argument("--frames", type=int, default=None, help="expect: compare the first FRAMES frames (all)")
    args = parser.parse_args()
    if args.datasets and args.step != "expect":
        parser.error("datasets are expect's: write records its own, check reads OUT")
    if args.step == "write":
        write(args.out, args.sim)
    elif args.step == "expect":
        expect(args.out, args.datasets, args.frames)
    elif not check(args.out):
        print("MISMATCH: LeRobot does not return what was written", file=sys.stderr)
        sys.exit(1)
    else:
        print("OK: LeRobot 0.6.1 returns what was written")


if __name__ == "__main__":
    main()
