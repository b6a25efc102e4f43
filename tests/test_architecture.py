"""The package's layers, drawn from its imports (function-local ones included), point one way: down.

cli > demo > maps > viz > cam > monitor > serving > checkpoints > lerobot > policies > {model, tokenizers,
transforms and the package-root utilities}. A function-local import is allowed only for an optional heavy
dependency (not a module of this package). The maps room is imported by the command line only, and the side
channel's room reaches none of it. docs/ARCHITECTURE.md says why each room sits where it does. Inside a room, no
function runs past MAX_FUNCTION_LINES (docstrings aside; a command line's `main` lists its flags and is exempt)."""

from __future__ import annotations

import ast
import pathlib
import subprocess
import sys

from paths import REPO_ROOT

SRC = REPO_ROOT / "src"
LAYERS = ("cli", "demo", "maps", "viz", "cam", "monitor", "serving", "checkpoints", "lerobot", "policies", "base")
MAX_FUNCTION_LINES = 80
# The LeRobot room's dataset modules, usable without the rest of the package.
LEROBOT_FORMAT = ("dataset", "writer", "stats", "video", "rollouts")


def _module(path: pathlib.Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] == "__main__":
        return "cli"  # `python -m openpi_cam` is the command line
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else "base"


def _imports(path: pathlib.Path) -> list[tuple[str, bool]]:
    """(imported module, whether the import sits inside a function) for every import of the package's modules."""
    tree = ast.parse(path.read_text())
    local = {
        id(node)
        for fn in ast.walk(tree)
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef)
        for node in ast.walk(fn)
        if isinstance(node, ast.Import | ast.ImportFrom)
    }
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, id(node) in local) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, id(node) in local))
    return out


def test_every_import_points_down_the_layers():
    upward, local = [], []
    for path in sorted(SRC.rglob("*.py")):
        module = _module(path)
        for target, in_function in _imports(path):
            if not target.startswith("openpi_cam"):
                continue
            if in_function:
                local.append(f"{module} imports {target} inside a function")
            if LAYERS.index(_layer(target)) < LAYERS.index(_layer(module)):
                upward.append(f"{module} ({_layer(module)}) imports {target} ({_layer(target)})")
    assert not upward, "imports that run up the layers:\n" + "\n".join(upward)
    assert not local, "function-local imports of the package:\n" + "\n".join(local)


def test_the_lerobot_format_modules_import_nothing_of_the_package_but_its_errors():
    """The LeRobot reader and writer stay usable on their own: only `openpi_cam.errors` may come in (the writer
    reports errors as the reader does)."""
    own = {"openpi_cam.errors", *(f"openpi_cam.lerobot.{name}" for name in LEROBOT_FORMAT)}
    found = [
        f"{name} imports {target}"
        for name in LEROBOT_FORMAT
        for target, _ in _imports(SRC / "openpi_cam" / "lerobot" / f"{name}.py")
        if target.startswith("openpi_cam") and target not in own
    ]
    assert not found, found


def test_the_monitor_room_is_numpy_and_the_standard_library_over_the_base_modules():
    """The failure monitor runs in the side channel, in dataset jobs and in the viewers alike: besides its own
    modules it imports NumPy, the standard library and the package-root utilities, never JAX nor a room above or
    beside it (serving, policies, model, tokenizers)."""
    found = []
    for path in sorted((SRC / "openpi_cam" / "monitor").rglob("*.py")):
        for target, _ in _imports(path):
            top = target.split(".")[0]
            if top == "openpi_cam":
                if not (_layer(target) == "monitor" or (_layer(target) == "base" and target.count(".") == 1)):
                    found.append(f"{_module(path)} imports {target}")
            elif top != "numpy" and top not in sys.stdlib_module_names:
                found.append(f"{_module(path)} imports {target}")
    assert not found, "\n".join(found)


def test_only_the_command_line_imports_the_maps_room():
    found = [
        f"{_module(path)} imports {target}"
        for path in sorted(SRC.rglob("*.py"))
        if _layer(_module(path)) not in ("cli", "maps")
        for target, _ in _imports(path)
        if _layer(target) == "maps"
    ]
    assert not found, "\n".join(found)


def test_a_dataset_job_does_not_load_the_threaded_side_channel():
    """A Ray worker explaining episodes imports the maps room; nothing it imports, however indirectly, is the
    live side channel (its worker thread and queue belong to `serve`)."""
    code = (
        "import sys, openpi_cam.maps.explain, openpi_cam.maps.ray_engine, openpi_cam.maps.faithfulness; "
        "print(sorted(m for m in sys.modules if m == 'openpi_cam.cam.side_channel'))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_the_checker_sees_an_upward_import(tmp_path):
    """The rule above would catch a policies module importing the side channel, even from inside a function."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from openpi_cam.cam.side_channel import CAMPolicy\n")
    ((target, in_function),) = _imports(bad)
    assert in_function and LAYERS.index(_layer(target)) < LAYERS.index(_layer("openpi_cam.policies.policy"))


def test_no_import_cycles_among_files_or_subpackages():
    """The shared checker (`../shared/tools/import_cycles.py`) finds no cycle among files or sub-packages."""
    checker = REPO_ROOT.parent / "shared" / "tools" / "import_cycles.py"
    result = subprocess.run([sys.executable, str(checker), str(SRC)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def _long_functions(path: pathlib.Path, module: str) -> list[str]:
    """`module.function (N lines)` for each function or method of the file longer than MAX_FUNCTION_LINES, its
    docstring not counted; a command line's `main` is exempt."""
    found = []
    for fn in ast.walk(ast.parse(path.read_text())):
        if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        if fn.name == "main" and _layer(module) == "cli":
            continue
        lines = fn.end_lineno - fn.lineno + 1  # type: ignore[operator]
        if ast.get_docstring(fn) is not None:
            doc = fn.body[0]
            lines -= doc.end_lineno - doc.lineno + 1  # type: ignore[operator]
        if lines > MAX_FUNCTION_LINES:
            found.append(f"{module}.{fn.name} ({lines} lines)")
    return found


def test_no_function_runs_past_the_line_limit():
    found = [f for path in sorted(SRC.rglob("*.py")) for f in _long_functions(path, _module(path))]
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(found)


def test_the_line_check_counts_code_and_leaves_docstrings_and_cli_mains_out(tmp_path):
    """A function one line over the limit is named; one at the limit is not, however long its docstring; a command
    line's `main` is exempt, the same function elsewhere is not."""

    def function(name: str, code_lines: int, docstring_lines: int = 0) -> str:
        doc = '    """' + "\n".join(["words"] * docstring_lines) + '"""\n' if docstring_lines else ""
        body = "".join(f"    x{i} = {i}\n" for i in range(code_lines - 1))  # the `def` line is the first
        return f"def {name}():\n{doc}{body}\n"

    path = tmp_path / "m.py"
    path.write_text(function("over", MAX_FUNCTION_LINES + 1) + function("at", MAX_FUNCTION_LINES, docstring_lines=30))
    assert _long_functions(path, "openpi_cam.cam.m") == [f"openpi_cam.cam.m.over ({MAX_FUNCTION_LINES + 1} lines)"]
    path.write_text(function("main", MAX_FUNCTION_LINES + 1))
    assert _long_functions(path, "openpi_cam.cli.m") == []
    assert _long_functions(path, "openpi_cam.cam.m") == [f"openpi_cam.cam.m.main ({MAX_FUNCTION_LINES + 1} lines)"]
