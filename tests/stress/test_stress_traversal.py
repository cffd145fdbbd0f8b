"""Property-based stress tests of voxel traversal / coverage against the reference (docs/architecture.md, Kernel contract).

Grids offset by up to 1e6 m, voxels from 1 cm to 2 m, rays up to 500 m, adversarial directions
(axis-parallel, -0.0 components, exact diagonals, near-axis), origins on voxel faces, edges and corners,
inside and outside the grid, t_end = 0 and inf. Each hypothesis example is one grid and a batch of rays,
so each backend is launched once per example. The number of voxels a ray can visit is bounded by
nx + ny + nz <= ~50k, which keeps the Python reference fast.
"""

from __future__ import annotations

import numpy as np
import pytest
from checks import assert_visits_close
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import place3d_kernels as p3k

SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), print_blob=True)
NEG0 = np.copysign(0.0, -1.0)

VOXELS = st.sampled_from([0.01, 0.02, 0.05, 0.1, 0.2, 0.25, 0.3, 0.5, 1.0, 1.5, 2.0]) | st.floats(0.01, 2.0)
OFFSETS = st.sampled_from([0.0, 1e6, -1e6, 123456.789, -0.5, 1e5]) | st.floats(-1e6, 1e6)


@st.composite
def grids(draw):
    s = draw(VOXELS)
    lower = np.array([draw(OFFSETS) for _ in range(3)])
    long_axis = draw(st.integers(0, 2))
    # one long axis (up to 500 m and up to 50k voxels), the others short: n_voxels <= ~1e6
    n_long = draw(st.integers(1, max(1, min(50_000, int(500.0 / s)))))
    shape = [draw(st.integers(1, 40)) for _ in range(3)]
    shape[long_axis] = n_long
    if shape[0] * shape[1] * shape[2] > 1_000_000:
        shape[(long_axis + 1) % 3] = max(1, 1_000_000 // (n_long * shape[(long_axis + 2) % 3]))
    upper = lower + np.array(shape) * s
    return p3k.Grid(lower=tuple(lower), upper=tuple(upper), voxel_size=s)


def _direction(draw, long_axis):
    kind = draw(st.sampled_from(["random", "axis", "plane", "diag3", "diag2", "near_axis", "along_long"]))
    if kind == "random":
        d = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
        if not np.any(np.abs(d) > 1e-3):
            d = np.array([1.0, 0.5, 0.25])
    elif kind == "axis":
        d = np.array([draw(st.sampled_from([0.0, NEG0])) for _ in range(3)])
        d[draw(st.integers(0, 2))] = draw(st.sampled_from([1.0, -1.0]))
    elif kind == "plane":
        d = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
        d[draw(st.integers(0, 2))] = draw(st.sampled_from([0.0, NEG0]))
        if not np.any(np.abs(d) > 1e-3):
            d = np.array([NEG0, 1.0, -1.0])
    elif kind == "diag3":
        d = np.array([draw(st.sampled_from([1.0, -1.0])) for _ in range(3)])
    elif kind == "diag2":
        d = np.array([draw(st.sampled_from([1.0, -1.0])) for _ in range(3)])
        d[draw(st.integers(0, 2))] = draw(st.sampled_from([0.0, NEG0]))
    elif kind == "near_axis":
        d = np.array([draw(st.sampled_from([1e-12, -1e-9, 1e-6, -1e-4, 0.0, NEG0, 1e-300])) for _ in range(3)])
        d[draw(st.integers(0, 2))] = draw(st.sampled_from([1.0, -1.0]))
    else:  # along the long axis with a small slope: tiny voxels on a long ray
        d = np.array([draw(st.floats(-2e-3, 2e-3)) for _ in range(3)])
        d[long_axis] = draw(st.sampled_from([1.0, -1.0]))
    n = np.linalg.norm(d)
    # keep exact signed zeros: dividing 0.0 / n keeps the sign
    return d / n


def _origin(draw, grid):
    s = grid.voxel_size
    shape = np.array(grid.shape)
    lo = np.asarray(grid.lower)
    kind = draw(st.sampled_from(["inside", "face", "edge", "corner", "boundary", "outside"]))
    frac = np.array([draw(st.floats(0, 1, exclude_max=True)) for _ in range(3)])
    ijk = np.array([draw(st.integers(0, int(n))) for n in shape], dtype=float)
    if kind == "inside":
        local = (np.minimum(ijk, shape - 1) + frac) * s
    elif kind in ("face", "edge", "corner"):
        on = {"face": 1, "edge": 2, "corner": 3}[kind]
        axes = draw(st.permutations([0, 1, 2]))[:on]
        f = frac.copy()
        f[list(axes)] = 0.0
        local = (np.minimum(ijk, shape - (f > 0)) + f) * s
    elif kind == "boundary":  # on the grid's outer box, a face / edge / corner of it
        local = (np.minimum(ijk, shape - 1) + frac) * s
        for a in draw(st.sets(st.integers(0, 2), min_size=1)):
            local[a] = draw(st.sampled_from([0.0, float(shape[a])])) * s
    else:
        margin = draw(st.floats(0.0, 50.0))
        local = (frac * (shape + 6) - 3) * s + np.array([draw(st.sampled_from([-margin, 0.0, margin]))
                                                          for _ in range(3)])
    return lo + local


@st.composite
def scenes(draw, n_rays=(1, 16)):
    grid = draw(grids())
    long_axis = int(np.argmax(grid.shape))
    n = draw(st.integers(*n_rays))
    o = np.array([_origin(draw, grid) for _ in range(n)])
    d = np.array([_direction(draw, long_axis) for _ in range(n)])
    t_end = np.array([draw(st.sampled_from([0.0, np.inf, 500.0, 200.0]) | st.floats(0.0, 500.0))
                      for _ in range(n)])
    return grid, o, d, t_end


def _check_csr(tr, n, grid):
    assert tr.offsets.shape == (n + 1,)
    assert tr.offsets[0] == 0 and np.all(np.diff(tr.offsets) >= 0)
    assert len(tr.voxels) == tr.offsets[-1]
    if len(tr.voxels):
        assert tr.voxels.min() >= 0 and tr.voxels.max() < grid.n_voxels
    # a ray crosses at most nx + ny + nz - 2 voxels (each step changes one index by one)
    assert np.all(np.diff(tr.offsets) <= sum(grid.shape))


@settings(max_examples=600, **SETTINGS)
@given(scenes())
def _traverse_property(backend, case):
    grid, o, d, t_end = case
    got = p3k.traverse(grid, o, d, t_end, backend=backend)
    want = p3k.traverse(grid, o, d, t_end, backend="reference")
    _check_csr(got, len(o), grid)
    te = np.where(np.isfinite(t_end), t_end, 1e9)
    for i in range(len(o)):
        g, w = got.ray(i), want.ray(i)
        if t_end[i] == 0:
            assert len(g) == 0, f"t_end = 0 visited {g}"
        ctx = f"ray {i}: grid {grid}, o={o[i].tolist()}, d={d[i].tolist()}, t_end={t_end[i]!r}"
        try:
            assert_visits_close(grid, o[i], d[i], te[i], g, w)
        except AssertionError as e:
            raise AssertionError(f"{e}\n{ctx}\n got {g.tolist()[:20]}... ({len(g)})\n want {w.tolist()[:20]}... "
                                 f"({len(w)})") from None
        if set(g.tolist()) == set(w.tolist()):
            # same voxels -> same visit order (order along the ray is unique)
            np.testing.assert_array_equal(g, w, err_msg=f"visit order differs; {ctx}")
    # coverage is the union of the same backend's visits
    cov = p3k.coverage(grid, o, d, t_end, backend=backend).reshape(-1)
    union = np.zeros(grid.n_voxels, dtype=bool)
    union[got.voxels] = True
    np.testing.assert_array_equal(cov, union)


def test_traverse_stress(device_backend):
    _traverse_property(device_backend)


def test_reference_visits_are_exact():
    """The oracle itself, checked against the exact geometry on the same adversarial inputs."""

    @settings(max_examples=100, **SETTINGS)
    @given(scenes(n_rays=(1, 6)))
    def prop(case):
        grid, o, d, t_end = case
        want = p3k.traverse(grid, o, d, t_end, backend="reference")
        _check_csr(want, len(o), grid)
        te = np.where(np.isfinite(t_end), t_end, 1e9)
        # every voxel the segment passes through by more than 0.1 mm is visited, nothing farther away
        for i in range(len(o)):
            w = want.ray(i)
            s = grid.voxel_size
            local = grid.to_local(o[i])
            # candidate voxels: those whose box the segment comes near (sample densely along the ray)
            assert_visits_close(grid, o[i], d[i], te[i], w, _sampled_voxels(grid, local, d[i], te[i], s))

    prop()


def _sampled_voxels(grid, local, d, t_end, s):
    """Voxels containing sample points along the clipped segment: a lower bound on the true visit set,
    with points near voxel boundaries dropped so they never count (the checker tolerates those)."""
    size = np.array(grid.shape) * s
    t0, t1 = 0.0, t_end
    for a in range(3):
        if d[a] == 0:
            if not 0 <= local[a] <= size[a]:
                return np.empty(0, np.int64)
            continue
        ta, tb = (0 - local[a]) / d[a], (size[a] - local[a]) / d[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    if not t1 > t0:
        return np.empty(0, np.int64)
    n = int(min(200_000, max(2, 8 * (t1 - t0) / s)))
    t = np.linspace(t0, t1, n)
    p = local + t[:, None] * d
    f = p / s
    keep = np.all(np.abs(f - np.round(f)) > 2e-4 / s, axis=1)
    ijk = np.floor(f[keep]).astype(np.int64)
    ijk = np.clip(ijk, 0, np.array(grid.shape) - 1)
    return np.unique(grid.flat(ijk))


@settings(max_examples=80, **SETTINGS)
@given(scenes(n_rays=(1, 8)), st.floats(0.001, 0.2), st.integers(0, 2**31 - 1))
def _stop_property(backend, case, density, seed):
    grid, o, d, t_end = case
    if grid.n_voxels > 300_000:
        return
    stop = (np.random.default_rng(seed).uniform(size=grid.n_voxels) < density).astype(np.uint8)
    full = p3k.traverse(grid, o, d, t_end, backend=backend)
    cut = p3k.traverse(grid, o, d, t_end, backend=backend, stop=stop)
    ref = p3k.traverse(grid, o, d, t_end, backend="reference", stop=stop)
    for i in range(len(o)):
        f, c = full.ray(i), cut.ray(i)
        hit = np.flatnonzero(stop[f])
        expect = f[: hit[0] + 1] if hit.size else f
        np.testing.assert_array_equal(c, expect, err_msg=f"stop mask is not a prefix cut; ray {i}")
        r = ref.ray(i)
        if set(full.ray(i).tolist()) == set(p3k.traverse(grid, o[i:i + 1], d[i:i + 1], t_end[i:i + 1],
                                                          backend="reference").voxels.tolist()):
            np.testing.assert_array_equal(c, r, err_msg=f"stop differs from reference on ray {i}")
    cov = p3k.coverage(grid, o, d, t_end, backend=backend, stop=stop).reshape(-1)
    union = np.zeros(grid.n_voxels, dtype=bool)
    union[cut.voxels] = True
    np.testing.assert_array_equal(cov, union)


def test_stop_mask_stress(device_backend):
    _stop_property(device_backend)


# ------------------------------------------------------------------------------ bad inputs
@pytest.mark.parametrize("field, value", [("o", np.nan), ("o", np.inf), ("o", -np.inf), ("d", np.nan),
                                          ("d", np.inf), ("d", -np.inf), ("t", np.nan), ("t", -1.0)])
def test_nan_inf_rejected(backend, field, value):
    grid = p3k.Grid(lower=(1e6, -1e6, 0), upper=(1e6 + 4, -1e6 + 4, 4), voxel_size=0.5)
    o = np.array([[1e6 + 1, -1e6 + 1, 1.0]] * 3)
    d = np.array([[1.0, 0.0, 0.0]] * 3)
    t = np.array([1.0, 2.0, 3.0])
    {"o": o, "d": d, "t": t}[field][2 if field == "t" else (2, 1)] = value
    for fn in (p3k.traverse, p3k.coverage):
        with pytest.raises(ValueError):
            fn(grid, o, d, t, backend=backend)
