"""Every command that reads a user's file reports a damaged one in one line naming the file, and exits non-zero
without a traceback: safetensors weights and normaliser statistics, JSON configs and processor files, norm stats,
SentencePiece and FAST tokenizer files, npz step files and golden cases, PolicyRecorder records, parquet data,
episode metadata and maps shards, and MP4 videos, each truncated, replaced by garbage bytes or (JSON) holding another
type, fed to each command that reads that file.

The commands run in process (`openpi_cam.cli.main`), so an exception the command does not turn into its one line
fails the test with its traceback. The damaged copies link every other file to the original."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from command_inputs import DEMO_DATASET, damaged_copy
from demo_inputs import demo_observation
from paths import GOLDEN_DIR
from shared_copies import edit_json, writable_copy

from openpi_cam import cli
from openpi_cam.policies import demo_reach

LEROBOT_POLICY = GOLDEN_DIR / "lerobot_pi05_tiny"
STATS = "policy_preprocessor_step_3_normalizer_processor.safetensors"
NORM_STATS = f"checkpoint/assets/{demo_reach.ASSET_ID}/norm_stats.json"
STEP = "steps/00000000.npz"
SHARD = "data/chunk-000/episode_000000.parquet"
VIDEO = "videos/observation.images.base/chunk-000/file-000.mp4"


@dataclasses.dataclass(frozen=True)
class Case:
    """A file of a source folder, damaged each way of `corruptions`, then read by each of `commands` (its command
    line, where `{folder}` is the damaged copy, `{scratch}` a new folder, `{run}` a run the side channel wrote and
    `{maps}` a maps dataset whose source is the damaged copy)."""

    source: str  # a key of the `sources` fixture
    file: str
    corruptions: tuple[str, ...]
    commands: dict[str, tuple[str, ...]]


# Model files: a LeRobot folder, an OpenPI checkpoint (the bundled pi0.5's) and a FAST tokenizer (for the bundled
# pi0-FAST), read by every command that loads a model. A damaged file's folders are real, the others links to the
# bundled ones: a checkpoint folder that is a link is the bundled model itself.
LEROBOT = ("--checkpoint-dir", "{folder}")
PI05 = ("--checkpoint-dir", "{folder}/checkpoint", "--config", demo_reach.DEMO_PI05_CONFIG.name)
PI05_TOKENIZER = (*PI05, "--paligemma-tokenizer", "{folder}/paligemma_tokenizer.model")
FAST = ("--fast-tokenizer", "{folder}/fast_tokenizer")
# Limits `serve` refuses once the model is loaded: a model that loads ends the command instead of serving forever.
UNSERVABLE = ("--max-message-mb", "8", "--max-buffered-mb", "4")


def _model_commands(model: tuple[str, ...], *, dataset: bool = True) -> dict[str, tuple[str, ...]]:
    commands = {
        "serve": ("serve", *model, "--no-warm-up", *UNSERVABLE),
        "explain-run": ("explain-run", "{run}", *model, "--out", "{scratch}/runs", "--no-progress"),
        "faithfulness": ("faithfulness", "{run}", *model, "--out", "{scratch}/f.json", "--no-progress"),
    }
    if dataset:  # the bundled models' configs map the demo dataset; the LeRobot golden's features are others
        commands["explain-dataset"] = (
            "explain-dataset", str(DEMO_DATASET), *model, "--out", "{scratch}/maps", "--episodes", "0", "--no-progress"
        )  # fmt: skip
    return commands


GOLDEN = {"golden": ("golden", "{folder}")}
LEROBOT_COMMANDS = {**_model_commands(LEROBOT, dataset=False), **GOLDEN}
PI05_COMMANDS = {**_model_commands(PI05), "export": ("export", *PI05, "--out", "{scratch}/export")}
PI05_TOKENIZER_COMMANDS = {
    **_model_commands(PI05_TOKENIZER),
    "export": ("export", *PI05_TOKENIZER, "--out", "{scratch}/export"),
}
EXPLAIN_RUN = {"explain-run": ("explain-run", "{folder}", "--out", "{scratch}/runs", "--no-progress")}
RUN_COMMANDS = {
    **EXPLAIN_RUN,
    "faithfulness": ("faithfulness", "{folder}", "--out", "{scratch}/f.json", "--no-progress"),
    "render": ("render", "{folder}", "--out", "{scratch}/render", "--no-progress"),
    "stats": ("stats", "{folder}", "--out", "{scratch}/stats.csv"),
}
MAPS_COMMANDS = {
    "faithfulness": ("faithfulness", "{folder}", "--out", "{scratch}/f.json", "--no-progress"),
    "render": ("render", "{folder}", "--out", "{scratch}/render", "--no-progress"),
    "stats": ("stats", "{folder}", "--format", "json", "--out", "{scratch}/stats.json"),
}
EXPLAIN_DATASET = {
    "explain-dataset": ("explain-dataset", "{folder}", "--out", "{scratch}/maps", "--episodes", "0", "--no-progress")
}
DATASET_COMMANDS = {**EXPLAIN_DATASET, "render": ("render", "{maps}", "--out", "{scratch}/render", "--no-progress")}
JSON_WAYS = ("truncated", "garbage", "json-array")
BINARY_WAYS = ("truncated", "garbage")

CASES = [
    Case("lerobot", "model.safetensors", BINARY_WAYS, LEROBOT_COMMANDS),
    Case("lerobot", "config.json", JSON_WAYS, LEROBOT_COMMANDS),
    Case("lerobot", "policy_preprocessor.json", JSON_WAYS, LEROBOT_COMMANDS),
    Case("lerobot", "policy_postprocessor.json", ("garbage",), LEROBOT_COMMANDS),
    Case("lerobot", STATS, BINARY_WAYS, LEROBOT_COMMANDS),
    Case("lerobot", "tokenizer/tokenizer.model", BINARY_WAYS, LEROBOT_COMMANDS),
    Case("lerobot", "golden_meta.json", ("truncated", "json-array"), LEROBOT_COMMANDS),
    Case("lerobot", "cases.npz", BINARY_WAYS, GOLDEN),
    Case("pi05", NORM_STATS, JSON_WAYS, PI05_COMMANDS),
    Case("pi05", "paligemma_tokenizer.model", BINARY_WAYS, PI05_TOKENIZER_COMMANDS),
    Case("pi0_fast", "fast_tokenizer/tokenizer.json", BINARY_WAYS, _model_commands(FAST)),
    Case("pi0_fast", "fast_tokenizer/processor_config.json", JSON_WAYS, _model_commands(FAST)),
    Case("tiny_pi0_fast", "config.json", JSON_WAYS, GOLDEN),
    Case("tiny_pi0_fast", "case_a.npz", BINARY_WAYS, GOLDEN),
    Case("policy_golden", "case.json", JSON_WAYS, GOLDEN),
    Case("policy_golden", "case_1.npz", BINARY_WAYS, GOLDEN),
    Case("run", "run.json", JSON_WAYS, {**RUN_COMMANDS, "rebuild-manifest": ("rebuild-manifest", "{folder}")}),
    Case("run", STEP, (*BINARY_WAYS, "middle"), RUN_COMMANDS),
    Case("records", "step_0.npy", BINARY_WAYS, EXPLAIN_RUN),
    Case("maps", "meta/info.json", JSON_WAYS, MAPS_COMMANDS),
    Case("maps", SHARD, BINARY_WAYS, MAPS_COMMANDS),
    Case("dataset", "meta/info.json", JSON_WAYS, EXPLAIN_DATASET),
    Case("dataset", "meta/episodes/chunk-000/file-000.parquet", BINARY_WAYS, DATASET_COMMANDS),
    Case("dataset", "meta/tasks.parquet", BINARY_WAYS, DATASET_COMMANDS),
    Case("dataset", "data/chunk-000/file-000.parquet", BINARY_WAYS, DATASET_COMMANDS),
    Case("dataset", VIDEO, ("head", "garbage"), DATASET_COMMANDS),
]


@pytest.fixture(scope="module")
def records_dir(tmp_path_factory) -> Path:
    """An upstream PolicyRecorder folder of one demo request (a pickled dict of `inputs/...` and `outputs/...`)."""
    folder = tmp_path_factory.mktemp("records")
    record = {f"inputs/{k}": v for k, v in demo_observation(0).items()} | {"outputs/actions": np.zeros((10, 2))}
    np.save(folder / "step_0", np.asarray(record))
    return folder


@pytest.fixture(scope="module")
def sources(request, records_dir) -> Callable[[str], Path]:
    """Source name -> its folder (the run and the maps dataset made on first use)."""
    fixed = {
        "lerobot": LEROBOT_POLICY,
        "pi05": demo_reach.ASSETS_PI05,
        "pi0_fast": demo_reach.ASSETS,
        "tiny_pi0_fast": GOLDEN_DIR / "tiny_pi0_fast",
        "policy_golden": GOLDEN_DIR / "tiny_policy_pi05_droid",
        "records": records_dir,
        "dataset": DEMO_DATASET,
    }
    made = {"run": "served_run_dir", "maps": "demo_maps_dir"}
    return lambda name: fixed[name] if name in fixed else request.getfixturevalue(made[name])


def _params() -> list:
    return [
        pytest.param(case, corruption, command, id=f"{case.source}:{case.file}:{corruption}:{command}")
        for case in CASES
        for corruption in case.corruptions
        for command in case.commands
    ]


@pytest.mark.parametrize(("case", "corruption", "command"), _params())
def test_a_damaged_file_is_named_in_one_line(case, corruption, command, sources, tmp_path, capsys):
    folder = damaged_copy(sources(case.source), tmp_path / "damaged", case.file, corruption)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    places = {"{folder}": folder, "{scratch}": scratch}
    template = " ".join(case.commands[command])
    if "{run}" in template:
        places["{run}"] = sources("run")
    if "{maps}" in template:
        places["{maps}"] = _maps_reading(sources("maps"), folder, tmp_path / "maps")
    args = []
    for arg in case.commands[command]:
        for key, value in places.items():
            arg = arg.replace(key, str(value))
        args.append(arg)
    with pytest.raises(SystemExit) as exited:
        cli.main(args)
    out = capsys.readouterr()
    text = out.out + out.err
    assert exited.value.code not in (0, None), text
    assert "Traceback" not in text, text
    named = [line for line in text.splitlines() if str(folder / case.file) in line]
    assert len(named) == 1, f"{args}: not one line naming {folder / case.file}:\n{text}"


def _maps_reading(maps: Path, source: Path, dst: Path) -> Path:
    """A copy of a maps dataset whose source dataset is `source` (what `render` draws the maps over)."""
    copy = writable_copy(maps, dst)
    edit_json(copy / "meta" / "info.json", lambda info: info.update(source=str(source)))
    return copy
