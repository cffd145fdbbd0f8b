"""Leave-one-out grids patched from the full pool (place3d_kernels/left_out.py) are the grids of the
left-out P-SOGs built from scratch, bit for bit, and the jackknife scores on them are msog_batch's."""

from __future__ import annotations

import numpy as np
import pytest

from field_cases import exact_terms, grid_arrays, wide_rows

from place3d_kernels.backends.bricks import flat_brick_masks
from place3d_kernels.left_out import LeftOutGrids
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import msog_batch, msog_on_grid
from place3d_kernels.placement import Placement
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec
from place3d_kernels.subset_records import spec_subset_records
from place3d_kernels.uncertainty import jackknife_records


def _spec(seed=0, frames=16):
    return PSOGSpec(SceneSpec("town", seed, frames), "warp:cpu", RoiSpec(0.8)).resolved()


@pytest.fixture(scope="module")
def subsets():
    return PooledPSOG(_spec().grid.grid(), spec_subset_records(_spec()))


@pytest.fixture(scope="module")
def drives():
    # three drives of 4, 4 and 2 subsets: leaving one out gives T' = 6 or 8, two different bases
    recs = [DriveRecord.from_psog(_spec(s, f).build(), f"d{s}") for s, f in ((0, 16), (1, 16), (2, 8))]
    return PooledPSOG(_spec().grid.grid(), recs)


@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("pool", ["subsets", "drives"])
def test_every_left_out_grid_is_the_rebuilt_one(request, pool, task):
    pooled = request.getfixturevalue(pool)
    grids = LeftOutGrids(pooled, task)
    n = len(pooled)
    assert n >= 3
    for i in [*range(n), 0, n - 1, 1]:                  # again and out of order: the working copy is restored
        m = np.ones(n, dtype=np.int64)
        m[i] = 0
        want = pooled.psog(m).for_task(task)
        w, stop = grids.fields(i)
        assert w.dtype == want.weights.dtype and np.array_equal(w, want.weights), f"weights, record {i}"
        assert stop.dtype == want.stop_mask.dtype and np.array_equal(stop, want.stop_mask), f"stop, record {i}"
    if pool == "drives":
        assert len(grids._base) == 2                      # T' = 6 and 8


@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_jackknife_scores_are_msog_batch_on_the_rebuilt_pools(subsets, occlusion):
    lidar = LidarModel.load("place3d_16ch")
    rigs = {n: Placement.load(n).poses for n in ("center", "line", "pyramid")}
    got = jackknife_records(subsets.records, subsets.grid, lidar, rigs, ("seg", "det"), occlusion, "warp:cpu")
    n = len(subsets)
    poses = np.stack(list(rigs.values()))
    for t in ("seg", "det"):
        assert got[t].point.tobytes() == msog_batch(subsets.psog(), lidar, poses, occlusion, t, "warp:cpu").tobytes()
        for i in range(n):
            m = np.ones(n, dtype=np.int64)
            m[i] = 0
            want = msog_batch(subsets.psog(m), lidar, poses, occlusion, t, "warp:cpu")
            assert got[t].samples[i].tobytes() == want.tobytes(), (t, i)


def test_msog_on_grid_checks_its_inputs(subsets):
    lidar = LidarModel.load("place3d_16ch")
    ps = subsets.psog()
    far = Placement.load("center").poses.copy()
    far[0, 0] = 1e4
    with pytest.raises(ValueError, match="outside the grid"):
        msog_on_grid(ps.grid, ps.weights, ps.stop_mask, lidar, far, "warp:cpu")
    with pytest.raises(ValueError, match="minimum range"):
        msog_on_grid(ps.grid, ps.weights, ps.stop_mask,
                     LidarModel(lidar.elevations, lidar.azimuths, lidar.max_range, min_range=1.0),
                     Placement.load("center").poses, "warp:cpu")


def test_the_scene_psog_serves_as_the_point_when_it_is_the_pool(subsets):
    """The jackknife's point estimate reuses the scene's P-SOG (its weights and device grids) only when it
    is exactly the records' pool; another P-SOG is ignored, and the intervals are the same either way."""
    scene = _spec().build()
    assert subsets.plain_psog(scene) is scene
    other = _spec(1).build()
    rebuilt = subsets.plain_psog(other)
    assert rebuilt is not other
    assert np.array_equal(rebuilt.voxels, scene.voxels) and rebuilt.probs.tobytes() == scene.probs.tobytes()
    lidar = LidarModel.load("place3d_16ch")
    rigs = {n: Placement.load(n).poses for n in ("center", "pyramid")}
    plain = jackknife_records(subsets.records, subsets.grid, lidar, rigs, ("seg",), "sog", "warp:cpu")["seg"]
    for ref in (scene, other):
        got = jackknife_records(subsets.records, subsets.grid, lidar, rigs, ("seg",), "sog", "warp:cpu",
                                reference=ref)["seg"]
        assert got.point.tobytes() == plain.point.tobytes() and got.samples.tobytes() == plain.samples.tobytes()


def _patching_backends():
    # every Warp device, CPU included, where patching is not the default (Backend.patches_grids)
    import place3d_kernels as p3k

    return [b for b in p3k.available_backends() if b.startswith("warp:")]


def _arrays(h):
    # weights, brick pairs, and on CUDA the score kernel's flat masks (bricks.flat_brick_masks)
    return h.weights.numpy(), h.masks.numpy(), None if h.flat is None else h.flat.numpy()


@pytest.mark.parametrize("name", _patching_backends())
@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("pool", ["subsets", "drives"])
@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_grids_patched_on_the_device_are_the_uploaded_ones(request, pool, task, name, occlusion):
    """left_out.patched_on_backend (Warp: a base per T on the device, each record's rows written over a
    copy, brick masks made by a kernel) gives, for every record, the weights and masks that prepare_grid
    gives for the host-patched dense grid; prepared_grids takes that way exactly on CUDA."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out import patched_on_backend

    pooled = request.getfixturevalue(pool)
    b = get_backend(name)
    assert b.patches_grids == b.device.is_cuda
    host = LeftOutGrids(pooled, task)
    stop_of = (lambda s: s) if occlusion == "sog" else (lambda s: None)
    for i, h in enumerate(patched_on_backend(pooled, task, occlusion, b)):
        w, stop = host.fields(i)
        want = b.prepare_grid(pooled.grid.spec, w, stop_of(stop))
        gw, gm, gf = _arrays(h)
        ww, wm, wf = _arrays(want)
        assert gw.tobytes() == ww.tobytes(), f"weights, record {i}"
        assert gm.dtype == wm.dtype and gm.tobytes() == wm.tobytes(), f"masks, record {i}"
        assert (gf is None) == (wf is None) == (not b.device.is_cuda)
        assert gf is None or gf.tobytes() == wf.tobytes(), f"flat masks, record {i}"


@pytest.mark.parametrize("name", _patching_backends())
def test_patched_grid_on_partial_bricks_and_its_checks(name):
    """Random grids whose shape leaves partial bricks on every axis: patched_grid equals prepare_grid of the
    patched arrays, with no changed voxel too, and leaves its base alone; rows of mismatched length are
    refused with a message."""
    from place3d_kernels.backends.base import GridSpec
    from place3d_kernels.backends.registry import get_backend

    b = get_backend(name)
    rng = np.random.default_rng(3)
    spec = GridSpec(voxel_size=0.5, shape=(9, 6, 5))
    n = 9 * 6 * 5
    w = np.where(rng.random(n) < 0.3, rng.integers(1, 10**6, n), 0).astype(np.int64)
    stop = rng.random(n) < 0.2
    base = b.grid_base(spec, w, stop)
    for k in (0, 1, 17, n):
        ids = np.sort(rng.choice(n, k, replace=False)).astype(np.int64)
        wr = np.where(rng.random(k) < 0.5, rng.integers(1, 10**6, k), 0).astype(np.int64)
        sr = rng.random(k) < 0.5
        w2, s2 = w.copy(), stop.copy()
        w2[ids], s2[ids] = wr, sr
        got = _arrays(b.patched_grid(base, ids, wr, sr))
        want = _arrays(b.prepare_grid(spec, w2, s2))
        assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes(), k
        if b.device.is_cuda:      # the score kernel's masks, by the host's definition of their layout
            flat = flat_brick_masks(spec.shape, w2 != 0, s2)
            assert got[2].tobytes() == want[2].tobytes() == flat.tobytes(), k
    assert base.weights.numpy().tobytes() == w.tobytes()
    no_stop = b.grid_base(spec, w, None)
    got = _arrays(b.patched_grid(no_stop, np.array([4], dtype=np.int64), np.array([7]), None))
    w2 = w.copy()
    w2[4] = 7
    want = _arrays(b.prepare_grid(spec, w2, None))
    assert got[1].tobytes() == want[1].tobytes()
    if b.device.is_cuda:
        assert got[2].tobytes() == flat_brick_masks(spec.shape, w2 != 0, None).tobytes()
    with pytest.raises(ValueError, match="one weight and one stop value per voxel"):
        b.patched_grid(base, np.array([1, 2], dtype=np.int64), np.array([5]), np.array([True, False]))


def _small_lidar():
    # few rays: the reference backend walks each one in Python
    return LidarModel(np.radians([-20.0, -8.0, -2.0, 4.0]), np.radians(np.arange(0.0, 360.0, 15.0)), 30.0, "small")


@pytest.mark.parametrize("normalisation", ["paper", "evidence", "uncertain"])
@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_jackknife_of_every_normalisation_is_msog_batch_on_rebuilt_pools(drives, backend, normalisation, occlusion):
    """The fused jackknife (each backend's way: written in place on reference and OpenCL, a host copy on Warp's
    CPU) gives every normalisation's scores msog_batch gives on the rebuilt left-out pools, bit for bit; two
    T's (6 and 8 subsets) need two working grids."""
    from place3d_kernels.left_out import fused_path

    lidar = _small_lidar()
    assert fused_path(lidar, occlusion, normalisation)
    rigs = {n: Placement.load(n).poses for n in ("center", "line", "pyramid")}
    poses = np.stack(list(rigs.values()))
    got = jackknife_records(drives, drives.grid, lidar, rigs, ("seg", "det"), occlusion, backend,
                            normalisation=normalisation)
    n = len(drives)
    for t in ("seg", "det"):
        want = msog_batch(drives.psog(), lidar, poses, occlusion, t, backend, normalisation=normalisation)
        assert got[t].point.tobytes() == want.tobytes(), t
        for i in [*range(n)]:
            m = np.ones(n, dtype=np.int64)
            m[i] = 0
            want = msog_batch(drives.psog(m), lidar, poses, occlusion, t, backend, normalisation=normalisation)
            assert got[t].samples[i].tobytes() == want.tobytes(), (t, i)


def _in_place_backends():
    import place3d_kernels as p3k
    from place3d_kernels.backends.registry import get_backend

    names = [n for n in ["reference", *p3k.available_backends()] if get_backend(n).writes_grids]
    return list(dict.fromkeys(names)) + (["opencl:pocl/atomic"] if "opencl:pocl" in names else [])


def _in_place_backend(name):
    from place3d_kernels.backends.registry import get_backend

    if name.endswith("/atomic"):          # the GPU's score strategy (brick pairs, flat masks), on the CPU device
        from place3d_kernels.backends.opencl.host import OpenCLBackend

        return OpenCLBackend(name.split(":")[1].split("/")[0], score_strategy="atomic")
    return get_backend(name)


@pytest.mark.parametrize("name", _in_place_backends())
@pytest.mark.parametrize("with_stop", [True, False])
def test_voxels_written_in_place_are_the_uploaded_grid(name, with_stop):
    """working_grid and write_voxels on random grids whose shape leaves partial bricks and words: after each
    write (nothing, a few voxels, all of them, set and cleared) the handle holds what prepare_grid makes of
    the dense arrays so changed; rows of mismatched length are refused with a message."""
    from place3d_kernels.backends.base import GridSpec

    b = _in_place_backend(name)
    rng = np.random.default_rng(5)
    spec = GridSpec(voxel_size=0.5, shape=(9, 6, 5))
    n = 9 * 6 * 5
    at = np.sort(rng.choice(n, 40, replace=False)).astype(np.int64)
    w = np.zeros(n, dtype=np.int64)
    stop = np.zeros(n, dtype=bool)
    w[at] = rng.integers(0, 10**6, len(at))
    stop[at] = rng.random(len(at)) < 0.5
    sv = (lambda s: s) if with_stop else (lambda s: None)
    h = b.working_grid(spec, at, w[at], sv(stop[at]))
    for k in (0, 1, 17, n, 3):
        if getattr(b, "score_strategy", None) == "atomic" and k == 17:
            b._flat_masks(h)               # made once scored: later writes must make it again
        ids = np.sort(rng.choice(n, k, replace=False)).astype(np.int64)
        wr = np.where(rng.random(k) < 0.5, rng.integers(1, 10**6, k), 0).astype(np.int64)
        sr = rng.random(k) < 0.5
        w[ids], stop[ids] = wr, sr
        b.write_voxels(h, ids, wr, sv(sr))
        want = b.prepare_grid(spec, w, sv(stop))
        if getattr(b, "score_strategy", None) == "atomic" and h.flat is not None:
            b._flat_masks(want)
        got_a, want_a = grid_arrays(b, h), grid_arrays(b, want)
        assert len(got_a) == len(want_a)
        for g, x in zip(got_a, want_a):
            assert (g is None) == (x is None) and (g is None or g.tobytes() == x.tobytes()), k
    with pytest.raises(ValueError, match="one weight and one stop value per voxel"):
        b.write_voxels(h, np.array([1, 2], dtype=np.int64), np.array([5]), np.array([True, False]))
    with pytest.raises(ValueError, match=r"voxel indices must lie in \[0, 270\)"):
        b.write_voxels(h, np.array([n], dtype=np.int64), np.array([5]), np.array([True]))
    if b.name != "reference":
        with pytest.raises(TypeError, match="working_grid"):
            b.write_voxels(b.prepare_grid(spec, w, sv(stop)), at[:1], w[at[:1]], sv(stop[at[:1]]))


@pytest.mark.parametrize("name", [*dict.fromkeys(["reference", *__import__("place3d_kernels").available_backends()]),
                                  "opencl:pocl/atomic"])
def test_grids_of_one_stop_mask_score_together_as_alone(name):
    """score_placements_many (OpenCL's private strategy walks the rays once for all grids) gives each grid
    what score_placements gives it alone: random weights, one shared stop mask, and an indicator grid."""
    import place3d_kernels as p3k
    from place3d_kernels.backends.base import GridSpec

    if name.startswith("opencl:") and "opencl:pocl" not in p3k.available_backends():
        pytest.skip("no opencl:pocl here")
    b = _in_place_backend(name)
    rng = np.random.default_rng(11)
    spec = GridSpec(voxel_size=0.5, shape=(21, 19, 7))
    n = 21 * 19 * 7
    stop = rng.random(n) < 0.03
    grids = [np.where(rng.random(n) < 0.4, rng.integers(1, 10**9, n), 0).astype(np.int64) for _ in range(2)]
    grids.append((grids[0] > 0).astype(np.int64))
    # more 0/1 grids: one with ones where the first grid has none (the "evidence" kind), one of zeros only
    grids.append((rng.random(n) < 0.5).astype(np.int64))
    grids.append(np.zeros(n, dtype=np.int64))
    lidar = _small_lidar()
    poses = np.zeros((3, 2, 6))
    poses[..., :3] = rng.uniform(1.0, 3.0, (3, 2, 3))
    poses[..., 3:] = rng.uniform(-0.3, 0.3, (3, 2, 3))
    orders = [list(range(len(grids))), [2, 0, 3, 1, 2, 4]]     # an indicator first; one grid twice
    def prepared(i, s):     # the 0/1 grids as indicators (Warp and OpenCL count them from the first grid's walk)
        return (b.prepare_indicator if i >= 2 else b.prepare_grid)(spec, grids[i], s)

    for s, order, rigs in ((stop, orders[0], poses), (None, orders[0], poses), (stop, orders[1], poses),
                           (stop, orders[0], poses[:1])):
        handles = [prepared(i, s) for i in order]
        got = b.score_placements_many(handles, lidar.elevations, lidar.azimuths, 6.0, rigs)
        assert len(got) == len(handles)
        for i, h, (sums, counts) in zip(order, handles, got):
            want = b.score_placements(h, lidar.elevations, lidar.azimuths, 6.0, rigs)
            assert sums.tobytes() == want[0].tobytes() and counts.tobytes() == want[1].tobytes()
            plain = b.score_placements(b.prepare_grid(spec, grids[i], s), lidar.elevations, lidar.azimuths, 6.0, rigs)
            assert sums.tobytes() == plain[0].tobytes() and counts.tobytes() == plain[1].tobytes()
        assert got[0][1].tobytes() == got[1][1].tobytes()          # one walk: the same voxels counted
        if order == orders[0]:
            assert got[2][0].tobytes() != got[3][0].tobytes() and not got[4][0].any()   # not all alike


def test_records_in_any_entry_order_give_the_same_left_out_grids(drives):
    """A record's entries are found in the pool by voxel; entries out of voxel order (not what from_psog
    writes, but allowed) take the sorting path and give the same grids."""
    recs = list(drives.records)
    r = recs[1]
    order = np.random.default_rng(2).permutation(len(r.voxels))
    recs[1] = DriveRecord(r.label, r.n_subsets, r.voxels[order], r.classes[order], r.counts[order])
    shuffled = PooledPSOG(drives.grid, recs)
    for task in ("seg", "det"):
        a, b = LeftOutGrids(drives, task), LeftOutGrids(shuffled, task)
        for i in range(len(recs)):
            wa, sa = (x.copy() for x in a.fields(i))
            wb, sb = b.fields(i)
            assert wa.tobytes() == wb.tobytes() and sa.tobytes() == sb.tobytes(), (task, i)


@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("T", [1, 2, 3, 7, 30, 81])
def test_field_tables_are_left_out_fields(task, T):
    """FieldTables (look-ups of each c / T's entropy term) gives left_out_fields' weights and stop masks bit
    for bit: every split of T subsets among empty, vehicle and one other class, and random rows over all
    22 channels."""
    from place3d_kernels.classes import N_CLASSES, VEHICLE
    from place3d_kernels.left_out import FieldTables, left_out_fields

    rows = []
    for e in range(T + 1):                                  # empty, vehicle, one more class: every split
        for v in range(T + 1 - e):
            r = np.zeros(N_CLASSES, dtype=np.int64)
            r[0], r[VEHICLE], r[1 if VEHICLE != 1 else 2] = e, v, T - e - v
            rows.append(r)
    rng = np.random.default_rng(T)
    for _ in range(2000):                                   # T subsets spread over random classes
        r = np.bincount(rng.integers(0, N_CLASSES, T), minlength=N_CLASSES).astype(np.int64)
        rows.append(r)
    counts = np.array(rows)
    want = left_out_fields(counts, T, task)
    got = FieldTables(T, task)(counts)
    assert got[0].dtype == want[0].dtype and got[0].tobytes() == want[0].tobytes()
    assert got[1].dtype == want[1].dtype and got[1].tobytes() == want[1].tobytes()


@pytest.mark.parametrize("name", _patching_backends())
@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("pool", ["subsets", "drives"])
@pytest.mark.parametrize("threads", [1, 3])
def test_left_out_rows_made_on_the_device_are_the_hosts(request, monkeypatch, pool, task, name, threads):
    """left_out.device_fields (every record's rows in one Warp launch, tables from the host, NumPy's order of
    addition; the records' indexes made on ``threads`` threads, as for a large pool) gives each record's weights
    and stop flags bit for bit as LeftOutGrids.rows; patched_on_backend takes that way where the backend says
    so (on CUDA), and its grids are then the uploaded ones."""
    import place3d_kernels.threads as threads_mod
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out import device_fields, patched_on_backend

    monkeypatch.setattr(threads_mod, "threads_for", lambda entries: threads)
    pooled = request.getfixturevalue(pool)
    b = get_backend(name)
    host = LeftOutGrids(pooled, task)
    batch = device_fields(pooled, task, b)
    for i, (T, at, w, s) in enumerate(batch):
        hT, _, hat, hw, hs, _ = host.rows(i)
        assert T == hT and at.tobytes() == hat.tobytes(), i
        assert w.numpy().tobytes() == hw.tobytes(), f"weights, record {i}"
        assert s.numpy().tobytes() == hs.astype(np.uint8).tobytes(), f"stop, record {i}"
    monkeypatch.setattr(type(b), "fields_on_device", property(lambda self: True))
    dense = LeftOutGrids(pooled, task)
    for i, h in enumerate(patched_on_backend(pooled, task, "sog", b)):
        w, stop = dense.fields(i)
        want = b.prepare_grid(pooled.grid.spec, w, stop)
        assert h.weights.numpy().tobytes() == want.weights.numpy().tobytes(), f"weights, record {i}"
        assert h.masks.numpy().tobytes() == want.masks.numpy().tobytes(), f"masks, record {i}"


@pytest.mark.parametrize("name", _patching_backends())
def test_both_tasks_rows_from_one_shared_batch_are_the_hosts(name, drives):
    """The jackknife shares one LeftOutRows between its tasks: the records' entry tables are made once
    (read-only) and each task's left-out rows from them are still LeftOutGrids.rows' bits."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out import LeftOutRows, device_fields

    b = get_backend(name)
    rows = LeftOutRows(drives)
    for task in ("seg", "det", "seg"):
        host = LeftOutGrids(drives, task)
        for i, (T, at, w, s) in enumerate(device_fields(drives, task, b, rows)):
            hT, _, hat, hw, hs, _ = host.rows(i)
            assert T == hT and at.tobytes() == hat.tobytes(), (task, i)
            assert w.numpy().tobytes() == hw.tobytes() and s.numpy().tobytes() == hs.astype(np.uint8).tobytes()
    assert rows.batch() is rows.batch()
    assert not any(a.flags.writeable for a in rows.batch()[2:])


def test_one_pools_jackknifes_share_its_rows_until_a_record_is_added(drives):
    """LeftOutRows.shared: reproduce's two jackknifes (one per task) share the records' index and tables, kept
    with the pool; a pool with a record added gets rows made anew."""
    from place3d_kernels.left_out import LeftOutRows

    pool = PooledPSOG(drives.grid, drives.records[:-1])
    rows = LeftOutRows.shared(pool)
    assert LeftOutRows.shared(pool) is rows and rows.T == pool.n_subsets
    pool.add(drives.records[-1])
    grown = LeftOutRows.shared(pool)
    assert grown is not rows and grown.T == drives.n_subsets and len(grown.batch()[0]) == len(drives)
    for i in range(len(drives)):                 # the same rows as the full pool's own
        assert np.array_equal(grown.of(i)[2], LeftOutRows(drives).of(i)[2]), i
    assert pool.derived == {LeftOutRows: grown}


@pytest.mark.parametrize("name", _patching_backends())
def test_warp_keeps_device_copies_only_of_arrays_nobody_can_write(name):
    """WarpScoring._resident: a read-only array that owns its memory is sent once while it lives; a writable
    array or a view is sent again each time, so a changed array is never scored from a stale copy."""
    import gc

    from place3d_kernels.backends.registry import get_backend

    b = get_backend(name)
    x = np.arange(10, dtype=np.int32)
    b._resident(x, np.int32)
    x[0] = 7
    assert b._resident(x, np.int32).numpy()[0] == 7          # writable: sent again, with its new value
    x.setflags(write=False)
    kept = b._resident(x, np.int32)
    assert b._resident(x, np.int32) is kept and kept.numpy().tolist() == x.tolist()
    view = x[2:]
    assert b._resident(view, np.int32) is not b._resident(view, np.int32)
    assert b._resident(x, np.int64).dtype != kept.dtype      # another type: converted, not the kept copy
    key = id(x)
    del x, view
    gc.collect()
    assert key not in b._resident_arrays                     # dropped with the host array


@pytest.mark.parametrize("name", _patching_backends())
@pytest.mark.parametrize("task", ["seg", "det"])
def test_device_fields_add_terms_in_numpys_order(name, task):
    """Backend.left_out_fields on rows whose T = 81 subsets spread over all 22 channels (many terms per row,
    where the order of addition shows) and one entry taken out of each: FieldTables' weights bit for bit; at
    ENTROPY_SCALE the rounding hides most last-bit differences of H, at 2**60 every bit of H shows."""
    from place3d_kernels.backends.base import ENTROPY_SCALE
    from place3d_kernels.backends.registry import get_backend

    b = get_backend(name)
    args, rows, tb = wide_rows(task, 5000)
    ww, ws = tb(rows)
    assert len(rows) > 1000
    w, s = b.left_out_fields(*args, float(ENTROPY_SCALE))
    assert w.numpy().tobytes() == ww.tobytes() and s.numpy().tobytes() == ws.astype(np.uint8).tobytes()
    w60, _ = b.left_out_fields(*args, 2.0**60)
    assert w60.numpy().tobytes() == exact_terms(task, rows, tb).tobytes()


@pytest.mark.parametrize("name", _patching_backends())
@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("pool", ["subsets", "drives"])
def test_bases_made_on_the_device_are_the_hosts(request, pool, task, name):
    """left_out_tables.device_row_fields on the pool's rows (every row over a left-out T, counts clipped into
    [0, T], in one Warp launch), as patched_on_backend makes its bases, gives LeftOutGrids._base_fields' weights and stop flags bit for bit, rows holding more
    than T subsets included; a base grid filled from those device rows is the one filled from the host's."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out_tables import device_row_fields

    pooled = request.getfixturevalue(pool)
    b = get_backend(name)
    host = LeftOutGrids(pooled, task)
    Ts = sorted({host.source.of(i)[0] for i in range(len(pooled))})
    over = 0
    for T in Ts:
        hw, hs, _ = host._base_fields(T)
        w, s = device_row_fields(host.counts, T, task, b)
        assert w.numpy().tobytes() == hw.tobytes(), f"weights, T={T}"
        assert s.numpy().tobytes() == hs.astype(np.uint8).tobytes(), f"stop, T={T}"
        over += int((host.counts[:, 1:].sum(axis=1) > T).sum())
        spec = pooled.grid.spec
        got = b.grid_base_from_rows(spec, host.voxels, w, s)
        want = b.grid_base_from_rows(spec, host.voxels, hw, hs)
        assert got.weights.numpy().tobytes() == want.weights.numpy().tobytes()
        assert got.stop.numpy().tobytes() == want.stop.numpy().tobytes()
    assert over > 0                                  # the clip was exercised


@pytest.mark.parametrize("name", _patching_backends())
@pytest.mark.parametrize("task", ["seg", "det"])
def test_uncertain_indicator_from_device_rows_is_the_hosts(monkeypatch, drives, task, name):
    """With the rows' fields on the device (as on CUDA), patched_on_backend makes the "uncertain" indicator of
    each left-out grid from those weights (above 0) and its base from the base's: each pair of grids is what the
    host's patched copies give (LeftOutGrids.dense with the indicator), weights and brick masks bit for bit."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out import patched_on_backend

    b = get_backend(name)
    monkeypatch.setattr(type(b), "fields_on_device", property(lambda self: True))
    dense = LeftOutGrids(drives, task, "uncertain")
    n = 0
    for i, (h, hi) in enumerate(patched_on_backend(drives, task, "sog", b, "uncertain")):
        w, stop, ind = dense.dense(i)
        assert ind.any() and not np.array_equal(ind, w)        # the two grids differ: each is checked
        for got, weights in ((h, w), (hi, ind)):
            want = b.prepare_grid(drives.grid.spec, weights, stop)
            assert got.weights.numpy().tobytes() == want.weights.numpy().tobytes(), f"record {i}"
            assert got.masks.numpy().tobytes() == want.masks.numpy().tobytes(), f"masks, record {i}"
        n += 1
    assert n == len(drives)
