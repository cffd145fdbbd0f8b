"""Test helpers: exact float64 geometry to judge visit lists within the 0.1 mm tolerance."""

from __future__ import annotations

import numpy as np

EPS = 1e-4  # 0.1 mm: docs/architecture.md, Kernel contract


def segment_overlap(o, d, t_end, box_lo, box_hi, grid_lo, grid_hi):
    """Length of the part of segment [0, t_end] inside box and grid (float64; 0 when none)."""
    t0, t1 = 0.0, float(t_end)
    for lo, hi in ((box_lo, box_hi), (grid_lo, grid_hi)):
        for a in range(3):
            if d[a] == 0.0:
                if o[a] < lo[a] or o[a] > hi[a]:
                    return 0.0
                continue
            ta, tb = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return max(0.0, t1 - t0)


def voxel_box(grid, flat):
    ijk = grid.unflat(np.array([flat]))[0]
    lo = np.asarray(grid.lower) + ijk * grid.voxel_size
    return lo, lo + grid.voxel_size


def assert_visits_close(grid, o, d, t_end, got, want, eps=EPS):
    """``got`` may differ from ``want`` only by voxels the segment passes within ``eps`` of."""
    got = np.asarray(got)
    assert len(np.unique(got)) == len(got), f"duplicate voxels in visit list {got}"
    glo, ghi = np.asarray(grid.lower), np.asarray(grid.upper)
    for v in set(got.tolist()) - set(np.asarray(want).tolist()):
        lo, hi = voxel_box(grid, v)
        assert segment_overlap(o, d, t_end, lo - eps, hi + eps, glo - eps, ghi + eps) > 0, \
            f"voxel {v} visited but the ray passes farther than {eps} m from it"
    for v in set(np.asarray(want).tolist()) - set(got.tolist()):
        lo, hi = voxel_box(grid, v)
        assert segment_overlap(o, d, t_end, lo + eps, hi - eps, glo + eps, ghi - eps) == 0, \
            f"voxel {v} skipped although the ray passes through its interior by more than {eps} m"


def assert_same_run(a, b):
    """Two ``OptimizeResult``s of the same search: evaluations, best score and rig, and the history with
    its wall-clock fields left out, all equal."""
    assert a.evaluations == b.evaluations
    assert a.best_score == b.best_score
    np.testing.assert_array_equal(a.best_placement.poses, b.best_placement.poses)
    drop = ("seconds", "time")
    assert ([{k: v for k, v in h.items() if k not in drop} for h in a.history]
            == [{k: v for k, v in h.items() if k not in drop} for h in b.history])
