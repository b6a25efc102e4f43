"""Where the test suite's time goes: the README's test command run cold, with every XLA compilation of every process
it starts (xdist workers, `serve` / `explain` / `faithfulness` subprocesses, Ray workers) recorded.

    python benchmarks/suite_census.py [--out /tmp/census] [-- <pytest arguments>]   (`-- --full`: both tiers)

A fresh, empty JAX compilation cache is used, as in a fresh clone. Each Python process imports a `sitecustomize`
placed on PYTHONPATH that listens to JAX's compile-duration event (`jax.monitoring`) and appends (test, program,
seconds) to a file of its own. Prints the wall and CPU time of the run, the compilation time of the workers and of
the processes they start, and the programs and test files that compile the most. A compilation that loads its
program from the persistent cache also reports (its load time); those under `--hit-below` seconds are counted as
cache hits.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import resource
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Runs at start-up in every Python process of the run. It imports no JAX and changes no logging: it listens to JAX's
# own compile-duration event once JAX is imported.
SITECUSTOMIZE = r"""
import importlib.abc, importlib.util, json, os, sys

_OUT = os.environ.get("SUITE_CENSUS_DIR")
_EVENT = "/jax/core/compile/backend_compile_duration"
# pytest sets PYTEST_CURRENT_TEST while a test (or its fixtures) runs: a process that starts with it set was started
# by a test; the pytest processes themselves start before any test.
_WORKER = "PYTEST_CURRENT_TEST" not in os.environ
_file = []


def _record(event, seconds, **kwargs):
    if event != _EVENT:
        return
    if not _file:
        _file.append(open(os.path.join(_OUT, f"{os.getpid()}.jsonl"), "a"))
    test = os.environ.get("PYTEST_CURRENT_TEST", "")
    row = {"test": test, "program": kwargs.get("fun_name", "?"), "seconds": seconds, "worker": _WORKER}
    _file[0].write(json.dumps(row) + "\n")
    _file[0].flush()


class _ListenOnImport(importlib.abc.MetaPathFinder):
    # Registers the listener when JAX's monitoring module is first imported, so that processes that never import
    # JAX (and import-time checks) see no difference.
    def find_spec(self, name, path, target=None):
        if name != "jax._src.monitoring":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            module.register_event_duration_secs_listener(_record)

        spec.loader.exec_module = exec_module
        return spec


if _OUT:
    sys.meta_path.insert(0, _ListenOnImport())
"""


def run_suite(out: pathlib.Path, pytest_args: list[str]) -> tuple[float, float, int]:
    """Runs pytest cold with the census hook -> (wall seconds, CPU seconds of all children, exit code). The hook lives
    in the census folder; the compilation cache is kept (and named) for a warm rerun."""
    hook = out / "hook"
    hook.mkdir(exist_ok=True)
    (hook / "sitecustomize.py").write_text(SITECUSTOMIZE)
    cache = tempfile.mkdtemp(prefix="suite-census-jax-cache-")
    print(f"cold JAX compilation cache: {cache} (rerun warm with JAX_COMPILATION_CACHE_DIR={cache})", flush=True)
    env = os.environ | {
        "SUITE_CENSUS_DIR": str(out),
        "JAX_COMPILATION_CACHE_DIR": cache,
        "PYTHONPATH": os.pathsep.join(p for p in (str(hook), os.environ.get("PYTHONPATH", "")) if p),
    }
    start = time.perf_counter()
    code = subprocess.call([sys.executable, "-m", "pytest", "-q", *pytest_args], cwd=ROOT, env=env)
    wall = time.perf_counter() - start
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, usage.ru_utime + usage.ru_stime, code


def summarize(out: pathlib.Path, hit_below: float, top: int) -> None:
    rows = [json.loads(line) for f in sorted(out.glob("*.jsonl")) for line in f.read_text().splitlines()]
    compiled = [r for r in rows if r["seconds"] >= hit_below]
    for label, worker in (("pytest workers", True), ("processes the tests start", False)):
        part = [r for r in compiled if r["worker"] == worker]
        hits = sum(1 for r in rows if r["worker"] == worker and r["seconds"] < hit_below)
        seconds = sum(r["seconds"] for r in part)
        print(f"{label}: {len(part)} compilations, {seconds:,.0f} s; {hits} cache hits or trivial programs")
    by_program, by_file = collections.Counter(), collections.Counter()
    count = collections.Counter()
    for r in compiled:
        by_program[r["program"]] += r["seconds"]
        count[r["program"]] += 1
        by_file[r["test"].split("::")[0] or "(outside a test)"] += r["seconds"]
    print(f"\nprograms compiling the most (of {len(by_program)}):")
    for program, seconds in by_program.most_common(top):
        print(f"  {seconds:8,.0f} s  {count[program]:4d}x  {program}")
    print("\ntest files compiling the most (their subprocesses included):")
    for name, seconds in by_file.most_common(top):
        print(f"  {seconds:8,.0f} s  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=pathlib.Path, default=None, help="census folder (default: a new temp folder)")
    parser.add_argument("--hit-below", type=float, default=0.5, help="seconds under which a compilation is a hit")
    parser.add_argument("--top", type=int, default=15)
    parser.add_argument("--summarize-only", action="store_true", help="summarize an existing --out folder")
    args, pytest_args = parser.parse_known_args()
    pytest_args = [a for a in pytest_args if a != "--"]
    out = args.out or pathlib.Path(tempfile.mkdtemp(prefix="suite-census-"))
    if not args.summarize_only:
        out.mkdir(parents=True, exist_ok=True)
        wall, cpu, code = run_suite(out, pytest_args)
        print(f"\npytest exit code {code}; wall {wall / 60:.1f} min, CPU {cpu:,.0f} s ({cpu / wall:.2f} cores busy)")
        print(f"machine: {os.cpu_count()} CPUs; census in {out}\n")
    summarize(out, args.hit_below, args.top)


if __name__ == "__main__":
    main()
