"""A training run's state between two steps, so that a run stopped on a machine whose jobs end continues elsewhere.

`--save-every N` writes it every N steps, and a SIGTERM or SIGINT makes the run write it after the step under way and
stop; `--resume` continues from it and ends with the very params the unstopped run ends with (the same batches, noise
draws and schedule position: everything that decides a step is in the state or follows from the step's index). The
state is one file, `<out>/train_state.npz`, replaced atomically; it names the run that wrote it (its flags and a digest
of its data) and a different run refuses it. A finished run removes it: its result is the checkpoint.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import threading
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

FILE = "train_state.npz"
# Flags a resumed run may set otherwise than the stopped one: none of them decides what a step computes (the state
# found in --out is that folder's, wherever it was moved).
FREE_FLAGS = ("out", "resume", "save_every", "log_every", "probe_every", "eval_episodes")


class StateError(ValueError):
    """A state that cannot be resumed: absent, unreadable, or another run's (the message names the file)."""


class Stopped(Exception):
    """The run stopped on a signal after saving its state (the message says where and how to continue)."""


def path(out: Path) -> Path:
    return out / FILE


@dataclasses.dataclass
class Saved:
    """A state as read back: where the run was, and its arrays, shaped when `restore` is given their structure."""

    phase: str
    step: int  # the phase's steps done
    rng: dict[str, Any]  # the batch sampler's numpy bit generator state
    losses: list[float]  # the phase's losses so far
    leaves: list[np.ndarray]  # params, then optimizer state, flattened
    source: Path | None = None  # the file it was read from (named by `restore`'s refusals)

    @classmethod
    def capture(
        cls, phase: str, step: int, rng: np.random.Generator, losses: Sequence[Any], params: Any, opt_state: Any
    ) -> Saved:
        """The state after `step` steps of `phase` (host copies: the next step may reuse the arrays' buffers)."""
        leaves = [np.array(x) for x in jax.tree_util.tree_leaves((params, opt_state))]
        return cls(phase, step, rng.bit_generator.state, [float(x) for x in losses], leaves)

    def restore(self, params: Any, opt_state: Any) -> tuple[Any, Any]:
        """(params, optimizer state) with the structure of the given ones; a StateError if shapes or dtypes differ."""
        where = self.source
        template, treedef = jax.tree_util.tree_flatten((params, opt_state))
        if len(template) != len(self.leaves):
            raise StateError(f"{where}: {len(self.leaves)} arrays, this model and optimizer have {len(template)}")
        for i, (want, got) in enumerate(zip(template, self.leaves, strict=True)):
            if tuple(want.shape) != got.shape or np.dtype(want.dtype) != got.dtype:
                raise StateError(
                    f"{where}: array {i} is {got.dtype}{list(got.shape)}, this model's {want.dtype}{list(want.shape)}"
                )
        return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(x) for x in self.leaves])


def save(out: Path, run: dict[str, Any], state: Saved) -> Path:
    """Writes `state` for `run`, replacing any earlier one at once (a crash while writing leaves the earlier one)."""
    meta = {"run": run, "phase": state.phase, "step": state.step, "rng": state.rng, "losses": state.losses}
    target = path(out)
    partial = target.with_name(target.name + ".partial")
    with open(partial, "wb") as f:
        np.savez(f, meta=np.array(json.dumps(meta)), **{f"leaf_{i:05d}": x for i, x in enumerate(state.leaves)})
    os.replace(partial, target)
    return target


def read(out: Path, run: dict[str, Any], defaults: dict[str, Any] | None = None) -> Saved:
    """The state in `out`, checked to be the one saved by `run` (a run's flags and data digest; `difference`)."""
    where = path(out)
    if absent := missing(out):
        raise StateError(absent)
    try:
        with np.load(where) as z:
            meta = json.loads(str(z["meta"]))
            leaves = [z[k] for k in sorted(n for n in z.files if n.startswith("leaf_"))]
        phase, step, rng, losses = meta["phase"], int(meta["step"]), meta["rng"], meta["losses"]
        saved_run = meta["run"]
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as e:
        raise StateError(f"{where}: unreadable training state ({type(e).__name__}: {e})") from None
    if differs := difference(saved_run, run, defaults):
        raise StateError(f"{where} was saved by another run ({differs}): resume with the flags and data it had")
    return Saved(phase, step, rng, [float(x) for x in losses], leaves, where)


def missing(out: Path) -> str | None:
    """Why there is nothing in `out` to resume, or None: what a command says before it reads any data."""
    if (where := path(out)).exists():
        return None
    return f"{where}: no saved training state (--save-every N saves one, and so does a stop)"


def difference(saved: dict[str, Any], now: dict[str, Any], defaults: dict[str, Any] | None = None) -> str | None:
    """The first thing that tells two runs apart, in a few words, or None. A flag the saved run did not have yet (a
    later version's) tells nothing when this run leaves it at its `defaults` value."""
    for key in sorted(set(saved) | set(now)):
        if key not in saved and defaults is not None and key in defaults and now.get(key) == defaults[key]:
            continue
        if saved.get(key) != now.get(key):
            return f"{key}: {saved.get(key)!r} there, {now.get(key)!r} here"
    return None


def remove(out: Path) -> None:
    path(out).unlink(missing_ok=True)


class StopRequest:
    """Set by SIGTERM or SIGINT while entered (in the main thread; elsewhere signals are left as they are): the loop
    asks `signum` between steps, so a step under way finishes and its state is saved before the run stops."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def _handle(self, signum: int, frame: Any) -> None:
        self.signum = signum


@contextlib.contextmanager
def stop_request() -> Iterator[StopRequest]:
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = {s: signal.signal(s, request._handle) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield request
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
