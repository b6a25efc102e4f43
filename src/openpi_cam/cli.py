"""`openpi-cam` command line: one subcommand per job, each a tyro-parsed function.

Subcommands are imported lazily so that `openpi-cam --help` and light commands stay fast.
"""

from __future__ import annotations

import importlib
import sys

# name -> (module, function, one-line help). Each function takes tyro-parsable arguments.
COMMANDS: dict[str, tuple[str, str, str]] = {
    "serve": ("openpi_cam.serving.serve_cmd", "serve", "serve a pi0-FAST checkpoint over websockets"),
    "demo": ("openpi_cam.demo.demo_cmd", "demo", "run the bundled tiny model end to end with Grad-CAM on"),
    "golden": ("openpi_cam.golden", "golden_cmd", "check the model against an upstream golden folder"),
    "cam-index": ("openpi_cam.cam.reader", "cam_index_cmd", "rebuild a CAM run's manifest from its step files"),
    "render": ("openpi_cam.viz.render", "render_cmd", "overlays, videos and an HTML report for a CAM run"),
    "stats": ("openpi_cam.viz.stats", "stats_cmd", "per-step, per-camera attention statistics of a CAM run"),
    "explain": ("openpi_cam.cam.explain", "explain_cmd", "compute Grad-CAM offline for recorded observations"),
}


def _usage() -> str:
    lines = ["usage: openpi-cam COMMAND [--help] [ARGS...]", "", "commands:"]
    lines += [f"  {name:<10} {help_}" for name, (_, _, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"openpi-cam: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        raise SystemExit(2)
    module_name, func_name, _ = COMMANDS[name]
    import tyro

    func = getattr(importlib.import_module(module_name), func_name)
    result = tyro.cli(func, args=rest, prog=f"openpi-cam {name}")
    if isinstance(result, int) and result != 0:
        raise SystemExit(result)
