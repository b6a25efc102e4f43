"""`openpi-cam stats` and `render` read run directories only: they must not import JAX (seconds of start-up, and a
viewer must work where no accelerator stack is installed). Checked on the interpreter's own import log
(`python -X importtime`) of the real commands, run in a fresh process on a run written by CAMLogger."""

from __future__ import annotations

import pathlib
import re
import subprocess
import sys

import numpy as np

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.run_format import StepRecord

CAMERA = "base_0_rgb"
# One line per imported module: "import time: <self us> | <cumulative us> | <indent><module>".
_IMPORT_LINE = re.compile(r"^import time:\s+\d+ \|\s+\d+ \| (\s*)(\S+)$")


def _imported(args: list[str], cwd: pathlib.Path) -> list[str]:
    """The modules `python -X importtime -m openpi_cam ARGS` imports, after checking the command succeeded."""
    result = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "openpi_cam", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    modules = [m.group(2) for line in result.stderr.splitlines() if (m := _IMPORT_LINE.match(line))]
    assert "openpi_cam.cli" in modules  # the log is the command's, not an empty one
    return modules


def _jax_modules(modules: list[str]) -> list[str]:
    return [m for m in modules if m.split(".")[0] in ("jax", "jaxlib")]


def _run(cam_dir: pathlib.Path) -> pathlib.Path:
    """Two logged steps with gradnorm and ig maps, a model frame, IG's completeness and a spot check: what `render`
    draws and reads evidence from."""
    with CAMLogger(cam_dir, run_config={}, checkpoint="ckpt", options={}) as logger:
        for step in range(2):
            grid = np.zeros((4, 4), np.float32)
            grid[step, 2] = 1.0
            meta = {
                "target": "chunk",
                "score": -3.0 + step,
                "cameras": {CAMERA: {"valid": True, "grid": [4, 4], "span": [0, 16], "geometry": None}},
                "map_kinds": ["gradnorm", "ig"],
                "ig_completeness": {"relative_error": [0.01], "steps": 16},
                "check": {
                    "patches": 2,
                    "seed": step,
                    "cameras": {
                        CAMERA: {
                            "score": -3.0,
                            "top_patch": {"gradnorm": 2, "ig": 2},
                            "top_patch_drop": {"gradnorm": 0.5, "ig": 0.5},
                            "random_patches": [0, 9],
                            "random_patch_drops": [0.1, 0.0],
                        }
                    },
                },
            }
            maps = {"gradnorm": {CAMERA: grid}, "ig": {CAMERA: -grid}}
            frames = {CAMERA: np.full((64, 64, 3), 90, np.uint8)}
            record = StepRecord("c", step, 100.0 + step, maps, {}, frames, meta=meta)
            assert logger.log_step(record)
    return logger.run_dir


def test_stats_help_imports_no_jax(tmp_path):
    assert _jax_modules(_imported(["stats", "--help"], tmp_path)) == []


def test_stats_and_render_of_a_run_import_no_jax(tmp_path):
    run_dir = _run(tmp_path / "cam")
    modules = _imported(["stats", str(run_dir), "--map", "gradnorm", "--format", "json"], tmp_path)
    assert "openpi_cam.viz.stats" in modules and _jax_modules(modules) == []
    out = tmp_path / "render"
    args = ["render", str(run_dir), "--map", "ig", "--out", str(out), "--no-videos", "--no-progress"]
    modules = _imported([*args, "--tile-height", "64"], tmp_path)
    assert "openpi_cam.viz.render" in modules and _jax_modules(modules) == []
    assert (out / "index.html").is_file() and len(list((out / "panels").glob("*.png"))) == 2
