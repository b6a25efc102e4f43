"""Nested dicts <-> flat dicts with '/'-joined keys (upstream's convention for params and observations)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def flatten_dict(tree: Mapping[str, Any], sep: str = "/") -> dict[str, Any]:
    """Nested dicts -> one dict with ``a/b/c`` keys; an empty dict stays a leaf."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        if isinstance(v, Mapping) and v:
            for sub_k, sub_v in flatten_dict(v, sep).items():
                out[f"{k}{sep}{sub_k}"] = sub_v
        else:
            out[k] = v
    return out


def unflatten_dict(flat: Mapping[str, Any], sep: str = "/") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in flat.items():
        *parents, leaf = k.split(sep)
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = v
    return out
