"""The scene builders' shortcuts give what the plain forms give, element for element.

The OpenDRIVE builder takes a few shortcuts for speed (a pooled study builds 32 scenes): parked cars are
copied as bare arrays instead of checked meshes, the fill's ground heights come from one KD-tree query for all
its candidate points, and an unrotated rectangle's raster cells are found per row and per column. Each is
compared here with the form it replaces, on the inputs the builder gives it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from place3d_kernels.data import opendrive_path
from place3d_kernels.scene import opendrive
from place3d_kernels.scene.bodies import vehicle_body, vehicle_mesh
from place3d_kernels.scene.opendrive_roadside import Raster, fill
from place3d_kernels.scene.props import Props


@pytest.mark.parametrize("kind", [None, "car", "van", "truck", "bus"])
def test_a_vehicle_body_is_the_vehicle_meshs_arrays(kind):
    for seed in range(20):
        body, k1 = vehicle_body(np.random.default_rng(seed), kind)
        rng = np.random.default_rng(seed)
        mesh, k2 = vehicle_mesh(rng, kind)
        assert k1 == k2
        assert np.array_equal(body.vertices, mesh.vertices) and body.vertices.dtype == mesh.vertices.dtype
        assert np.array_equal(body.faces, mesh.faces) and np.array_equal(body.labels, mesh.labels)
        assert np.array_equal(body.bounds, mesh.bounds)
        # the same draws: the generators are in the same state afterwards
        rest = np.random.default_rng(seed)
        vehicle_body(rest, kind)
        assert rest.random() == rng.random()


def _rect_cells_rotated(r: Raster, x, y, w, d, yaw, pad):
    """The general formula of ``Raster._rect_cells``, for any yaw: every sample point rotated and floored."""
    u = np.append(np.arange(-w / 2 - pad, w / 2 + pad + 1e-9, r.cell * 0.5), w / 2 + pad)[:, None]
    v = np.append(np.arange(-d / 2 - pad, d / 2 + pad + 1e-9, r.cell * 0.5), d / 2 + pad)[None, :]
    c, s = math.cos(yaw), math.sin(yaw)
    px, py = (x + c * u) - s * v, (y + s * u) + c * v
    return (np.floor((px.ravel() - r.lo[0]) / r.cell).astype(np.int64),
            np.floor((py.ravel() - r.lo[1]) / r.cell).astype(np.int64))


def test_an_unrotated_rectangles_cells_are_the_rotated_formulas():
    r = Raster(np.array([-512.3, -300.7]), np.array([400.1, 377.9]), 1.0)
    rng = np.random.default_rng(0)
    for n in range(3000):
        x, y = rng.uniform(-600.0, 500.0), rng.uniform(-400.0, 450.0)
        if n % 2:                                           # the fill's candidates: cell centres
            x, y = math.floor(x) + 0.5, math.floor(y) + 0.5
        w, d = rng.uniform(0.2, 26.0), rng.uniform(0.2, 18.0)
        pad = float(rng.choice([0.1, 0.3, 0.5, 0.8, 1.0, 1.5]))
        i, j = r._rect_cells(x, y, w, d, 0.0, pad)
        bi, bj = np.broadcast_arrays(i, j)
        assert set(zip(bi.ravel().tolist(), bj.ravel().tolist())) == set(
            zip(*(a.tolist() for a in _rect_cells_rotated(r, x, y, w, d, 0.0, pad))))
        assert r._inside(i, j) == r._inside(*_rect_cells_rotated(r, x, y, w, d, 0.0, pad))


def test_the_fills_batched_heights_are_the_one_point_queries():
    """``fill`` with its heights from one query places what it places with a query per point."""
    base = opendrive._town_base(opendrive_path("Town01"), dict(opendrive.OPENDRIVE_OPTIONS))
    tree, ref = cKDTree(base.ref[:, :2]), base.ref

    def batched(x, y):
        _, i = tree.query(np.stack([x, y], 1), k=8)
        return ref[i, 2].min(axis=1)

    def one_by_one(x, y):
        return np.array([float(np.min(ref[tree.query([a, b], k=8)[1], 2])) for a, b in zip(x, y)])

    out = []
    for heights in (batched, one_by_one):
        rng = np.random.default_rng(3)
        raster = Raster(base.lo - 40.0, base.hi + 40.0, 1.0)
        raster.occ = base.road_occ.copy()
        T = Props(rng, {})
        fill(T, rng, raster, base.road_distance(), heights, 0.3)
        out.append((T.b.arrays(), raster.occ))
    (a, occ_a), (b, occ_b) = out
    assert len(a[0]) > 1000
    assert all(np.array_equal(p, q) for p, q in zip(a, b)) and np.array_equal(occ_a, occ_b)



def _densified_by_stretch(pts: np.ndarray, step: float) -> np.ndarray:
    """The densifying loop ``paths.fillet`` ran until 2026-11-30: one block of rows per stretch."""
    out = [pts[:1]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def test_a_fillets_stretches_densified_at_once_are_the_loops_rows(monkeypatch):
    # the points of the town's lanes and pedestrian rings (corners and radii as the builder gives them), then
    # random polylines with repeated and axis-aligned points: the same rows, bit for bit
    from place3d_kernels.scene import paths, town_actors
    from place3d_kernels.spec import SceneSpec, make_scene

    calls, plain = [], paths.fillet

    def keep(corners, radii, step=0.25):
        calls.append((paths._arcs(corners, radii, step), step))
        return plain(corners, radii, step)

    monkeypatch.setattr(town_actors, "fillet", keep)
    monkeypatch.setattr(paths, "fillet", keep)
    for seed in range(3):
        make_scene(SceneSpec("town", seed, 8))
    rng = np.random.default_rng(7)
    for _ in range(30):
        p = np.round(rng.uniform(-30, 30, (int(rng.integers(2, 9)), 2)), int(rng.integers(0, 3)))
        p[int(rng.integers(1, len(p)))] = p[0]
        calls.append((p, float(rng.choice([0.2, 0.25, 1.0]))))
    # stretches whose length is a whole number of steps, where a length off in its last bit changes the rows
    for leg in ((0.3, 0.4), (0.6, 0.8), (1.2, 1.6), (0.09, 0.12), (2.1, 2.8), (0.15, 0.2), (0.5, 1.2)):
        calls.append((np.cumsum(np.tile(leg, (40, 1)) * rng.choice([-1.0, 1.0], (40, 2)), axis=0), 0.25))
        calls.append((np.cumsum(np.tile(leg, (40, 1)), axis=0), 0.1))
    assert len(calls) > 100
    for pts, step in calls:
        got, want = paths._densify(pts, step), _densified_by_stretch(pts, step)
        assert got.shape == want.shape and np.array_equal(got.view(np.uint64), want.view(np.uint64))
