"""The failure monitor live: one `monitor.stream.Stream` per connection, fed every served call's signals in the
connection's order, and the counters `/stats` reports. The side channel (`cam.side_channel.CAMPolicy`) decides when
a call is scored (by its worker, or before the response for `--cam.monitor-response`); this module only scores.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np

from openpi_cam.monitor.monitor_file import UNTRAINED, Monitor
from openpi_cam.monitor.stream import StepScore, Stream, execution_horizon

log = logging.getLogger(__name__)

# The response key of `--cam.monitor-response`.
RESPONSE_KEY = "monitor"


def response_entry(scored: StepScore | None) -> dict[str, Any]:
    """What a response carries of its call's score: {"score": the step's score (None where the monitor could not
    score it), "flag": whether the connection is flagged as of this call}."""
    if scored is None or scored.score is None:
        return {"score": None, "flag": None}
    return {"score": scored.score if math.isfinite(scored.score) else None, "flag": bool(scored.flag)}


class LiveMonitor:
    """A monitor over a server's connections. Thread-safe: a connection's calls are scored in the order it made
    them (the server answers one request of a connection at a time), by whichever thread scores."""

    def __init__(self, monitor: Monitor, source: str) -> None:
        self.monitor = monitor
        self.source = source  # the monitor file's name, for `/stats` and messages
        self.horizon = execution_horizon(monitor)
        self._lock = threading.Lock()
        self._streams: dict[str, Stream] = {}
        self._scored = 0
        self._flagged = 0  # connections that have been flagged, open or closed
        self._untrained: set[str] = set()  # open connections served under an instruction the policy never learnt
        self._untrained_count = 0  # such connections, open or closed

    def check(self, signals: Mapping[str, np.ndarray], prompt: str) -> None:
        """Raises ValueError (one line naming the monitor file and the input) when a call with these signals cannot
        be scored: the monitor reads an input the served model does not give, or one of another width."""
        try:
            Stream(self.monitor, self.horizon).step(signals, prompt=prompt)
        except ValueError as e:
            raise ValueError(f"monitor {self.source}: {e}") from None

    def score(self, connection: str, signals: Mapping[str, np.ndarray], prompt: str) -> StepScore:
        """Scores the connection's next call, served under `prompt` (raises ValueError as `Stream.step` does)."""
        with self._lock:
            stream = self._streams.get(connection)
            if stream is None:
                stream = self._streams[connection] = Stream(self.monitor, self.horizon)
            was_flagged = stream.flagged
            scored = stream.step(signals, prompt=prompt)
            self._scored += 1
            self._flagged += int(stream.flagged and not was_flagged)
            untrained = connection not in self._untrained and self.monitor.trust(prompt) == UNTRAINED
            if untrained:
                self._untrained.add(connection)
                self._untrained_count += 1
        if untrained:  # why the connection is flagged, once: no score of its says it
            log.warning(
                "monitor %s: connection %s is served under %r, an instruction the policy was not trained on%s",
                self.source,
                connection,
                prompt[:200],  # the client's text: bounded in the log
                " (flagged)" if scored.flag else "",
            )
        return scored

    def closed(self, connection: str) -> None:
        """The connection ended: its stream (its episode) is over."""
        with self._lock:
            self._streams.pop(connection, None)
            self._untrained.discard(connection)

    def stats(self) -> dict[str, Any]:
        """The `/stats` counters: calls scored, connections flagged (ever, and among those open now)."""
        with self._lock:
            open_flagged = sum(s.flagged for s in self._streams.values())
            streams = len(self._streams)
            scored, flagged, untrained = self._scored, self._flagged, self._untrained_count
        threshold = self.monitor.threshold
        return {
            "file": self.source,
            "kind": self.monitor.kind,
            "threshold": threshold if math.isfinite(threshold) else None,
            "execution_horizon": self.horizon,
            "calls_scored": scored,
            "connections_flagged": flagged,
            "connections_open": streams,
            "connections_open_flagged": open_flagged,
            "connections_untrained": untrained,
        }
