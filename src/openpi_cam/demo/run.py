"""The whole system on a bundled tiny model: serve it on loopback with the side channel explaining every
inference, drive simulated episodes (the reaching task, or Meta-World's button press) through a websocket client
exactly as a robot would, render the maps and score them against the ground-truth boxes the client sent along
(`cam_extra/target_box`)."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from typing import Any, Literal

from openpi_cam.cam.faithfulness_run import FaithfulnessOptions, evaluate_run
from openpi_cam.cam.run_evidence import REPORT_FILE
from openpi_cam.cam.run_format import dumps, load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.demo import bundled, metaworld_loop, quality, sim
from openpi_cam.demo.client import PolicyClient
from openpi_cam.demo.metaworld_sim import Perturbation
from openpi_cam.policies.model_spec import ModelSpec
from openpi_cam.serving.server import start_server_in_thread
from openpi_cam.viz.render import RenderOptions, default_render_dir, render_run
from openpi_cam.vocabulary import MAP_KINDS, Baseline, IgSpace, MapKind, MapOptions, Target


def run_episodes(url: str, episodes: int, *, seed: int, max_calls: int, execute: int) -> list[dict[str, Any]]:
    """Closed loop over the server: observe, infer a chunk, execute its first `execute` actions, repeat."""
    results = []
    with PolicyClient(url) as client:
        for e in range(episodes):
            episode = sim.new_episode(seed + e)
            calls = 0
            while calls < max_calls and not episode.success:
                reply = client.infer(bundled.client_observation(episode.observe(), episode.scene))
                calls += 1
                episode.execute(reply["actions"], execute)
            results.append(
                {
                    "seed": seed + e,
                    "prompt": episode.observe().prompt,
                    "success": bool(episode.success),
                    "calls": calls,
                    "final_distance": float(((episode.state - episode.goal) ** 2).sum() ** 0.5),
                }
            )
    return results


def run_metaworld_episodes(
    url: str,
    episodes: int,
    *,
    seed: int,
    max_calls: int,
    execute: int,
    perturbations: tuple[Perturbation, ...],
    sink: metaworld_loop.RolloutSink | None = None,
) -> list[dict[str, Any]]:
    """Meta-World episodes over the server: episode i is the scene of seed + i // P under the (i mod P)-th of the P
    perturbations, so every perturbation meets the same scenes."""
    with PolicyClient(url) as client:
        return [
            metaworld_loop.run_episode(
                client.infer,
                seed + e // len(perturbations),
                perturbations[e % len(perturbations)],
                max_calls=max_calls,
                execute=execute,
                sink=sink,
            )
            for e in range(episodes)
        ]


DRAIN_S = 3600.0  # how long the end of a demo run may spend explaining requests still queued


@dataclasses.dataclass(frozen=True)
class DemoOptions:
    """What `openpi-cam demo` runs (its flags)."""

    # the folder in which the CAM run directory is created.
    out: pathlib.Path = pathlib.Path("demo_runs")
    # which simulator the robot lives in: the synthetic reaching task, or Meta-World's button press (MuJoCo; needs
    # `pip install -e ".[metaworld]"`), served by its own bundled pi0.5.
    sim: Literal["reach", "metaworld"] = "reach"
    # simulated episodes to drive.
    num_episodes: int = 3
    # inference calls per episode at most (default: 6 for reach, 30 for metaworld).
    max_calls: int | None = None
    # actions of each returned chunk the robot executes before asking again.
    execute: int = 5
    # the first episode's seed (episode i uses seed + i).
    seed: int = 0
    # what the maps explain for each inference.
    target: Target = "chunk"
    # write overlays and the HTML report of each map kind after the run.
    render: bool = True
    # with `render`, also write an MP4 and a GIF per episode.
    videos: bool = True
    # which bundled model serves the reaching task: the tiny pi0-FAST or the tiny pi0.5 (metaworld has its pi0.5).
    model: Literal["pi0_fast", "pi05"] = "pi0_fast"
    # metaworld: what the episodes run under, in turn (`kind=strength`: clean, colour=DEGREES, light=FACTOR,
    # shift=METRES, distractors=N, prompt=TEXT; `demo.metaworld_sim.Perturbation`): episode i under the (i mod P)-th.
    perturb: tuple[str, ...] = ("clean",)
    # the folder holding the model (checkpoint/) and its tokenizers; default: the bundled ones of `model`.
    assets: pathlib.Path | None = None
    # which map kinds the side channel computes (all four, so that the faithfulness table compares them).
    maps: tuple[MapKind, ...] = MAP_KINDS
    # re-score every step afterwards and report how faithful each map kind is.
    faithfulness: bool = True
    # the frame `ig` starts from and `occlusion` (and the faithfulness deletion) paints with.
    baseline: Baseline = MapOptions.baseline
    # where the `ig` path runs: between the SigLIP tokens of the baseline frame and the frame, or between the frames'
    # pixels (through SigLIP).
    ig_space: IgSpace = MapOptions.ig_space

    @property
    def calls(self) -> int:
        return self.max_calls or (metaworld_loop.MAX_CALLS if self.sim == "metaworld" else 6)

    @property
    def perturbations(self) -> tuple[Perturbation, ...]:
        return tuple(Perturbation.parse(p) for p in self.perturb)

    def __post_init__(self) -> None:
        if not self.perturb:
            raise ValueError("--perturb needs at least one perturbation (clean: none)")
        if self.sim == "reach" and self.perturb != ("clean",):
            raise ValueError("--perturb is for --sim metaworld")
        self.perturbations  # noqa: B018  (refused as the flags are parsed)


@dataclasses.dataclass
class DemoResult:
    run_dir: pathlib.Path
    episodes: list[dict[str, Any]]
    figures: dict[str, Any]
    reports: dict[str, pathlib.Path]
    seconds: float
    faithfulness: dict[str, Any] | None = None  # `cam.faithfulness_run.evaluate_run`'s report


def run_demo(opts: DemoOptions, sink: metaworld_loop.RolloutSink | None = None) -> DemoResult:
    """Serves, drives (recording every Meta-World step into `sink`), renders and scores; raises OSError when the side
    channel cannot create its run directory."""
    t0 = time.time()
    model = ModelSpec.demo("metaworld" if opts.sim == "metaworld" else opts.model, opts.assets)
    policy = model.create()
    options = CAMOptions(
        every_k=1,
        cam_dir=opts.out,
        save_frames="both",
        target=opts.target,
        maps=opts.maps,
        map_options=MapOptions(baseline=opts.baseline, ig_space=opts.ig_space),
        queue_size=max(64, opts.num_episodes * opts.calls),  # room for every request: the demo logs each one
    )
    demo = {"episodes": opts.num_episodes, "seed": opts.seed, "model": opts.model, "sim": opts.sim}
    if opts.sim == "metaworld":
        demo |= {"perturb": list(opts.perturb)}
    run_config = {**model.resolved().to_json(), "demo": demo}
    cam = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=str(model.checkpoint))
    # The demo explains every request: the drain at the end is the rest of the run's work, not a shutdown grace.
    server = start_server_in_thread(cam, metadata=policy.metadata, close_timeout=DRAIN_S)
    try:
        if opts.sim == "metaworld":
            episodes = run_metaworld_episodes(
                server.url,
                opts.num_episodes,
                seed=opts.seed,
                max_calls=opts.calls,
                execute=opts.execute,
                perturbations=opts.perturbations,
                sink=sink,
            )
        else:
            episodes = run_episodes(
                server.url, opts.num_episodes, seed=opts.seed, max_calls=opts.calls, execute=opts.execute
            )
    finally:
        server.stop(timeout=DRAIN_S + 60)  # closes the side channel too, which drains its queue
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
        for kind in options.maps:
            render_opts = RenderOptions(map=kind, videos=opts.videos, progress=False)
            result = render_run(run, default_render_dir(run_dir, kind), render_opts)
            if result.report is not None:
                reports[kind] = result.report
    return DemoResult(run_dir, episodes, quality.run_figures(run_dir), reports, time.time() - t0, faithfulness)
