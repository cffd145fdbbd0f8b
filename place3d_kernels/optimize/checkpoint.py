"""Atomic checkpoints of an optimisation run (a pickle, written by ``optimize`` after each generation).

A checkpoint holds the whole state needed to continue: the strategy (pycma's ``CMAEvolutionStrategy``
with its random state), the score cache, the evaluated samples, the history and counters, plus the
run's setup, so that a resume with a different setup is refused. It is written to ``<path>.tmp``,
flushed and fsync'ed, then moved over ``<path>`` with ``os.replace``: a run killed at any moment leaves
either the previous checkpoint or the new one, never a torn file.

Checkpoints are pickles: load only files you wrote yourself.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

__all__ = ["save_checkpoint", "load_checkpoint", "snapshot", "write_snapshot", "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT = 1


def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` atomically to ``path``."""
    return write_snapshot(path, snapshot(state))


def snapshot(state: dict) -> bytes:
    """``state`` as checkpoint bytes (a pickle: taking one is cheap, writing it is not)."""
    return pickle.dumps({"format": CHECKPOINT_FORMAT, **state}, protocol=pickle.HIGHEST_PROTOCOL)


def write_snapshot(path, data: bytes) -> Path:
    """Write ``snapshot`` bytes atomically to ``path`` (temporary file, fsync, rename)."""
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
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not an optimisation checkpoint of format {CHECKPOINT_FORMAT}")
    return state
