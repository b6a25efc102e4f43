"""The whole system on a bundled tiny model: serve it on loopback with the side channel explaining every
inference, drive simulated episodes (the reaching task, or Meta-World's button press) through a websocket client
exactly as a robot would, render the maps and score them against the ground-truth boxes the client sent along
(`cam_extra/target_box`)."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from openpi_cam.cam.faithfulness_run import FaithfulnessOptions, evaluate_run
from openpi_cam.cam.monitoring import LiveMonitor
from openpi_cam.cam.run_evidence import REPORT_FILE
from openpi_cam.cam.run_format import dumps, load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.demo import bundled, metaworld_data, metaworld_loop, metaworld_sim, quality, task
from openpi_cam.demo.client import PolicyClient, RolloutSink
from openpi_cam.demo.perturb import Perturbation
from openpi_cam.monitor import monitor_file
from openpi_cam.policies import demo_metaworld
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.viz.render import RenderOptions, default_render_dir, render_run
from openpi_cam.vocabulary import (
    COMPARED_KINDS,
    DEFAULT_KINDS,
    OCCLUSION_HEAD,
    Baseline,
    IgSpace,
    MapKind,
    MapOptions,
    Target,
)


def run_episodes(
    url: str,
    episodes: int,
    *,
    seed: int,
    max_calls: int,
    execute: int,
    perturbations: Sequence[Perturbation],
    sink: RolloutSink | None = None,
) -> list[dict[str, Any]]:
    """Closed loop over the server: observe, infer a chunk, execute its first `execute` actions one step at a time,
    repeat until the block is reached or `max_calls` chunks are spent. Episode i is the scene of seed + i // P under
    perturbation i % P (P perturbations): every perturbation meets the same scenes. Each step goes to `sink`. Each
    episode is a connection of its own, as a robot's: what the server keeps per connection (the monitor's score,
    STAC's previous chunk) starts afresh with it."""
    results = []
    for e in range(episodes):
        with PolicyClient(url) as client:
            which = e % len(perturbations)
            episode_seed = seed + e // len(perturbations)
            episode = perturbations[which].episode(episode_seed)
            calls = 0
            while calls < max_calls and not episode.success:
                sample = episode.observe()
                reply = client.infer(bundled.client_observation(sample, episode.scene))
                calls += 1
                chunk = np.asarray(reply["actions"])[:execute]
                for j, action in enumerate(chunk):
                    success = episode.execute(action[None])
                    last = calls == max_calls and j == len(chunk) - 1
                    if sink is not None:
                        frame = bundled.recorded_frame(sample, action, which)
                        sink.step(
                            frame, task=sample.prompt, reward=float(success), success=success, done=success or last
                        )
                    if success:
                        break
                    sample = episode.observe()
            if sink is not None:
                sink.end_episode()
            results.append(
                {
                    "seed": episode_seed,
                    "perturbation": perturbations[which].name,
                    "prompt": episode.observe().prompt,
                    "success": bool(episode.success),
                    "calls": calls,
                    "steps": episode.steps,
                    "final_distance": float(((episode.state - episode.goal) ** 2).sum() ** 0.5),
                }
            )
    return results


def run_metaworld_episodes(
    url: str,
    episodes: int,
    *,
    seed: int,
    max_calls: int | None,
    execute: int,
    perturbations: Sequence[metaworld_sim.Perturbation],
    tasks: Sequence[str] = (metaworld_sim.TASK,),
    image_size: int = metaworld_sim.IMAGE_SIZE,
    sink: RolloutSink | None = None,
) -> list[dict[str, Any]]:
    """Meta-World episodes over the server: episode i drives task (i // P) mod T under perturbation i mod P in the
    scene of seed + i // (P T) (T tasks, P perturbations), so every task meets every perturbation in the same scenes;
    `max_calls` None gives each task its own budget. Cameras render at `image_size` px (the robot the model serves).
    Each episode is a connection of its own (`run_episodes`)."""
    p, t = len(perturbations), len(tasks)
    results = []
    for e in range(episodes):
        with PolicyClient(url) as client:
            results.append(
                metaworld_loop.run_episode(
                    client.infer,
                    seed + e // (p * t),
                    perturbations[e % p],
                    task=tasks[(e // p) % t],
                    max_calls=max_calls,
                    execute=execute,
                    sink=sink,
                    perturbation_index=e % p,
                    image_size=image_size,
                )
            )
    return results


ROLLOUT_FPS = 10  # the frame rate recorded rollouts declare (the simulator has no clock: one frame per action)
ROLLOUT_FPS_METAWORLD = metaworld_data.FPS  # Meta-World's control rate
MAX_CALLS = 6  # the reaching task's calls per episode (a Meta-World task's: `metaworld_loop.max_calls_of`)
# The Meta-World models `--model` names, and the size their robot's cameras render at.
METAWORLD_MODELS = {"pi05": "metaworld_mt_pi05", "pi0_fast": "metaworld_mt_pi0_fast"}
METAWORLD_CAMERA_SIZE = demo_metaworld.MT_IMAGE_SIZE
# `--task` names that stand for a group of Meta-World tasks.
TASK_GROUPS = {"all": metaworld_sim.TRAINED_TASKS, "held-out": metaworld_sim.HELD_OUT_TASKS}
DRAIN_S = 3600.0  # how long the end of a demo run may spend explaining requests still queued


@dataclasses.dataclass(frozen=True)
class DemoOptions:
    """What `openpi-cam demo` runs (its flags)."""

    # the folder in which the CAM run directory is created.
    out: pathlib.Path = pathlib.Path("demo_runs")
    # which simulator the robot lives in: the synthetic reaching task, or Meta-World (MuJoCo; needs
    # `pip install -e ".[metaworld]"`), whose tasks a bundled multi-task model serves.
    sim: Literal["reach", "metaworld"] = "reach"
    # metaworld: the tasks the episodes drive, in turn (names of `openpi_cam.demo.metaworld_sim.TASKS`; `all`: the six
    # the models were trained on; `held-out`: the two they never saw).
    task: tuple[str, ...] = (metaworld_sim.TASK,)
    # simulated episodes to drive.
    num_episodes: int = 3
    # inference calls per episode at most (default: 6 for reach; for a Meta-World task its own budget, about twice
    # the steps its expert needs, at `execute` actions a call).
    max_calls: int | None = None
    # actions of each returned chunk the robot executes before asking again.
    execute: int = 5
    # the first episode's seed (episode i uses seed + i // P for P perturbations).
    seed: int = 0
    # what the episodes are run under, in turn (`kind=strength`; reach: clean, distractors=N, hue=DEGREES,
    # shift=PIXELS, dim=FACTOR, absent (`openpi_cam.demo.perturb`); metaworld: clean, hue=DEGREES, dim=FACTOR,
    # shift=METRES, distractors=N, prompt=TEXT (`openpi_cam.demo.metaworld_sim`)): episode i under the (i mod P)-th,
    # so each meets the same scenes.
    perturb: tuple[str, ...] = ("clean",)
    # serve with the explanation side channel on (every request explained and logged, then faithfulness and reports);
    # off, the episodes are only driven (and recorded with `--record`).
    explain: bool = True
    # what the maps explain for each inference.
    target: Target = "chunk"
    # write overlays and the HTML report of each map kind after the run.
    render: bool = True
    # with `render`, also write an MP4 and a GIF per episode.
    videos: bool = True
    # which bundled model serves: the tiny pi0-FAST or the tiny pi0.5 of the simulator's task (metaworld: the
    # multi-task models).
    model: Literal["pi0_fast", "pi05"] = "pi0_fast"
    # the folder holding the model (checkpoint/) and its tokenizers; default: the bundled ones of `model`.
    assets: pathlib.Path | None = None
    # which map kinds the side channel computes (default: reach, the kinds the faithfulness table compares,
    # `vocabulary.COMPARED_KINDS`; metaworld, the cheap ones, `vocabulary.DEFAULT_KINDS`: the costly kinds and
    # `occlusion-head` are opt-in).
    maps: tuple[MapKind, ...] | None = None
    # the head file `occlusion-head` applies (`openpi-cam head fit`); default: the model's own, where it ships one.
    head: pathlib.Path | None = None
    # re-score every step afterwards and report how faithful each map kind is.
    faithfulness: bool = True
    # the frame `ig` starts from and `occlusion` (and the faithfulness deletion) paints with.
    baseline: Baseline = MapOptions.baseline
    # where the `ig` path runs: between the SigLIP tokens of the baseline frame and the frame, or between the frames'
    # pixels (through SigLIP).
    ig_space: IgSpace = MapOptions.ig_space

    @property
    def perturbations(self) -> tuple[Perturbation, ...] | tuple[metaworld_sim.Perturbation, ...]:
        parse = metaworld_sim.Perturbation.parse if self.sim == "metaworld" else Perturbation.parse
        return tuple(parse(p) for p in self.perturb)

    @property
    def calls(self) -> int:
        """Calls per episode at most (Meta-World: the most any of the tasks may make)."""
        if self.max_calls is not None:
            return self.max_calls
        if self.sim == "metaworld":
            return max(metaworld_loop.max_calls_of(t, self.execute) for t in self.tasks)
        return MAX_CALLS

    @property
    def tasks(self) -> tuple[str, ...]:
        """The Meta-World tasks, groups expanded."""
        return tuple(dict.fromkeys(t for name in self.task for t in TASK_GROUPS.get(name, (name,))))

    @property
    def map_kinds(self) -> tuple[MapKind, ...]:
        if self.maps is not None:
            return self.maps
        return DEFAULT_KINDS if self.sim == "metaworld" else COMPARED_KINDS

    @property
    def bundled_model(self) -> str:
        """The bundled model that serves (`model_spec.BUNDLED_CONFIGS`)."""
        return METAWORLD_MODELS[self.model] if self.sim == "metaworld" else self.model

    def ignored(self) -> dict[str, str]:
        """The flags given (other than their defaults) that the other flags leave without effect: flag -> why. The
        command refuses them, so that no flag is accepted and then ignored."""
        flags = {}
        changed = [f.name for f in dataclasses.fields(self) if getattr(self, f.name) != f.default]
        spelled = {name: _flag(name, getattr(self, name)) for name in changed}
        if not self.explain:
            why = "--no-explain explains nothing (no run, maps, renders or faithfulness)"
            flags |= {spelled[name]: why for name in changed if name in _EXPLAINED}
        elif not self.render and "videos" in changed:
            flags[spelled["videos"]] = "--no-render writes no videos"
        return flags

    def __post_init__(self) -> None:
        if not self.perturb:
            raise ValueError("--perturb needs at least one perturbation (clean: none)")
        self.perturbations  # noqa: B018  (refused as the flags are parsed)
        unknown = [t for t in self.tasks if t not in metaworld_sim.TASKS]
        if unknown or not self.task:
            names = ", ".join([*TASK_GROUPS, *metaworld_sim.TASKS])
            raise ValueError(f"--task {' '.join(unknown) or '(none)'}: not a Meta-World task; one or more of {names}")
        if self.sim != "metaworld" and self.task != (metaworld_sim.TASK,):
            raise ValueError("--task names Meta-World tasks: it needs --sim metaworld")
        if self.head is not None and OCCLUSION_HEAD not in self.map_kinds:
            raise ValueError(f"--head {self.head} given but {OCCLUSION_HEAD} is not among the maps: add it to --maps")


# What only an explained run uses (the run's folder, the maps, their renders and faithfulness).
_EXPLAINED = ("out", "target", "render", "videos", "maps", "head", "faithfulness", "baseline", "ig_space")


def _flag(field: str, value: object) -> str:
    """How the command line spells a field set to `value` (`--no-render` for a switch turned off)."""
    name = field.replace("_", "-")
    return f"--no-{name}" if value is False else f"--{name}"


@dataclasses.dataclass
class DemoResult:
    run_dir: pathlib.Path | None  # None: the side channel was off
    episodes: list[dict[str, Any]]
    figures: dict[str, Any]
    reports: dict[str, pathlib.Path]
    seconds: float
    faithfulness: dict[str, Any] | None = None  # `cam.faithfulness_run.evaluate_run`'s report


class UnfitModel(ValueError):
    """The model folder cannot be served as the model `--model` and `--sim` choose (e.g. `--assets` holds another
    family's weights)."""


def _side_channel_options(opts: DemoOptions, model: ModelSpec) -> CAMOptions:
    """The side channel's options: every request explained with the flags' maps, with the head `occlusion-head`
    applies (UnfitModel when the model has none, or the one named was fitted for another model)."""
    try:
        head = model.occlusion_head(opts.head) if OCCLUSION_HEAD in opts.map_kinds else None
    except ValueError as e:
        raise UnfitModel(str(e)) from None
    return CAMOptions(
        every_k=1,
        dir=opts.out,
        save_frames="both",
        target=opts.target,
        maps=opts.map_kinds,
        map_options=MapOptions(baseline=opts.baseline, ig_space=opts.ig_space),
        occlusion_head=head,
        queue_size=max(64, opts.num_episodes * opts.calls),  # room for every request: the demo logs each one
    )


def _own_monitor(model: ModelSpec) -> LiveMonitor | None:
    """The failure monitor the bundled model ships (`ModelSpec.default_monitor`): the side channel scores every call
    of each episode with it, as `serve` does."""
    path = model.default_monitor()
    return None if path is None else LiveMonitor(monitor_file.load(path), path.name)


def run_demo(opts: DemoOptions, sink: RolloutSink | None = None) -> DemoResult:
    """Serves, drives (recording every step into `sink`), renders and scores; raises OSError when the side channel
    cannot create its run directory or the model's files are missing, ImportError when `--sim metaworld` lacks its
    extra, UnfitModel when the model's folder does not hold the chosen model or `occlusion-head` has no head that fits
    it."""
    t0 = time.time()
    if opts.sim == "metaworld":
        metaworld_sim.require_simulator()
    model = ModelSpec.demo(opts.bundled_model, opts.assets)
    try:
        policy = model.create()
    except ValueError as e:
        raise UnfitModel(f"--model {opts.model} (--sim {opts.sim}: {opts.bundled_model}): {e}") from None
    options = _side_channel_options(opts, model)
    demo = {
        "episodes": opts.num_episodes,
        "seed": opts.seed,
        "model": opts.bundled_model,
        "perturb": list(opts.perturb),
        "sim": opts.sim,
        **({"tasks": list(opts.tasks)} if opts.sim == "metaworld" else {}),
    }
    run_config = {**model.resolved().to_json(), "demo": demo}
    checkpoint = str(model.checkpoint)
    cam = None
    if opts.explain:
        monitor = _own_monitor(model)
        cam = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=checkpoint, monitor=monitor)
    # The demo explains every request: the drain at the end is the rest of the run's work, not a shutdown grace.
    server = start_server_in_thread(cam or policy, metadata=policy.metadata, drain_timeout=DRAIN_S)
    try:
        if opts.sim == "metaworld":
            episodes = run_metaworld_episodes(
                server.url,
                opts.num_episodes,
                seed=opts.seed,
                max_calls=opts.max_calls,
                execute=opts.execute,
                perturbations=opts.perturbations,  # type: ignore[arg-type]
                tasks=opts.tasks,
                image_size=METAWORLD_CAMERA_SIZE,
                sink=sink,
            )
        else:
            episodes = run_episodes(
                server.url,
                opts.num_episodes,
                seed=opts.seed,
                max_calls=opts.calls,
                execute=opts.execute,
                perturbations=opts.perturbations,  # type: ignore[arg-type]
                sink=sink,
            )
    finally:
        server.stop(timeout=DRAIN_S + 60)  # closes the side channel too, which drains its queue
    if cam is None:
        figures = {"episodes": len(episodes), "success_rate": quality.success_rate(episodes), "steps": 0, "maps": {}}
        return DemoResult(None, episodes, figures, {}, time.time() - t0)
    if cam.run_dir is None:
        raise OSError(f"the side channel could not create a run directory under {opts.out}; see the log")
    run_dir = cam.run_dir
    (run_dir / quality.EPISODES_FILE).write_text(json.dumps(episodes, indent=2))
    # Measured before rendering, so every rendered map carries its run's figures (`viz.evidence`).
    faithfulness = None
    if opts.faithfulness:
        faithfulness = evaluate_run(load_run(run_dir), policy.explainer, FaithfulnessOptions(randomize="llm"))
        (run_dir / REPORT_FILE).write_text(dumps(faithfulness, indent=2))
    reports = {}
    if opts.render:
        run = load_run(run_dir, load_arrays=False)
        for kind in opts.map_kinds:
            render_opts = RenderOptions(map=kind, videos=opts.videos, progress=False)
            result = render_run(run, default_render_dir(run_dir, kind), render_opts)
            if result.report is not None:
                reports[kind] = result.report
    size = METAWORLD_CAMERA_SIZE if opts.sim == "metaworld" else task.TaskConfig().image_size
    figures = quality.run_figures(run_dir, size)
    return DemoResult(run_dir, episodes, figures, reports, time.time() - t0, faithfulness)
