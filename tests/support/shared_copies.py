"""Writable copies of the read-only reference data in `../shared` (the tests that break a dataset or a policy folder
edit a copy under tmp_path), and in-place edits of a copy's JSON files."""

from __future__ import annotations

import json
import shutil
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any


def writable_copy(src: Path, dst: Path) -> Path:
    """`src` copied to `dst`, every file and folder writable by its owner (copytree keeps the shared files' modes)."""
    shutil.copytree(src, dst)
    for path in [dst, *dst.rglob("*")]:
        path.chmod(path.stat().st_mode | stat.S_IWUSR)
    return dst


def edit_json(path: Path, change: Callable[[Any], Any]) -> None:
    """Rewrites the JSON file at `path` after `change` has edited its parsed value in place."""
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
