"""`python -m openpi_cam serve` as a child process on a free loopback port: how the serving tests start the real
command line, wait for it to answer, and stop it as a container would (SIGTERM)."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from paths import REPO_ROOT
from real_clients import http_get

START_TIMEOUT_S = 300  # loading and compiling on a loaded 2-core machine


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "openpi_cam", "serve", *args]


@contextlib.contextmanager
def serve_subprocess(tmp_path: Path, *args: str) -> Iterator[tuple[subprocess.Popen, int, Path]]:
    """`python -m openpi_cam serve ARGS` on a free loopback port, once its /healthz answers: (process, port, log)."""
    port = free_port()
    log_path = tmp_path / "serve.log"
    with log_path.open("w") as log:
        cmd = serve_cmd("--host", "127.0.0.1", "--port", str(port), *args)
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=REPO_ROOT)
        try:
            wait_healthy(proc, port, log_path)
            yield proc, port, log_path
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def wait_healthy(proc: subprocess.Popen, port: int, log_path: Path) -> None:
    """Returns once `serve` on `port` answers /healthz; fails with its log if it exits or takes too long."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        if proc.poll() is not None:
            raise AssertionError(f"serve exited with {proc.returncode}:\n{log_path.read_text()}")
        try:
            if http_get(f"http://127.0.0.1:{port}/healthz", timeout=1)[0] == 200:
                return
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise AssertionError(f"serve did not answer /healthz within {START_TIMEOUT_S} s:\n{log_path.read_text()}")
        time.sleep(0.2)


def stop(proc: subprocess.Popen, log_path: Path) -> None:
    """SIGTERM, and a clean exit (status 0) within two minutes."""
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(120) == 0, log_path.read_text()
