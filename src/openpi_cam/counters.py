"""Thread-safe event counters that log the first occurrence of each event and only count the rest.

A server that meets the same malformed generation, I/O error or side-channel failure thousands of times must neither
stay silent nor flood its log: each event is logged once, and every occurrence is counted for `/stats` and manifests.
"""

from __future__ import annotations

import collections
import logging
import threading


class WarnOnceCounter:
    def __init__(self, logger: logging.Logger, prefix: str) -> None:
        self._logger = logger
        self._prefix = prefix
        self._lock = threading.Lock()
        self._counts: collections.Counter[str] = collections.Counter()

    def count(self, event: str, message: str | None = None, *, n: int = 1) -> None:
        """Adds `n` to `event`'s count; logs `message` (if any) the first time `event` is counted."""
        with self._lock:
            first = event not in self._counts
            self._counts[event] += n
        if first and message is not None:
            self._logger.warning("%s: %s (%s); further occurrences are only counted", self._prefix, message, event)

    def get(self, event: str) -> int:
        with self._lock:
            return self._counts[event]

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)
