"""Shannon entropy of probability rows, as the P-SOG's weights compute it (``sog.PSOG``) and the left-out
tables mirror it (``left_out_tables``); its own module so that both import it without importing each other."""

from __future__ import annotations

import numpy as np

__all__ = ["entropy", "ENTROPY_BLOCK"]


#: Rows per block in ``entropy``: 8192 rows of 22 float64 channels are 1.4 MB, so a block's temporaries
#: stay in the cache and are reused, where whole-array ones (40 MB on the default town) are fresh memory
#: that every cold process first has to fault in.
ENTROPY_BLOCK = 8192


def entropy(probs: np.ndarray) -> np.ndarray:
    """Shannon entropy (natural log, 0 log 0 = 0) over the last axis, float64."""
    p = np.asarray(probs, dtype=np.float64)
    if p.ndim < 2 or len(p) <= ENTROPY_BLOCK:
        return _entropy_rows(p)
    # each row's entropy depends on that row alone: blocks of rows give the same sums
    out = np.empty(p.shape[:-1], dtype=np.float64)
    for a in range(0, len(p), ENTROPY_BLOCK):
        out[a:a + ENTROPY_BLOCK] = _entropy_rows(p[a:a + ENTROPY_BLOCK])
    return out


def _entropy_rows(p: np.ndarray) -> np.ndarray:
    # logs of the nonzero probabilities only (a small share of a P-SOG's entries): many times faster than
    # a log of every entry, and the same terms in the same places, so the row sums are bit-identical
    nz = p > 0
    terms = np.zeros(p.shape, dtype=np.float64)
    v = p[nz]
    terms[nz] = -v * np.log(v)
    return terms.sum(axis=-1)
