"""Shared fixtures, and the rule that CI runs every test it claims to run.

Reference data lives in `../shared/golden` beside the repo (read-only, never copied here). The expensive parts (a
model's compiled programs) are built once per session:

- `golden_dir`: the upstream goldens folder.
- `tiny_fast_model`: upstream's tiny pi0-FAST (`tiny_pi0_fast`), float32, in the layout it is served with.
- `tiny_policy_files` / `tiny_droid_policy`: upstream's tiny pi0-FAST DROID policy (`tiny_policy_droid`), float32. Its
  random model never writes `Action: `, so every response is the same fallback chunk: use it where upstream parity is
  the point, never for "same actions" checks.
- `demo_policy`: the bundled demo model (float32), whose actions depend on the observation: use it wherever actions
  must differ between observations.
- `demo_observations`: distinct demo-robot observations, each with its own actions under `demo_policy`.
- `demo_pi05_policy`: the bundled pi0.5 (float32), one per module (its noise stream starts afresh in each).
- `demo_pi05_lerobot`: the bundled pi0.5 exported as a LeRobot policy folder.

Under `CI=true` a skipped test fails (see `pytest_runtest_makereport`), so a missing dependency cannot pass silently.

Two tiers (see `SLOW`): the README's test command runs the fast tier, `-m slow` the rest; CI runs both.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from command_inputs import explained_dataset, served_run
from demo_inputs import demo_observation
from paths import GOLDEN_DIR

# Tests that may skip under CI=true, with the reason each is allowed to: node id -> reason. Keep it empty unless a
# test truly cannot run on the CI machine.
ALLOWED_CI_SKIPS: dict[str, str] = {}


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Any:
    report = yield
    if _in_ci() and report.skipped and not hasattr(report, "wasxfail") and item.nodeid not in ALLOWED_CI_SKIPS:
        reason = report.longrepr[-1] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"skipped under CI=true, which runs every test: {reason}"
    return report


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector: pytest.Collector) -> Any:
    # A module-level `pytest.skip(..., allow_module_level=True)` skips at collection, before any test report exists.
    report = yield
    if _in_ci() and report.skipped and collector.nodeid not in ALLOWED_CI_SKIPS:
        reason = report.longrepr[-1] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"collection skipped under CI=true, which runs every test: {reason}"
    return report


# The fast tier checks every behaviour once. The slow tier holds what repeats a computation the fast tier already
# checks, under another configuration or along another path (a second layout, remat, bfloat16, a second device,
# batched rows, larger occlusion regions, re-scoring, other side-channel targets and LRP entry points, pi0 beside
# pi0.5, the second golden case, the golden pi0's replay, the demo end to end with every kind), and the long runs of
# extra processes (hostile clients, stalled peers at SIGTERM, the training script, `explain` in a fresh process,
# Ray's retries, every README command as written) or of compilation counting, and the tests that step the Meta-World
# simulator. The fast tier leaves it out unless tests are named by node id, `-m` selects, or `--full` asks for
# everything.
SLOW = "slow"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--full", action="store_true", help="run the slow tier too (CI runs it as `-m slow`)")


def _fast_tier_only(config: pytest.Config) -> bool:
    named = any("::" in arg for arg in config.args)
    return not (config.option.markexpr or config.getoption("--full") or named)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not _fast_tier_only(config):
        return
    fast, slow = [], []
    for item in items:
        (slow if item.get_closest_marker(SLOW) else fast).append(item)
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = fast


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    if _fast_tier_only(config):
        terminalreporter.write_line(
            "fast tier: the slow tier was left out (`python -m pytest -q -m slow` runs it; CI runs both)"
        )


# Compiling XLA programs is most of the suite's CPU time, and the same programs are compiled again by every process
# that builds the same model: the subprocesses the tests start (`serve`, `explain`, `faithfulness`, scripts), each
# xdist worker, and this process after `_bounded_compiled_programs` drops its in-memory caches. JAX's persistent
# compilation cache lets them load a program instead. It lives in pytest's cache directory (a fresh clone starts
# cold; `pytest --cache-clear` empties it), or in a directory of this run only when the cache plugin is off. The
# environment carries it to subprocesses and workers. A program loaded from it still fires JAX's compile event and
# log line, so tests that count compilations count the same; its key covers the program, the jax version and the
# XLA flags, so a stale entry is never used.
JAX_CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"
# Past this size the cache is emptied at the start of a run (entries of earlier code versions are never evicted).
MAX_JAX_CACHE_BYTES = 2 << 30


def _jax_compilation_cache(config: pytest.Config) -> Path:
    cache = getattr(config, "cache", None)
    if cache is None:
        path = Path(tempfile.mkdtemp(prefix="jax-compilation-cache-"))
        config.add_cleanup(lambda: shutil.rmtree(path, ignore_errors=True))
        return path
    path = cache.mkdir("jax-compilation-cache")
    if sum(f.stat().st_size for f in path.iterdir() if f.is_file()) > MAX_JAX_CACHE_BYTES:
        shutil.rmtree(path, ignore_errors=True)
        path = cache.mkdir("jax-compilation-cache")
    return path


# Every program is cached, however small or quick to compile (the defaults keep only those over a second).
JAX_CACHE_SETTINGS = {"jax_persistent_cache_min_compile_time_secs": 0, "jax_persistent_cache_min_entry_size_bytes": 0}


def pytest_configure(config: pytest.Config) -> None:
    # Already set: by the user, or by the xdist controller for its workers (which inherit its environment).
    if JAX_CACHE_ENV not in os.environ:
        os.environ[JAX_CACHE_ENV] = str(_jax_compilation_cache(config))
    for name, value in JAX_CACHE_SETTINGS.items():
        os.environ.setdefault(name.upper(), str(value))
    if "jax" in sys.modules:  # imported before this hook, so it read its settings from the environment already
        import jax

        jax.config.update(JAX_CACHE_ENV.lower(), os.environ[JAX_CACHE_ENV])
        for name, value in JAX_CACHE_SETTINGS.items():
            jax.config.update(name, type(value)(os.environ[name.upper()]))


# Every compiled XLA program keeps ~3 memory mappings per kernel (one demo inference and its explanation: ~1,100), and
# one process running the whole suite compiles thousands of programs: past Linux's default vm.max_map_count (65,530)
# the next compilation dies with a segmentation fault inside XLA (seen at ~80,000 projected mappings). Dropping the
# compiled-program caches between tests once the count is high frees them; the programs still in use recompile.
MAX_MAPPINGS_BEFORE_CLEARING = 40_000


def _mappings() -> int:
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux: no such limit to stay under
        return 0


@pytest.fixture(autouse=True)
def _logging_as_it_was() -> Any:
    """Commands run in process (`serve`, `cli.main`) point the root logger at the stderr of their call, here a test's
    captured one: put it back, or a later test's log line is written to a closed stream."""
    root, ours = logging.getLogger(), logging.getLogger("openpi_cam")
    handlers, level, our_level = list(root.handlers), root.level, ours.level
    yield
    root.handlers[:], root.level = handlers, level
    ours.setLevel(our_level)


@pytest.fixture(autouse=True)
def _bounded_compiled_programs() -> Any:
    yield
    if _mappings() > MAX_MAPPINGS_BEFORE_CLEARING:
        import gc

        import jax

        jax.clear_caches()
        gc.collect()


@pytest.fixture(scope="session")
def golden_dir() -> Path:
    if not GOLDEN_DIR.is_dir():
        pytest.skip(f"upstream goldens not found at {GOLDEN_DIR} (expected ../shared/golden beside the repo)")
    return GOLDEN_DIR


@pytest.fixture(scope="session")
def tiny_fast_model(golden_dir: Path):
    """`tiny_pi0_fast` with its `Pi0FASTConfig` (action_dim 8, horizon 10, max_token_len 48), float32."""
    from openpi_cam.model.pi0_fast import Pi0FAST

    return Pi0FAST.from_checkpoint(
        golden_dir / "tiny_pi0_fast" / "checkpoint" / "params",
        dtype="float32",
        action_dim=8,
        action_horizon=10,
        max_token_len=48,
    )


@dataclasses.dataclass(frozen=True)
class TinyPolicyFiles:
    checkpoint: Path
    paligemma_tokenizer: Path
    fast_tokenizer: Path

    def create_kwargs(self) -> dict:
        """Keyword arguments of `create_policy` (besides config and checkpoint) for these files."""
        return {
            "paligemma_tokenizer": self.paligemma_tokenizer,
            "fast_tokenizer": self.fast_tokenizer,
            "dtype": "float32",
        }


@pytest.fixture(scope="session")
def tiny_policy_files(golden_dir: Path) -> TinyPolicyFiles:
    root = golden_dir / "tiny_policy_droid"
    return TinyPolicyFiles(
        checkpoint=root / "checkpoint",
        paligemma_tokenizer=root / "paligemma_tokenizer_tiny.model",
        fast_tokenizer=root / "fast_tokenizer",
    )


@pytest.fixture(scope="session")
def tiny_droid_policy(tiny_policy_files: TinyPolicyFiles):
    from openpi_cam.policies.policy import create_policy

    return create_policy("pi0_fast_droid", tiny_policy_files.checkpoint, **tiny_policy_files.create_kwargs())


@pytest.fixture(scope="session")
def demo_policy():
    from openpi_cam.checkpoints.model_spec import create_demo_policy

    return create_demo_policy()


@pytest.fixture(scope="module")
def demo_pi05_policy():
    """The bundled pi0.5 (float32), one per test module: it draws its noise from the policy's own rng stream, which
    each module then starts afresh."""
    from openpi_cam.checkpoints.model_spec import create_demo_policy

    return create_demo_policy(model="pi05")


@pytest.fixture(scope="session")
def demo_observations(demo_policy) -> list[dict[str, Any]]:
    """Four demo observations whose actions under `demo_policy` are pairwise different (asserted here, so that every
    "each got its own answer" check built on them can fail)."""
    observations = [demo_observation(seed) for seed in range(4)]
    actions = [demo_policy.infer(obs)["actions"] for obs in observations]
    for i in range(len(actions)):
        for j in range(i):
            assert not np.array_equal(actions[i], actions[j]), f"demo observations {i} and {j} give the same actions"
    return observations


@pytest.fixture(scope="session")
def demo_pi05_lerobot(tmp_path_factory) -> Path:
    """The bundled pi0.5 exported as a LeRobot policy folder (`openpi-cam export --to lerobot --config
    demo_reach_pi05`): a LeRobot checkpoint that has learned the demo task, with the demo datasets' feature names."""
    from openpi_cam.checkpoints.model_spec import ModelSpec
    from openpi_cam.cli import export

    out = tmp_path_factory.mktemp("lerobot") / "demo_pi05"
    assert export.main(out, ModelSpec(config="demo_reach_pi05")) == 0
    return out


@pytest.fixture(scope="session")
def served_run_dir(tmp_path_factory, demo_policy) -> Path:
    """A run the side channel wrote for the bundled pi0-FAST (two requests, defaults, raw and model frames): read by
    the command-line tests, never written (copy it first)."""
    return served_run(tmp_path_factory.mktemp("served_run"), demo_policy)


@pytest.fixture(scope="session")
def demo_maps_dir(tmp_path_factory) -> Path:
    """`explain-dataset` of the demo dataset's first two episodes with the bundled model: read by the command-line
    tests, never written (copy it first)."""
    return explained_dataset(tmp_path_factory.mktemp("demo_maps") / "demo.maps")
