"""Websocket serving: the msgpack-numpy wire format, the policy server and `openpi-cam serve`.

Only `RequestContext` lives here so that policies and the CAM wrapper can import it without pulling in websockets.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class RequestContext:
    """Who sent a request: passed by the server as `policy.infer(obs, context)`.

    `connection_id` is unique within one server process and safe to use in file names; `request_index` counts the
    frames received on that connection, from 0, including rejected ones.
    """

    connection_id: str
    request_index: int


__all__ = ["RequestContext"]
