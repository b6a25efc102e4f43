"""A separate virtual environment holding the real `openpi-client` from PyPI, used like a robot computer would.

openpi-client pins numpy<2 while our JAX needs numpy>=2, so the client cannot live in the project's venv. The venv is
built once at `<repo>/.venv-client` (gitignored), reused while it imports cleanly, and rebuilt when it does not.
Client code runs there as subprocesses that talk to our server over loopback.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

OPENPI_CLIENT_VERSION = "0.1.2"  # newest release on PyPI; its WebsocketClientPolicy matches upstream 15a9616's
REPO_ROOT = Path(__file__).resolve().parents[2]
CLIENT_VENV = REPO_ROOT / ".venv-client"
_STAMP = CLIENT_VENV / "openpi-client-version.txt"
_PROBE = "import numpy, msgpack, websockets, openpi_client.websocket_client_policy as w; print(numpy.__version__)"


def _python(venv: Path) -> Path:
    return venv / "bin" / "python"


def _is_healthy(venv: Path) -> bool:
    stamp = venv / _STAMP.name
    if not _python(venv).exists() or not stamp.exists() or stamp.read_text().strip() != OPENPI_CLIENT_VERSION:
        return False
    probe = subprocess.run([_python(venv), "-c", _PROBE], capture_output=True, text=True, timeout=120)
    return probe.returncode == 0


def client_python(venv: Path = CLIENT_VENV) -> Path:
    """Path of the client venv's interpreter, building the venv first if it is missing or broken."""
    lock_path = venv.parent / f"{venv.name}.lock"
    with open(lock_path, "w") as lock:
        # Several test processes may ask at once; only one builds.
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not _is_healthy(venv):
            shutil.rmtree(venv, ignore_errors=True)
            subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True)
            pip = [str(_python(venv)), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
            # openpi-client imports typing_extensions without declaring it as a dependency.
            packages = [f"openpi-client=={OPENPI_CLIENT_VERSION}", "typing-extensions"]
            result = subprocess.run([*pip, *packages], capture_output=True, text=True)
            if result.returncode != 0:
                raise RuntimeError(f"could not install openpi-client into {venv}:\n{result.stdout}\n{result.stderr}")
            (venv / _STAMP.name).write_text(OPENPI_CLIENT_VERSION + "\n")
            if not _is_healthy(venv):
                raise RuntimeError(f"{venv} was built but openpi-client does not import")
    return _python(venv)


def spawn_client(script: str, *args: str, cwd: Path | None = None) -> subprocess.Popen:
    """Starts `script` (Python source) with the client venv's interpreter; finish it with `collect`."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    return subprocess.Popen(
        [str(client_python()), "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=env,
    )


def collect(proc: subprocess.Popen, timeout: float = 180.0) -> dict:
    """Waits for a client script; returns the JSON object it printed last. A failure raises AssertionError."""
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        stdout, stderr = proc.communicate()
        raise AssertionError(f"client script timed out after {timeout}s:\n{stderr}\n{stdout}") from None
    if proc.returncode != 0:
        raise AssertionError(f"client script failed ({proc.returncode}):\n{stderr}\n{stdout}")
    lines = [line for line in stdout.splitlines() if line.strip()]
    if not lines:
        raise AssertionError(f"client script printed nothing; stderr:\n{stderr}")
    return json.loads(lines[-1])


def run_client(script: str, *args: str, timeout: float = 180.0) -> dict:
    """`spawn_client` + `collect`."""
    return collect(spawn_client(script, *args), timeout=timeout)


if __name__ == "__main__":
    print(client_python())
