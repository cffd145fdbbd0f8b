"""Atomic checkpoints of an optimisation run (a pickle, written by ``optimize`` between generations).

A checkpoint holds the whole state needed to continue: the strategy (pycma's ``CMAEvolutionStrategy``
with its random state), the score cache, the evaluated samples, the history and counters, plus the
run's setup, so that a resume with a different setup is refused. It is written to ``<path>.tmp``,
flushed and fsync'ed, then moved over ``<path>`` with ``os.replace``: a run killed at any moment leaves
either the previous checkpoint or the new one, never a torn file.

A checkpoint may also hold a batch the strategy has proposed but not yet been told the scores of
(``state["asked"]``, written when the objective raised): the resumed run scores that batch first, as the
interrupted run would have.

Between writes the optimiser keeps a ``snapshot`` of the state after each generation: no pickle, only
the lengths of the parts that grow by appending (the cache, the scores, the history) and references to
the rest, which the optimiser replaces rather than changes. ``write_snapshot`` pickles the state the
snapshot describes when a checkpoint is due.

Checkpoints are pickles: load only files you wrote yourself.
"""

from __future__ import annotations

import os
import pickle
from itertools import islice
from pathlib import Path

__all__ = ["save_checkpoint", "load_checkpoint", "snapshot", "snapshot_state", "write_snapshot", "CHECKPOINT_FORMAT"]

#: 2: may hold a proposed batch not yet told (``asked``); format 1 files (older, without one) are read too
CHECKPOINT_FORMAT = 2
_READABLE = (1, 2)
#: the parts of an optimisation state that only ever grow by appending: a snapshot keeps their lengths
APPENDED = ("cache", "F", "P", "history")


def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` atomically to ``path``."""
    return _write(path, pickle.dumps({**state, "format": CHECKPOINT_FORMAT}, protocol=pickle.HIGHEST_PROTOCOL))


def snapshot(state: dict) -> dict:
    """A record of ``state`` as it is now, for ``write_snapshot`` later: the lengths of its ``APPENDED``
    parts and references to its other values (no copy: microseconds, whatever the size of the state).

    Valid while the state's owner only appends to the ``APPENDED`` parts and replaces (never changes in
    place) every other value, as ``optimize`` does; the strategy, changed in place by each ask and tell,
    is written as it is when ``write_snapshot`` runs, so its caller decides whether that matches.
    """
    return {"values": {k: v for k, v in state.items() if k not in APPENDED},
            "lengths": {k: len(state[k]) for k in APPENDED}}


def snapshot_state(snap: dict, state: dict, **changes) -> dict:
    """The state ``snap`` recorded, rebuilt from ``state`` (the same run, later), with ``changes`` on top."""
    out = dict(snap["values"])
    for k, n in snap["lengths"].items():
        v = state[k]
        out[k] = dict(islice(v.items(), n)) if isinstance(v, dict) else v[:n]
    out.update(changes)
    return out


def write_snapshot(path, snap: dict, state: dict, **changes) -> Path:
    """Write the state ``snap`` recorded (see ``snapshot_state``) atomically to ``path``."""
    return save_checkpoint(path, snapshot_state(snap, state, **changes))


def _write(path, data: bytes) -> Path:
    """Write ``data`` atomically to ``path`` (temporary file, fsync, rename)."""
    path = Path(path)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def load_checkpoint(path) -> dict:
    """Read a checkpoint written by ``save_checkpoint``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a place3d checkpoint of a known format.
    """
    path = Path(path)
    with open(path, "rb") as f:
        try:
            state = pickle.load(f)
        except Exception as e:  # truncated or foreign file
            raise ValueError(f"{path} is not a readable optimisation checkpoint ({type(e).__name__}: {e}); "
                             f"delete it or start with resume=False") from None
    if not isinstance(state, dict) or state.get("format") not in _READABLE:
        raise ValueError(f"{path} is not an optimisation checkpoint of format {' or '.join(map(str, _READABLE))}; "
                         f"delete it or start with resume=False")
    return state
