"""M-SOG's denominators (docs/metric-normalisation.md): the names, and the 0/1 indicator grids whose exact
integer sums count the covered voxels that belong in the ``"evidence"`` and ``"uncertain"`` denominators.
Shared by ``metrics`` (grid LiDARs) and ``rig_metrics`` (explicit rays), which import it, not each other."""

from __future__ import annotations

import weakref

import numpy as np

from place3d_kernels.sog import PSOG

__all__ = ["NORMALISATIONS", "INDICATORS", "check_normalisation", "indicator_weights", "indicator_weight_rows",
           "indicator_handle"]

#: Denominators of M-SOG: the paper's N_L, and two that do not reward rays through never-occupied air.
NORMALISATIONS = ("paper", "evidence", "uncertain")
#: Indicator kinds counted by ``coverage_counts``: stored (ever occupied) voxels, voxels with H > 0.
INDICATORS = ("evidence", "uncertain")

# per P-SOG (task variant): {(indicator, backend, occlusion): grid handle}; dies with the P-SOG
_indicator_handles: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def check_normalisation(normalisation: str) -> str:
    """Return ``normalisation`` or raise ValueError naming the choices."""
    if normalisation not in NORMALISATIONS:
        raise ValueError(f"normalisation must be one of {NORMALISATIONS} (docs/metric-normalisation.md), "
                         f"got {normalisation!r}")
    return normalisation


def indicator_weights(p: PSOG, kind: str) -> np.ndarray:
    """(n_voxels,) int64 0/1 weights: stored voxels (``"evidence"``) or voxels with H > 0 (``"uncertain"``).

    Summed by the same integer kernels as the entropy weights, they count covered voxels exactly.
    """
    if kind == "evidence":
        w = np.zeros(p.grid.n_voxels, dtype=np.int64)
        w[p.voxels] = 1
        return w
    if kind == "uncertain":
        # H > 0 in the fixed-point weights the kernels sum: a voxel whose entropy rounds to 0 adds nothing
        return (p.weights > 0).astype(np.int64)
    raise ValueError(f"indicator must be one of {INDICATORS}, got {kind!r}")


def indicator_weight_rows(p: PSOG, kind: str) -> np.ndarray:
    """(M,) int64 0/1: ``indicator_weights(p, kind)`` at the P-SOG's stored voxels (0 everywhere else)."""
    if kind == "evidence":
        return np.ones(len(p.voxels), dtype=np.int64)
    if kind == "uncertain":
        return (p.weight_rows > 0).astype(np.int64)
    raise ValueError(f"indicator must be one of {INDICATORS}, got {kind!r}")


def indicator_handle(p: PSOG, kind: str, b, occlusion: str):
    """The prepared grid of ``indicator_weights(p, kind)`` on backend ``b`` (kept while ``p`` lives), made from
    the stored voxels' rows as ``PSOG.handle`` makes the weights' grid (``Backend.indicator_from_rows``: on
    CUDA filled on the device, no dense host array)."""
    cache = _indicator_handles.setdefault(p, {})
    key = (kind, b, occlusion)
    if key not in cache:
        stop = p.stop_rows if occlusion == "sog" else None
        cache[key] = b.indicator_from_rows(p.grid.spec, p.voxels, indicator_weight_rows(p, kind), stop)
    return cache[key]
