"""`openpi-cam` command line: one subcommand per module of this package, each a tyro-parsed function (a module with
a `route` instead names several commands and picks one from the arguments; a command named `GROUP WORD` is reached
as `openpi-cam GROUP WORD ...`, the word taken off its arguments).

Subcommand modules are imported only when chosen, so that `openpi-cam --help` stays fast.
"""

from __future__ import annotations

import importlib
import sys

import tyro

from openpi_cam.errors import BadFile

# name -> (module, one-line help). Each module defines `main`, a function with tyro-parsable arguments.
COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("openpi_cam.cli.serve", "serve a pi0-FAST, pi0 or pi0.5 checkpoint (OpenPI or LeRobot) over websockets"),
    "demo": ("openpi_cam.cli.demo", "a bundled tiny model end to end (reaching task or Meta-World), side channel on"),
    "golden": ("openpi_cam.cli.golden", "check the model against an upstream or LeRobot golden folder"),
    "explain": ("openpi_cam.cli.explain", "explain-dataset or explain-run, whichever SOURCE is"),
    "explain-run": ("openpi_cam.cli.explain_run", "maps for a recorded run (CAM run, PolicyRecorder records)"),
    "explain-dataset": ("openpi_cam.cli.explain_dataset", "a LeRobot dataset into a maps dataset (local or Ray)"),
    "faithfulness": ("openpi_cam.cli.faithfulness", "how faithful a run's or maps dataset's maps are, re-scored"),
    "render": ("openpi_cam.cli.render", "overlays, videos and an HTML report of a run or maps dataset"),
    "stats": ("openpi_cam.cli.stats", "per-step (per-frame) map statistics and views of a run or maps dataset"),
    "rebuild-manifest": ("openpi_cam.cli.rebuild_manifest", "rebuild a CAM run's manifest from its step files"),
    "export": ("openpi_cam.cli.export", "write an OpenPI pi0 / pi0.5 checkpoint as a LeRobot policy folder"),
    "monitor": ("openpi_cam.cli.monitor", "the failure monitor: `monitor fit` (a monitor for `serve --monitor`)"),
    "monitor fit": ("openpi_cam.cli.monitor_fit", "fit a failure monitor on labelled rollouts' maps datasets"),
    "head": ("openpi_cam.cli.head", "occlusion heads: `head fit` (the occlusion-head kind's head, per policy)"),
    "head fit": ("openpi_cam.cli.head_fit", "fit an occlusion head to a policy's own occlusion maps (maps datasets)"),
}
# Earlier names of commands, still accepted: alias -> command.
ALIASES: dict[str, str] = {"cam-index": "rebuild-manifest"}


def _usage() -> str:
    lines = ["usage: openpi-cam COMMAND [--help] [ARGS...]", "", "commands:"]
    width = max(map(len, COMMANDS)) + 2
    lines += [f"  {name:<{width}}{help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return
    name, rest = ALIASES.get(argv[0], argv[0]), argv[1:]
    if name not in COMMANDS:
        print(f"openpi-cam: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        raise SystemExit(2)
    module = importlib.import_module(COMMANDS[name][0])
    if hasattr(module, "route"):  # a name for several commands: the arguments say which one takes them
        routed = module.route(rest)
        if routed is None or rest[:1] in (["-h"], ["--help"]):
            print(module.USAGE)
            raise SystemExit(0 if rest[:1] in (["-h"], ["--help"]) else 2)
        if routed.startswith(f"{name} "):
            rest = rest[1:]
        name, module = routed, importlib.import_module(COMMANDS[routed][0])
    try:
        result = tyro.cli(module.main, args=rest, prog=f"openpi-cam {name}")
    except BadFile as e:  # a user's file its library could not read: named in one line, wherever it was read
        print(f"openpi-cam {name}: {e}", file=sys.stderr)
        raise SystemExit(1) from None
    if isinstance(result, int) and result != 0:
        raise SystemExit(result)
