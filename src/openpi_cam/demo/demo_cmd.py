"""`openpi-cam demo`: the whole system on the bundled tiny model, on CPU, in about a minute.

Serves the bundled pi0-FAST on loopback with the Grad-CAM side channel on for every inference, drives simulated
reaching episodes through a websocket client exactly as a robot would, then renders the logged heatmaps and scores
them against the ground-truth target boxes the client sent along (`cam_extra/target_box`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Literal

from openpi_cam.demo import bundled, sim
from openpi_cam.demo.client import PolicyClient
from openpi_cam.viz.stats import MAP_KINDS, MAP_LABELS

EPISODES_FILE = "demo_episodes.json"


def run_episodes(url: str, episodes: int, *, seed: int, max_calls: int, execute: int) -> list[dict]:
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


def demo(
    out: Path = Path("demo_runs"),
    episodes: int = 3,
    max_calls: int = 6,
    execute: int = 5,
    seed: int = 0,
    target: Literal["action-token", "all-action-tokens", "chunk"] = "chunk",
    render: bool = True,
    videos: bool = False,
    assets: Path = bundled.ASSETS,
) -> int:
    """Run the bundled model end to end: server + Grad-CAM side channel + simulated robot + rendered report.

    Args:
        out: directory for the CAM run (a new run directory is created inside).
        episodes: simulated reaching episodes to drive.
        max_calls: inference calls per episode at most.
        execute: actions of each returned chunk the robot executes before asking again.
        seed: first episode seed (episode i uses seed + i).
        target: what Grad-CAM explains for each inference.
        render: write overlays and the HTML report after the run.
        videos: also write MP4/GIF videos (needs the viz extra).
        assets: directory holding the model (checkpoint/) and its tokenizers (default: the bundled ones).
    """
    from openpi_cam.cam.wrapper import CAMOptions, wrap_policy_with_cam
    from openpi_cam.demo import quality
    from openpi_cam.serving.server import start_server_in_thread

    t0 = time.time()
    policy = bundled.create_demo_policy(assets=assets)
    options = CAMOptions(every_k=1, cam_dir=out, save_frames="both", target=target, queue_size=64)
    run_config = {"config": bundled.DEMO_CONFIG.name, "demo": {"episodes": episodes, "seed": seed}}
    cam = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=str(assets / bundled.CHECKPOINT.name))
    server = start_server_in_thread(cam, metadata=policy.metadata)
    try:
        results = run_episodes(server.url, episodes, seed=seed, max_calls=max_calls, execute=execute)
    finally:
        server.stop()  # closes the CAM wrapper too, which drains the Grad-CAM queue
    run_dir = cam.run_dir
    if run_dir is None:
        print("demo: the Grad-CAM side channel could not create its run directory; see the log")
        return 1
    (run_dir / EPISODES_FILE).write_text(json.dumps(results, indent=2))
    reports = {}
    if render:
        from openpi_cam.viz.render import default_render_dir, render_cmd

        for kind in MAP_KINDS:
            render_cmd(run_dir, map=kind, videos=videos, progress=False)
            reports[kind] = default_render_dir(run_dir, kind) / "index.html"
    figures = quality.run_figures(run_dir)
    wins = sum(r["success"] for r in results)
    print(f"\nopenpi-cam demo: {wins}/{len(results)} episodes reached their block in {time.time() - t0:.0f}s")
    print(f"pointing game over {figures['steps']} steps (the base camera's map peaks on the named block):")
    for kind, f in figures["maps"].items():
        print(f"  {MAP_LABELS[kind]:>13}: {f['pointing_game']:.0%} (chance {f['pointing_chance']:.0%})")
    print(f"run directory: {run_dir}")
    for kind, report in reports.items():
        if report.exists():
            print(f"open the {MAP_LABELS[kind]} report: {report}")
    return 0
