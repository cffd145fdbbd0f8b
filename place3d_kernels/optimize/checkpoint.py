"""Checkpoints of an optimisation run: data only (JSON and NumPy arrays), verified by content before use.

A checkpoint holds what is needed to continue a run exactly: its setup (a resume with another setup is
refused), the evaluated samples (grid point, score, penalty: the score cache), the history, the counters,
the incumbent, and the strategy's *log*: every batch it proposed (``ask``) and every set of values it was
told (``tell``), in order. The strategy itself (pycma's ``CMAEvolutionStrategy``) is not stored: a resumed
run builds a fresh one from the setup and replays the log, checking that every replayed ``ask`` proposes
bit for bit the batch the log holds; if one does not (another pycma or NumPy), the checkpoint is refused
rather than continued differently. Replaying is also what makes a resumed run equal to an uninterrupted
one: pycma keys its record of proposed solutions by ``hash(bytes)``, which Python salts per process, so a
pickled strategy continued in another process looked its own solutions up in vain and drifted off.

File layout (format 3)::

    PLACE3D-CHECKPOINT 3\\n
    <sha256 of the payload, 64 hex digits>\\n
    <payload: an uncompressed .npz: meta.npy (JSON text) and numeric arrays, read with allow_pickle=False>

The digest covers every byte after it, and a file whose first line differs is not read at all, so any
damaged byte is refused with a message (never a traceback, never a silently different run). The file is
written by ``atomic.atomic_write`` (temporary file, fsync, rename): a run killed at any moment leaves the
previous checkpoint or the new one. Checkpoints of earlier versions were pickles, which can run code
when loaded; they are recognised and refused unread (``LegacyCheckpointError``).

A checkpoint may also hold a batch the strategy has proposed but not yet been told the scores of
(``state["asked"]``, written when the objective raised): the resumed run scores that batch first, as the
interrupted run would have.

Between writes the optimiser keeps a ``snapshot`` of the state after each generation: only the lengths
of the parts that grow by appending (the cache, the scores, the history, the log) and references to the
rest, which the optimiser replaces rather than changes. ``write_snapshot`` writes the state the snapshot
describes when a checkpoint is due.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from itertools import islice
from pathlib import Path

import numpy as np

from place3d_kernels.atomic import atomic_write

__all__ = ["save_checkpoint", "load_checkpoint", "snapshot", "snapshot_state", "write_snapshot", "replay",
           "CHECKPOINT_FORMAT", "CheckpointError", "LegacyCheckpointError", "encode", "decode"]

CHECKPOINT_FORMAT = 3
MAGIC = b"PLACE3D-CHECKPOINT 3\n"
#: the parts of an optimisation state that only ever grow by appending: a snapshot keeps their lengths
APPENDED = ("cache", "F", "P", "history", "log")
FRESH_RUN_HINT = "start a fresh run (place3d optimize without --resume, with --overwrite or into a fresh folder; " \
                 "in Python resume=False)"


class CheckpointError(ValueError):
    """A checkpoint that is not read: damaged, foreign, or of a format this version does not read."""


class LegacyCheckpointError(CheckpointError):
    """A pickle checkpoint of an earlier version (refused unread: loading a pickle can run code)."""


def _legacy(path) -> str:
    return (f"{path} is a pickle checkpoint of an earlier place3d version; it is not read, because loading a "
            f"pickle can run any code its author put in it; {FRESH_RUN_HINT}")


# ------------------------------------------------------------------------------ encoding
def _npy(a) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(a), allow_pickle=False)
    return buf.getvalue()


def _f(v):
    return None if v is None else float(v)


def encode(state: dict) -> bytes:
    """The file bytes of ``state`` (see the module's docstring)."""
    keys = list(state["cache"])
    X = (np.frombuffer(b"".join(keys), dtype=np.float64).reshape(len(keys), -1) if keys
         else np.zeros((0, 0)))
    log = state.get("log") or []
    asks = [v for k, v in log if k == "a"]
    tells = [v for k, v in log if k == "t"]
    d = asks[0].shape[1] if asks else (0 if state.get("asked") is None else state["asked"]["K"].shape[1])
    best = state.get("best")
    asked = state.get("asked")
    meta = {
        "format": CHECKPOINT_FORMAT, "setup": state["setup"], "history": state["history"],
        "evaluations": int(state["evaluations"]), "generation": int(state["generation"]),
        "hits": int(state["hits"]), "stall": int(state["stall"]), "nonfinite": int(state["nonfinite"]),
        "worst_G": _f(state["worst_G"]), "seconds": float(state["seconds"]), "stop_reason": state["stop_reason"],
        "strategy_calls": int(state.get("strategy_calls", 0)), "log": "".join(k for k, _ in log),
        "best": None if best is None else {"rank": [int(best["rank"][0]), float(best["rank"][1])],
                                           "F": float(best["F"]), "G": float(best["G"]), "P": float(best["P"])},
        "asked": None if asked is None else {"sigma": _f(asked["sigma"])},
    }
    arrays = {
        "meta": np.array(json.dumps(meta)),
        "X": X, "F": np.asarray(state["F"], np.float64), "P": np.asarray(state["P"], np.float64),
        "U": np.asarray(state["U"], np.float64),
        "ask_rows": np.array([len(a) for a in asks], np.int64),
        "ask_K": np.concatenate(asks) if asks else np.zeros((0, d)),
        "tell_n": np.array([len(t) for t in tells], np.int64),
        "tell_G": np.concatenate(tells) if tells else np.zeros(0),
    }
    if best is not None:
        arrays["best_X"], arrays["best_U"] = np.asarray(best["X"], np.float64), np.asarray(best["U"], np.float64)
    if asked is not None:
        arrays["asked_K"] = np.asarray(asked["K"], np.float64)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, a in arrays.items():
            zf.writestr(f"{name}.npy", _npy(a))
    payload = buf.getvalue()
    return MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload


def decode(data: bytes, path="checkpoint") -> dict:
    """The state ``encode`` wrote (without a strategy: ``replay`` rebuilds it), checked byte for byte.

    Raises:
        LegacyCheckpointError: a pickle (an earlier version's checkpoint).
        CheckpointError: anything else that is not an intact format-3 checkpoint.
    """
    if data[:1] == b"\x80" or data[:1] in (b"(", b"}", b"]") and data.rstrip()[-1:] == b".":
        raise LegacyCheckpointError(_legacy(path))
    if not data.startswith(MAGIC):
        raise CheckpointError(f"{path} is not a place3d checkpoint of format {CHECKPOINT_FORMAT} (its first line "
                              f"differs: damaged, or another kind of file); {FRESH_RUN_HINT}")
    head = len(MAGIC)
    digest, payload = data[head:head + 64], data[head + 65:]
    if data[head + 64:head + 65] != b"\n" or hashlib.sha256(payload).hexdigest().encode() != digest:
        raise CheckpointError(f"{path} is damaged (its content does not match the sha256 it was written with); "
                              f"{FRESH_RUN_HINT}")
    try:
        return _state(payload)
    except Exception as e:  # noqa: BLE001 - an intact digest over a malformed body: written by something else
        raise CheckpointError(f"{path} is not a readable place3d checkpoint ({type(e).__name__}: {e}); "
                              f"{FRESH_RUN_HINT}") from None


def _state(payload: bytes) -> dict:
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(str(a["meta"]))
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"format {meta.get('format')!r}")
    X, F, P = a["X"], a["F"], a["P"]
    if not (len(X) == len(F) == len(P)) or X.dtype != np.float64:
        raise ValueError("sample arrays of different lengths")
    log, ai, ti, ao, to = [], 0, 0, 0, 0
    for kind in meta["log"]:
        if kind == "a":
            n = int(a["ask_rows"][ai])
            log.append(("a", a["ask_K"][ao:ao + n]))
            ai, ao = ai + 1, ao + n
        elif kind == "t":
            n = int(a["tell_n"][ti])
            log.append(("t", a["tell_G"][to:to + n]))
            ti, to = ti + 1, to + n
        else:
            raise ValueError(f"log entry {kind!r}")
    if ai != len(a["ask_rows"]) or ti != len(a["tell_n"]) or ao != len(a["ask_K"]) or to != len(a["tell_G"]):
        raise ValueError("log arrays do not match the log")
    b = meta["best"]
    best = None if b is None else {"rank": (int(b["rank"][0]), float(b["rank"][1])), "X": a["best_X"],
                                   "U": a["best_U"], "F": float(b["F"]), "G": float(b["G"]), "P": float(b["P"])}
    asked = None if meta["asked"] is None else {"K": a["asked_K"], "sigma": meta["asked"]["sigma"]}
    return {"setup": meta["setup"], "cache": {row.tobytes(): float(f) for row, f in zip(X, F)},
            "U": a["U"], "F": F.tolist(), "P": P.tolist(), "history": meta["history"], "log": log,
            "evaluations": int(meta["evaluations"]), "generation": int(meta["generation"]),
            "hits": int(meta["hits"]), "stall": int(meta["stall"]), "nonfinite": int(meta["nonfinite"]),
            "worst_G": meta["worst_G"], "best": best, "seconds": float(meta["seconds"]),
            "stop_reason": meta["stop_reason"], "asked": asked, "strategy_calls": int(meta["strategy_calls"]),
            "format": CHECKPOINT_FORMAT}


# ------------------------------------------------------------------------------ files
def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` atomically to ``path``."""
    return atomic_write(path, encode(state), fsync=True)


def load_checkpoint(path) -> dict:
    """Read a checkpoint written by ``save_checkpoint`` (every byte checked first; nothing is unpickled).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError (a ``ValueError``): damaged, foreign, or an earlier version's pickle.
    """
    path = Path(path)
    return decode(path.read_bytes(), path)


def replay(strategy, log, asked, path="checkpoint") -> None:
    """Bring a fresh ``strategy`` to the state of the run that wrote ``log``: its asks and tells in order,
    each ask checked to give bit for bit the logged batch (``stop`` is asked before each, as the run does).
    A pending batch (``asked``) is asked again and checked too.

    Raises:
        CheckpointError: a replayed ask proposed another batch than the logged one.
    """
    n_ask = 0
    for kind, v in list(log) + ([("a", asked["K"])] if asked is not None else []):
        if kind == "t":
            strategy.tell(v)
            continue
        strategy.stop()
        K = strategy.ask()
        n_ask += 1
        if K.shape != v.shape or K.tobytes() != np.ascontiguousarray(v, np.float64).tobytes():
            raise CheckpointError(
                f"{path}: replaying the run's strategy did not reproduce its batch {n_ask} (another version of "
                f"pycma or NumPy than the one that wrote it?), so the run cannot continue as it would have; "
                f"{FRESH_RUN_HINT}")


# ------------------------------------------------------------------------------ snapshots
def snapshot(state: dict) -> dict:
    """A record of ``state`` as it is now, for ``write_snapshot`` later: the lengths of its ``APPENDED``
    parts and references to its other values (no copy: microseconds, whatever the size of the state).

    Valid while the state's owner only appends to the ``APPENDED`` parts and replaces (never changes in
    place) every other value, as ``optimize`` does.
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


# ------------------------------------------------------------------------------ earlier versions
#: the checkpoint name ``place3d optimize --output DIR`` used before checkpoints were data only
LEGACY_NAME = "checkpoint.pkl"
#: the checkpoint name it uses now
DEFAULT_NAME = "checkpoint.ckpt"


def refuse_legacy(*paths) -> None:
    """Raise ``LegacyCheckpointError`` when one of ``paths`` (None ones skipped) is an earlier version's
    pickle checkpoint (read: its first bytes only)."""
    for p in paths:
        if p is None or not Path(p).is_file():
            continue
        with open(p, "rb") as f:
            head = f.read(len(MAGIC))
        if head != MAGIC and (head[:1] == b"\x80" or Path(p).suffix == ".pkl"):
            raise LegacyCheckpointError(_legacy(p))
