"""Test helpers shared by the left-out field tests (test_left_out.py, test_opencl_fields.py): count rows where the
order of addition shows, and what a prepared grid holds on each backend."""

from __future__ import annotations

import numpy as np

from place3d_kernels.classes import N_CLASSES, VEHICLE
from place3d_kernels.left_out import FieldTables


def wide_rows(task: str, R: int, seed: int = 4):
    """Rows whose T = 81 subsets spread over all 22 channels (many terms per row, where the order of addition
    shows), one occupied entry taken out of each, the rows that still fit T kept: (the arguments of
    ``Backend.left_out_fields`` but the scale, the host's left-out rows, their ``FieldTables``)."""
    rng = np.random.default_rng(seed)
    T = 81
    counts = np.stack([np.bincount(rng.integers(0, N_CLASSES, T + 3), minlength=N_CLASSES) for _ in range(R)])
    cls = np.array([1 + int(np.flatnonzero(r[1:])[0]) for r in counts])       # one occupied class per row
    cnt = np.minimum(counts[np.arange(R), cls], rng.integers(1, 4, R))
    rows = counts.copy()
    rows[np.arange(R), cls] -= cnt
    keep = rows[:, 1:].sum(axis=1) <= T                                       # rows that fit T subsets
    counts, cls, cnt, rows = counts[keep], cls[keep], cnt[keep], rows[keep]
    rows[:, 0] = T - rows[:, 1:].sum(axis=1)
    tb = FieldTables(T, task)
    n = len(counts)
    args = (counts.astype(np.int32), np.arange(n), np.arange(n + 1), cls, cnt, np.zeros(n, dtype=np.int32),
            np.array([T]), tb.term[None], tb.stop[None].astype(np.uint8),
            tb.other[None] if task == "det" else np.zeros((1, 1, 1)), task == "det", VEHICLE)
    return args, rows, tb


def exact_terms(task: str, rows: np.ndarray, tb: FieldTables) -> np.ndarray:
    """Each row's entropy times 2**60 rounded (every bit of H shows; H <= ln 22 < 8, so it fits an int64): NumPy's
    sum of the row's table terms."""
    if task == "seg":
        terms = tb.term[rows]
    else:
        c0, cv = rows[:, 0], rows[:, VEHICLE]
        terms = np.stack([tb.term[c0], tb.term[cv], tb.other[c0, cv]], axis=1)
    return np.rint(terms.sum(axis=-1) * 2.0**60).astype(np.int64)


def grid_arrays(b, h) -> list:
    """The arrays a grid handle holds, by backend: what score_placements reads."""
    if b.name == "reference":
        return [h.weights, h.stop]
    if b.name.startswith("warp:"):              # weights and the brick masks (flat masks too on CUDA)
        return [h.weights.numpy(), h.masks.numpy(), None if h.flat is None else h.flat.numpy()]
    n = h.spec.n_voxels
    out = [b._read(h.weights, np.int64, n)]
    if h.masks is not None and b.score_strategy == "atomic":
        out.append(b._read(h.masks, np.uint32, h.masks.size // 4))
        out.append(None if h.flat is None else b._read(h.flat, np.uint64, h.flat.size // 8))
    else:
        words = h.nonzero.size // 4
        out.append(b._read(h.nonzero, np.uint32, words))
        if h.use_stop:
            out += [b._read(h.stop, np.uint8, n), b._read(h.stop_bits, np.uint32, words)]
    return out


def same_arrays(a: list, b: list) -> bool:
    """Two ``grid_arrays`` lists hold the same arrays (or both None) bit for bit."""
    return len(a) == len(b) and all((u is None and v is None) or (u is not None and v is not None
                                                                  and u.tobytes() == v.tobytes()) for u, v in zip(a, b))
