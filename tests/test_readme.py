"""Every command the README shows, run as written: a default that breaks is a README command that fails here.

The README's shell commands and Python snippets are read from README.md itself, in order, and each is matched by
exactly one step below (a command no step runs fails the fast tier's check). The slow tier runs them all in a fresh
working folder beside `../shared`, with these substitutions only: `.venv/bin/` is this interpreter's environment,
`~/ckpt/<config>` and the tokenizer paths stand for the golden checkpoints of that config (`../shared/golden`), `8000`
is a free port, and `cam_runs/<run>` is the run the side-channel command wrote. The install prefixes of the first two
commands are what `.ci/run` itself does, and the README's test command is the one `.ci/run` runs.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from client_env import run_client
from paths import GOLDEN_DIR, REPO_ROOT, SHARED_DIR
from serve_process import free_port, stop, wait_healthy

from openpi_cam.lerobot.dataset import open_dataset

README = REPO_ROOT / "README.md"
BIN = Path(sys.prefix) / "bin"
DROID = GOLDEN_DIR / "tiny_policy_droid"
PI05_DROID = GOLDEN_DIR / "tiny_policy_pi05_droid"
# What each placeholder of the README stands for here.
CHECKPOINTS = {"~/ckpt/pi0_fast_droid": DROID, "~/ckpt/pi05_droid": PI05_DROID}
PALIGEMMA = "~/.cache/openpi/big_vision/paligemma_tokenizer.model"
FAST = "~/hf/fast"
# The README's robot-side snippets: a DROID robot's (OpenPI checkpoints) and a LeRobot policy's (its feature names).
CLIENT_MARKS = {"droid": "observation/exterior_image_1_left", "lerobot": "observation.images.base"}
LEROBOT_FOLDER = "demo_pi05_lerobot"  # what the README's export command writes
COMMAND_TIMEOUT_S = 900


def _blocks(language: str) -> list[tuple[int, str]]:
    """(offset in the README, text) of its fenced blocks of one language."""
    text = README.read_text()
    return [(m.start(), m.group(1)) for m in re.finditer(rf"```{language}\n(.*?)```", text, re.S)]


def readme_items() -> list[tuple[str, str]]:
    """The README's shell commands (continuation lines joined, comments dropped) and Python snippets, in order:
    ("bash", command) or ("python", source)."""
    items: list[tuple[int, str, str]] = []
    for offset, block in _blocks("bash"):
        joined = re.sub(r"\\\n\s*", "", block)
        for i, line in enumerate(joined.splitlines()):
            command = re.sub(r"(^|\s+)#.*$", "", line).strip()
            if command:
                items.append((offset + i, "bash", command))
    items += [(offset, "python", source) for offset, source in _blocks("python")]
    return [(kind, text) for _, kind, text in sorted(items)]


@dataclasses.dataclass
class Context:
    """What the steps share: the working folder and what earlier commands made."""

    workdir: Path
    clients: dict[str, str]  # the README's robot-side snippets, by `CLIENT_MARKS`' names
    run: Path | None = None  # the side channel's run (`cam_runs/<run>`)


@dataclasses.dataclass(frozen=True)
class Step:
    pattern: str  # matched (re.fullmatch) against a README command, or searched in a Python snippet
    run: Callable[[Context, str], None]
    kind: str = "bash"

    def matches(self, kind: str, text: str) -> bool:
        if kind != self.kind:
            return False
        return bool(re.fullmatch(self.pattern, text) if kind == "bash" else re.search(self.pattern, text))


def substituted(ctx: Context, text: str, port: int | None = None) -> str:
    """The README text with its placeholders replaced by what they stand for here."""
    golden = PI05_DROID if "pi05_droid" in text else DROID
    text = text.replace(".venv/bin/", f"{BIN}/")
    for placeholder, folder in CHECKPOINTS.items():
        text = text.replace(placeholder, str(folder / "checkpoint"))
    text = text.replace(PALIGEMMA, str(golden / "paligemma_tokenizer_tiny.model"))
    text = text.replace(FAST, str(DROID / "fast_tokenizer"))
    text = text.replace("../shared/", f"{SHARED_DIR}/")
    if ctx.run is not None:
        text = text.replace("cam_runs/<run>", str(ctx.run.relative_to(ctx.workdir)))
    if port is not None:
        text = text.replace("8000", str(port))
    return text


def shell(ctx: Context, command: str) -> subprocess.CompletedProcess:
    done = subprocess.run(
        substituted(ctx, command),
        shell=True,
        executable="/bin/bash",
        cwd=ctx.workdir,
        capture_output=True,
        text=True,
        timeout=COMMAND_TIMEOUT_S,
    )
    assert done.returncode == 0, f"{command}\n{done.stderr[-4000:]}"
    return done


# ---------------------------------------------------------------- the steps


def _first_command(ctx: Context, command: str) -> None:
    # The install is .ci/run's own (`python3 -m venv .venv`, then pip install -e); the rest runs here.
    install, run = command.rsplit(" && ", 1)
    assert install.startswith("python3 -m venv .venv && .venv/bin/pip install -e .")
    shell(ctx, run)
    (run_dir,) = (ctx.workdir / "demo_out").iterdir()
    assert (run_dir / "faithfulness.json").is_file() and list(run_dir.glob("render-*/index.html"))
    assert list(run_dir.glob("render-*/**/*.mp4")), "the demo writes its videos by default"


def _metaworld_demo(ctx: Context, command: str) -> None:
    # The extra is part of `.[dev]`, which .ci/run installs; the rest runs here.
    install, run = command.split(" && ", 1)
    assert install == '.venv/bin/pip install -e ".[metaworld]"'
    assert '.venv/bin/python -m pip install --quiet -e ".[dev]"' in (REPO_ROOT / ".ci" / "run").read_text()
    shell(ctx, run)
    (run_dir,) = (ctx.workdir / "metaworld_runs").iterdir()
    assert (run_dir / "faithfulness.json").is_file() and list(run_dir.glob("render-*/index.html"))
    assert len(list((run_dir / "steps").glob("*.npz"))) > 6  # several requests per episode, each explained


def _test_command(ctx: Context, command: str) -> None:
    install, run = command.rsplit(" && ", 1)
    assert install == 'python3 -m venv .venv && .venv/bin/pip install -e ".[dev]"'
    ci = (REPO_ROOT / ".ci" / "run").read_text()
    assert "python3 -m venv .venv\n.venv/bin/python -m pip install --quiet --upgrade pip\n" in ci
    assert f"{run} --durations=25\n" in ci, "CI runs the README's test command"


def _serving(ctx: Context, command: str, requests: int = 1) -> None:
    """A serve command until /healthz answers, the README's client snippet against it, then SIGTERM (exit 0)."""
    port = free_port()
    args = shlex.split(substituted(ctx, command, port))
    if "--port" not in args:  # the README's default port, 8000
        args += ["--port", str(port)]
    args += ["--host", "127.0.0.1"]
    log_path = ctx.workdir / f"serve-{port}.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, cwd=ctx.workdir)
        try:
            wait_healthy(proc, port, log_path)
            lerobot = LEROBOT_FOLDER in command
            client = ctx.clients["lerobot" if lerobot else "droid"]
            script = substituted(ctx, client, port) + "\nimport json; print(json.dumps(list(actions.shape)))\n"
            for _ in range(requests):
                shape = run_client(script)
            expected = [10, 2] if lerobot else [15 if "pi05_droid" in command else 10, 8]
            assert shape == expected, shape
            stop(proc, log_path)
        finally:
            if proc.poll() is None:
                proc.kill()


def _client_snippet(ctx: Context, source: str) -> None:
    assert source in ctx.clients.values()  # run against each serve command, above and below it


def _side_channel(ctx: Context, command: str) -> None:
    _serving(ctx, command, requests=2)
    (run_json,) = (ctx.workdir / "cam_runs").glob("*/run.json")
    ctx.run = run_json.parent
    assert len(list((ctx.run / "steps").glob("*.npz"))) == 2


def _numpy_snippet(ctx: Context, source: str) -> None:
    done = subprocess.run(
        [sys.executable, "-c", substituted(ctx, source) + "\nprint(heat.shape, meta['target'])"],
        cwd=ctx.workdir,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["(16,", "16)", "generated-tokens"], done.stdout  # the golden model is malformed


def _faithfulness(ctx: Context, command: str) -> None:
    shell(ctx, command)
    assert (ctx.run / "faithfulness.json").is_file()  # type: ignore[operator]


def _render(ctx: Context, command: str) -> None:
    shell(ctx, command)
    assert (ctx.run / "render-gradnorm" / "index.html").is_file()  # type: ignore[operator]


def _stats(ctx: Context, command: str) -> None:
    shell(ctx, command)
    rows = (ctx.workdir / "stats.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("seq,")


def _explain_run(ctx: Context, command: str) -> None:
    done = shell(ctx, command)
    (run_json,) = (ctx.workdir / "explained").glob("*/run.json")
    steps = sorted((run_json.parent / "steps").glob("*.npz"))
    assert len(steps) == 2 and "'actions_mismatched': 0" in done.stderr
    with np.load(steps[0]) as z:
        assert any(k.startswith("ig/") for k in z.files) and any(k.startswith("occlusion/") for k in z.files)


def _explain_dataset(ctx: Context, command: str) -> None:
    shell(ctx, command)
    if LEROBOT_FOLDER in command:  # every episode, with the LeRobot folder's own feature names
        info = json.loads((ctx.workdir / "lerobot_pi05.maps" / "meta" / "info.json").read_text())
        assert info["model"]["config"] is None and info["keys"]["observation.state"] == "observation.state"
        assert len(list((ctx.workdir / "lerobot_pi05.maps").glob("data/*/*.parquet"))) == 8
        return
    out = ctx.workdir / ("ray.maps" if "--engine ray" in command else "demo_reach_v30_video.maps")
    shards = sorted(out.glob("data/*/*.parquet"))
    assert [p.name for p in shards] == [f"episode_{e:06d}.parquet" for e in range(4)]
    if "--engine ray" in command:  # the same shards as the local engine's, on default flags
        local = ctx.workdir / "demo_reach_v30_video.maps"
        for shard in shards:
            ours, theirs = pq.read_table(shard), pq.read_table(local / shard.relative_to(out))
            # every column both have (the local command also carries the target box), timings aside
            columns = [c for c in theirs.column_names if c in ours.column_names and c != "explain_ms"]
            assert len(columns) == len(ours.column_names) - 1
            assert ours.select(columns).equals(theirs.select(columns)), shard.name


def _record_rollouts(ctx: Context, command: str) -> None:
    shell(ctx, command)
    dataset = open_dataset(ctx.workdir / "rollouts")
    assert len(dataset.episodes) == 12 and {"next.success", "next.reward", "next.done"} <= set(dataset.features)
    listed = json.loads((ctx.workdir / "rollouts" / "meta" / "demo_episodes.json").read_text())
    assert listed["perturbations"] == ["clean", "hue=45", "absent"] and len(listed["episodes"]) == 12
    # the perturbations in turn, each episode's outcome recorded: a prompt naming an absent block is never reached
    episodes = listed["episodes"]
    assert [e["perturbation"] for e in episodes] == listed["perturbations"] * 4
    assert not any(e["success"] for e in episodes if e["perturbation"] == "absent")


def _explain_rollouts(ctx: Context, command: str) -> None:
    shell(ctx, command)
    table = pq.read_table(next((ctx.workdir / "rollouts.maps").glob("data/*/*.parquet")))
    assert {"episode_success", "episode_length", "extra/target_box"} <= set(table.column_names)
    assert any(c.startswith("reliance") for c in table.column_names), table.column_names
    assert all(i % 5 == 0 for i in table.column("frame_index").to_pylist())  # --every-k 5


def _dataset_views(ctx: Context, command: str) -> None:
    if "failures.json" in command:  # the rollouts': outcomes and how well each figure finds the failures
        shell(ctx, command)
        _failure_views(ctx, json.loads((ctx.workdir / "failures.json").read_text()))
        return
    shell(ctx, command)
    lerobot = "lerobot_views" in command
    views = json.loads((ctx.workdir / ("lerobot_views.json" if lerobot else "views.json")).read_text())
    dataset = open_dataset(SHARED_DIR / "lerobot" / "demo_reach_v30_video")
    episodes = dataset.episodes if lerobot else range(4)
    assert views["summary"]["frames"] == sum(dataset.episode_length(e) for e in episodes)


def _failure_views(ctx: Context, views: dict) -> None:
    """What the README's "Finding failures" says the views of the recorded rollouts hold."""
    episodes = json.loads((ctx.workdir / "rollouts" / "meta" / "demo_episodes.json").read_text())["episodes"]
    succeeded = {e["episode_index"]: e["success"] for e in episodes}
    # rows carry their episode's outcome
    assert all(row["episode_success"] == succeeded[row["episode_index"]] for row in views["frames"])
    outcomes = views["summary"]["outcomes"]
    failures = sum(not s for s in succeeded.values())
    assert (outcomes["episodes"], outcomes["failures"]) == (12, failures) and 0 < failures < 12
    # failed episodes beside successful ones
    assert set(outcomes["by_outcome"]) == {"success", "failure"}
    # each figure's failure-finding ROC AUC (share, entropy, nuisance mass, reliance), next to the episode length's
    figures = ("entropy", "length", "base_0_rgb/mean_share", "base_0_rgb/mean_nuisance_mass",
               "base_0_rgb/mean_reliance_score", "prompt/mean_reliance_score")  # fmt: skip
    for figure in figures:
        assert 0.0 <= outcomes["failure_finding"][figure]["auroc"] <= 1.0, figure
    # and from the first request alone, where the length says nothing
    early = outcomes["early_warning"]
    assert early["frames"] == 1 and "length" not in early["figures"] and "entropy" in early["figures"]
    # episodes ranked most diffuse maps first
    entropies = [e["entropy"] for e in views["summary"]["episode_ranking"]]
    assert len(entropies) == 12 and entropies == sorted(entropies, reverse=True)


def _explain_monitor_features(ctx: Context, command: str) -> None:
    shell(ctx, command)
    table = pq.read_table(next((ctx.workdir / "features.maps").glob("data/*/*.parquet")))
    assert {"monitor/stac", "monitor/token_entropy", "monitor/features/prompt"} <= set(table.column_names)


def _monitor_fit(ctx: Context, command: str) -> None:
    done = shell(ctx, command)
    monitor = json.loads((ctx.workdir / "monitor.json").read_text())
    assert monitor["kind"] == "mahalanobis" and monitor["execution_horizon"] == 5
    assert "AUROC" in done.stdout and "false alarms" in done.stdout, done.stdout


# The bundled demo robot's request (64 px cameras), sent by the real openpi-client: its response carries the score.
DEMO_CLIENT = """
import json, numpy as np
from openpi_client import websocket_client_policy
policy = websocket_client_policy.WebsocketClientPolicy(host="localhost", port=8000)
frame = np.zeros((64, 64, 3), np.uint8)
obs = {"observation/image": frame, "observation/wrist_image": frame, "observation/state": np.zeros(2)}
obs["prompt"] = "reach the red block"
responses = [policy.infer(obs) for _ in range(2)]
print(json.dumps([sorted(r["monitor"]) for r in responses] + [list(responses[-1]["actions"].shape)]))
"""


def _monitored_serving(ctx: Context, command: str) -> None:
    port = free_port()
    args = [*shlex.split(substituted(ctx, command, port)), "--host", "127.0.0.1"]
    log_path = ctx.workdir / f"serve-{port}.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, cwd=ctx.workdir)
        try:
            wait_healthy(proc, port, log_path)
            received = run_client(DEMO_CLIENT.replace("8000", str(port)))
            assert received == [["flag", "score"], ["flag", "score"], [10, 2]], received
            stop(proc, log_path)
        finally:
            if proc.poll() is None:
                proc.kill()


def _explain_monitored(ctx: Context, command: str) -> None:
    shell(ctx, command)
    table = pq.read_table(next((ctx.workdir / "scored.maps").glob("data/*/*.parquet")))
    assert any(score is not None for score in table.column("monitor/score").to_pylist())


def _golden(ctx: Context, command: str) -> None:
    done = shell(ctx, command)
    assert " 0 failed" in done.stdout + done.stderr


def _export(ctx: Context, command: str) -> None:
    shell(ctx, command)
    assert json.loads((ctx.workdir / LEROBOT_FOLDER / "config.json").read_text())["type"] == "pi05"


def _dataset_render(ctx: Context, command: str) -> None:
    shell(ctx, command)
    render = ctx.workdir / "demo_reach_v30_video.maps" / "render-gradnorm"
    assert (render / "index.html").is_file() and len(list(render.glob("videos/*.mp4"))) == 4


def _dataset_faithfulness(ctx: Context, command: str) -> None:
    shell(ctx, command)
    report = json.loads((ctx.workdir / "demo_reach_v30_video.maps" / "meta" / "faithfulness.json").read_text())
    assert report["steps_evaluated"] == 16


STEPS = (
    Step(r"python3 -m venv \.venv && \.venv/bin/pip install -e \. && \.venv/bin/openpi-cam demo .*", _first_command),
    Step(r'python3 -m venv \.venv && \.venv/bin/pip install -e "\.\[dev\]" && .* -m pytest -q', _test_command),
    Step(r"\.venv/bin/openpi-cam serve --config \w+ --checkpoint-dir .* --port 8000", _serving),
    Step("|".join(CLIENT_MARKS.values()), _client_snippet, "python"),
    Step(r"\.venv/bin/openpi-cam serve .* --cam\.every-k 1 .*", _side_channel),
    Step(r"np\.load\(\"cam_runs/<run>/steps", _numpy_snippet, "python"),
    Step(r"\.venv/bin/openpi-cam faithfulness cam_runs/<run>", _faithfulness),
    Step(r"\.venv/bin/openpi-cam render cam_runs/<run> --kind gradnorm", _render),
    Step(r"\.venv/bin/openpi-cam stats cam_runs/<run> --kind gradnorm --format csv > stats\.csv", _stats),
    Step(r"\.venv/bin/openpi-cam explain-run cam_runs/<run> .*", _explain_run),
    Step(r"\.venv/bin/openpi-cam explain-dataset \.\./shared/lerobot/demo_reach_v30_video .*", _explain_dataset),
    Step(r"\.venv/bin/openpi-cam stats \w+\.maps --format json > \w+\.json", _dataset_views),
    Step(r"\.venv/bin/openpi-cam golden \.\./shared/golden/lerobot_pi05_tiny", _golden),
    Step(r"\.venv/bin/openpi-cam demo --no-explain .* --record rollouts", _record_rollouts),
    Step(r'\.venv/bin/pip install -e "\.\[metaworld\]" && .* demo --sim metaworld .*', _metaworld_demo),
    Step(r"\.venv/bin/openpi-cam explain-dataset rollouts --every-k 5 --reliance .*", _explain_rollouts),
    Step(r"\.venv/bin/openpi-cam explain-dataset rollouts .* --monitor-features .*", _explain_monitor_features),
    Step(r"\.venv/bin/openpi-cam monitor fit features\.maps .*", _monitor_fit),
    Step(r"\.venv/bin/openpi-cam serve --monitor monitor\.json .*", _monitored_serving),
    Step(r"\.venv/bin/openpi-cam explain-dataset rollouts .* --monitor monitor\.json .*", _explain_monitored),
    Step(r"\.venv/bin/openpi-cam export --to lerobot --config demo_reach_pi05 --out demo_pi05_lerobot", _export),
    Step(r"\.venv/bin/openpi-cam serve --checkpoint-dir demo_pi05_lerobot --port 8000", _serving),
    Step(r"\.venv/bin/openpi-cam render demo_reach_v30_video\.maps --kind gradnorm", _dataset_render),
    Step(r"\.venv/bin/openpi-cam faithfulness demo_reach_v30_video\.maps --max-steps 16", _dataset_faithfulness),
)  # fmt: skip


def _step_of(kind: str, text: str) -> Step:
    found = [step for step in STEPS if step.matches(kind, text)]
    assert len(found) == 1, f"README {kind} {text[:100]!r} is run by {len(found)} steps here (must be exactly one)"
    return found[0]


def test_every_readme_command_is_run_here():
    """Each README command and snippet has exactly one step, and each step has a README command: a command added
    to the README without a test, or a test left behind by a removed command, fails here."""
    items = readme_items()
    used = {id(_step_of(kind, text)) for kind, text in items}
    assert not [step.pattern for step in STEPS if id(step) not in used]
    # Only bash and python blocks are read above: a command in a block of another language would go unchecked.
    openings = re.findall(r"^```(.*)$", README.read_text(), re.M)[::2]
    assert set(openings) <= {"bash", "python"}, openings


@pytest.mark.slow
def test_readme_commands_run_as_written(tmp_path):
    workdir = tmp_path / "work"
    workdir.mkdir()
    items = readme_items()
    clients = {
        name: [text for kind, text in items if kind == "python" and mark in text] for name, mark in CLIENT_MARKS.items()
    }
    assert all(len(found) == 1 for found in clients.values()), clients
    ctx = Context(workdir, clients={name: found[0] for name, found in clients.items()})
    for kind, text in items:
        _step_of(kind, text).run(ctx, text)
    shutil.rmtree(workdir / "demo_out", ignore_errors=True)
