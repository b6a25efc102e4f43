"""Peak host memory and time of loading a LeRobot `model.safetensors` without torch (`load_safetensors_params`).

Writes a random float32 checkpoint in LeRobot's key names (`model.` prefix) at the full pi0.5 size (PaliGemma 2B,
the 300M action expert, SigLIP So400m: 3.6 B parameters, 14 GB) or at a smaller size, streamed one tensor at a time,
then loads it in a fresh process and prints, against the file's size: the growth of the process's resident-set
high-water mark (VmHWM) over its resident set just before loading (Python, NumPy, JAX imported), the resident
growth once loaded, and the load time. The file's pages in the page cache are not the process's (only mapped pages
count in its RSS), so the figure is what loading itself holds.

    python benchmarks/bench_lerobot_weights.py                  # full size: needs ~15 GB of disk and ~17 GB of RAM
    python benchmarks/bench_lerobot_weights.py --size small     # ~330 MB, as tests/model/test_safetensors_weights.py
    python benchmarks/bench_lerobot_weights.py --keep PATH      # write to PATH and keep it (default: a temp dir)
    python benchmarks/bench_lerobot_weights.py --json           # one JSON line (the memory test reads it)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from openpi_cam.model.config import GemmaConfig, Pi0Config, SiglipConfig
from openpi_cam.model.safetensors_weights import torch_shapes, write_safetensors

SIZES = {
    "full": Pi0Config(pi05=True),
    # Same structure with fewer and narrower layers; its largest tensor (the embedding) is a third of the file, as a
    # full-size one's largest stacked leaf is a third of its model.
    "small": Pi0Config(
        gemma=GemmaConfig(
            width=1024, depth=2, mlp_dim=4096, num_heads=8, num_kv_heads=1, head_dim=128, vocab_size=32_768
        ),
        expert=GemmaConfig(width=512, depth=2, mlp_dim=2048, num_heads=8, num_kv_heads=1, head_dim=128, vocab_size=0),
        siglip=SiglipConfig(width=1152, depth=2, mlp_dim=4304, num_heads=16, out_dim=1024),
        pi05=True,
    ),
}

LOAD_SCRIPT = r"""
import json, sys, time
from openpi_cam.model.safetensors_weights import load_safetensors_params

def status(field):  # bytes; VmHWM is this process's peak resident set since exec
    return int(open("/proc/self/status").read().split(field + ":")[1].split()[0]) * 1024

before = status("VmRSS")
start = time.perf_counter()
params, _ = load_safetensors_params(sys.argv[1], dtype="float32")
seconds = time.perf_counter() - start
print(json.dumps({"peak_growth": status("VmHWM") - before, "resident_growth": status("VmRSS") - before,
                  "baseline": before, "seconds": seconds}))
"""


def write_random(path: Path, cfg: Pi0Config, seed: int = 0) -> int:
    """A random float32 checkpoint of `cfg` in LeRobot's keys, one tensor in memory at a time; returns its size."""
    rng = np.random.default_rng(seed)
    shapes = torch_shapes(cfg)
    write_safetensors(path, shapes, "float32", lambda key: rng.random(shapes[key], np.float32) - np.float32(0.5))
    return sum(math.prod(s) * 4 for s in shapes.values())


def measure(path: Path) -> dict:
    """Loads `path` in a fresh process; its memory figures and load time."""
    out = subprocess.run([sys.executable, "-c", LOAD_SCRIPT, str(path)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=sorted(SIZES), default="full")
    parser.add_argument("--keep", type=Path, default=None, help="write the checkpoint here and keep it")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON line")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.keep or Path(tmp) / "model.safetensors"
        start = time.perf_counter()
        tensor_bytes = write_random(path, SIZES[args.size])
        written = time.perf_counter() - start
        file_bytes = os.path.getsize(path)
        result = measure(path)
    if args.json:
        print(json.dumps({**result, "file_bytes": file_bytes, "write_seconds": written}))
        return
    print(f"{args.size}: {file_bytes / 1e9:.2f} GB file ({tensor_bytes / 4e9:.2f} B float32 parameters), written in "
          f"{written:.0f} s; {platform.machine()}, {os.cpu_count()} CPUs")  # fmt: skip
    print(f"load: {result['seconds']:.1f} s; peak RSS growth {result['peak_growth'] / 1e9:.2f} GB = "
          f"{result['peak_growth'] / file_bytes:.3f} x the file; resident after {result['resident_growth'] / 1e9:.2f} "
          f"GB = {result['resident_growth'] / file_bytes:.3f} x; baseline before loading "
          f"{result['baseline'] / 1e9:.2f} GB")  # fmt: skip


if __name__ == "__main__":
    main()
