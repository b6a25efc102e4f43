"""Progress reporting for long renders: tqdm when installed, otherwise a sparse line on stderr."""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def progress(items: Iterable[T], total: int, desc: str, enabled: bool = True) -> Iterator[T]:
    """Yields `items` while reporting progress; silent when disabled or for tiny jobs."""
    if not enabled or total < 2:
        yield from items
        return
    try:
        from tqdm import tqdm
    except ImportError:
        tqdm = None
    if tqdm is not None:
        yield from tqdm(items, total=total, desc=desc, unit="step", file=sys.stderr)
        return
    last = 0.0
    for i, item in enumerate(items, 1):
        yield item
        now = time.monotonic()
        if now - last > 2.0 or i == total:
            print(f"{desc}: {i}/{total}", file=sys.stderr, flush=True)
            last = now


@dataclasses.dataclass(frozen=True)
class Reporter:
    """`progress` with its description and switch fixed: what a long job takes as its `progress` argument."""

    desc: str
    enabled: bool = True

    def __call__(self, items: Iterable[T], total: int) -> Iterator[T]:
        return progress(items, total, self.desc, self.enabled)
