"""The prepared left-out grids kept between jackknifes of one process (left_out.HANDLES, what a warm
``place3d serve`` reuses): a second jackknife on the same record file prepares no grid and gives the same
intervals bit for bit; a rewritten or touched record file is never served from the memo; the memo keeps
at most its bound. Tiny settings (0.8 m voxels, 16 frames) as in test_interval_memo.py, on both CPU device
backends of the dev VM; every backend's prepared grid is its own copy (the memo relies on it)."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.left_out import HANDLES, KEEP_LEFT_OUT
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import msog_batch
from place3d_kernels.placement import Placement
from place3d_kernels.pooled import PooledPSOG
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec
from place3d_kernels.subset_records import keyed_subset_records, records_aggregator, subset_records_path
from place3d_kernels.uncertainty import jackknife_records, rig_vs_baselines_intervals

BACKENDS = ["warp:cpu", "opencl:pocl", "reference"]
LIDAR = "place3d_16ch"


def _spec(folder, backend="warp:cpu"):
    return PSOGSpec(SceneSpec("town", 0, 16), backend, RoiSpec(0.8), cache=str(folder)).resolved()


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A cache folder holding the scene's P-SOG and its subset records, built once (copied per test)."""
    folder = tmp_path_factory.mktemp("left-out-memo")
    spec = _spec(folder)
    spec.build(cache=spec.cache, aggregate=records_aggregator(spec))
    return folder


@pytest.fixture
def spec(built, tmp_path, request):
    """A fresh copy of the cache folder (its record file may be rewritten) and the spec on it."""
    shutil.copytree(built, tmp_path / "cache")
    return _spec(tmp_path / "cache", request.param)


@pytest.fixture
def prepared(monkeypatch):
    """Counts the grids every backend instance prepares, whole, patched from a base or written into a
    working grid (the wrapped methods of the instance itself: the memo keys on the instance, so the wrapper
    must not change which one the code gets)."""
    calls = []
    for name in BACKENDS:
        b = get_backend(name)
        for method in ("prepare_grid", "patched_grid", "write_voxels"):
            real = getattr(b, method)

            def counting(*a, _real=real, **kw):
                calls.append(1)
                return _real(*a, **kw)

            monkeypatch.setattr(b, method, counting)
    HANDLES.clear()
    yield calls
    HANDLES.keep(KEEP_LEFT_OUT)
    HANDLES.clear()


def _rigs():
    return {n: Placement.load(n).poses for n in ("center", "pyramid")}


def _intervals_of(spec):
    """(backend, scene, run): ``run()`` is the jackknife of ``line-roll`` against three baselines through
    ``rig_vs_baselines_intervals``, as ``place3d optimize`` calls it."""
    b = get_backend(spec.backend)
    scene = spec.build(cache=spec.cache)
    best = Placement.load("line-roll").poses
    base = {n: Placement.load(n).poses for n in ("center", "line", "pyramid")}

    def run():
        return rig_vs_baselines_intervals(spec, LIDAR, best, base, "seg", "sog", b, method="jackknife",
                                          reference=scene)

    return b, scene, run


def _same(a, b):
    for t in a:
        assert a[t].point.tobytes() == b[t].point.tobytes(), t
        assert a[t].samples.tobytes() == b[t].samples.tobytes(), t


@pytest.mark.parametrize("spec", ["warp:cpu", "opencl:pocl"], indirect=True)
def test_a_second_jackknife_prepares_no_grid(spec, prepared):
    b = get_backend(spec.backend)
    scene = spec.build(cache=spec.cache)
    records, key = keyed_subset_records(spec, b)
    assert key is not None and key[0] == os.path.realpath(subset_records_path(spec)[0])
    n = len(records)
    grid = spec.grid.grid()
    rigs = _rigs()

    def run(**kw):
        return jackknife_records(records, grid, LIDAR, rigs, ("seg", "det"), "sog", b, **kw)

    computed = run()                                     # no key: nothing kept, the point computed
    assert len(HANDLES) == 0
    want_point = msog_batch(PooledPSOG(grid, records).psog(), LidarModel.load(LIDAR), np.stack(list(rigs.values())),
                            "sog", "seg", b)
    assert computed["seg"].point.tobytes() == want_point.tobytes()
    first = run(reference=scene, pool_key=key)
    assert len(HANDLES) == 2                             # both tasks
    del prepared[:]
    second = run(reference=scene, pool_key=key)
    assert len(prepared) == 0                            # no left-out grid, no point grid
    _same(second, computed)
    _same(first, computed)
    HANDLES.keep(0)                                      # switched off: every grid prepared again
    assert len(HANDLES) == 0
    del prepared[:]
    _same(run(reference=scene, pool_key=key), computed)
    # each left-out grid once; where grids are written in place, also each task's working grid filled once, and
    # where their rows are made on the device a record's grid after the first is two writes (the previous
    # record's rows put back from the base's, then its own; every record here leaves the same T)
    per_task = n + 1 + ((n - 1) if getattr(b, "left_out_on_device", False) else 0) if b.writes_grids else n
    assert len(prepared) == 2 * per_task


@pytest.mark.parametrize("spec", ["warp:cpu", "opencl:pocl"], indirect=True)
def test_warm_intervals_are_the_cold_ones(spec, prepared):
    """Through rig_vs_baselines_intervals (what ``place3d optimize`` calls): the second call, with the
    baselines remembered on disk and the left-out grids in memory, prepares nothing."""
    b, scene, run = _intervals_of(spec)

    cold = run()
    del prepared[:]
    warm = run()
    assert len(prepared) == 0
    assert warm == cold
    HANDLES.clear()
    assert run() == cold


@pytest.mark.parametrize("spec", ["warp:cpu", "opencl:pocl"], indirect=True)
def test_a_changed_record_file_is_not_served(spec, prepared):
    b = get_backend(spec.backend)
    scene = spec.build(cache=spec.cache)
    grid = spec.grid.grid()
    rigs = _rigs()
    path = subset_records_path(spec)[0]

    def run():
        records, key = keyed_subset_records(spec, b)
        assert key is not None
        del prepared[:]
        got = jackknife_records(records, grid, LIDAR, rigs, ("seg",), "sog", b, reference=scene, pool_key=key)
        count = len(prepared)
        HANDLES.keep(0)                                   # the same records, nothing kept: computed afresh
        want = jackknife_records(records, grid, LIDAR, rigs, ("seg",), "sog", b, reference=scene)
        HANDLES.keep(KEEP_LEFT_OUT)
        _same(got, want)
        return got, count

    before, count = run()
    assert count >= len(before["seg"].samples)
    n = len(before["seg"].samples)
    # touched: same content, another modification time, so another key: prepared again
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    records, key = keyed_subset_records(spec, b)
    del prepared[:]
    jackknife_records(records, grid, LIDAR, rigs, ("seg",), "sog", b, reference=scene, pool_key=key)
    assert len(prepared) == n
    # rewritten (a new file replaces it, as the cache writes it) with the last subset left out
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    keep = int(d["sizes"][:-1].sum())
    d.update(labels=d["labels"][:-1], n_subsets=d["n_subsets"][:-1], sizes=d["sizes"][:-1],
             voxels=d["voxels"][:keep], classes=d["classes"][:keep], counts=d["counts"][:keep])
    tmp = path.with_name("rewritten.npz")
    np.savez(tmp, **d)
    os.replace(tmp, path)
    # and its manifest with the new content's hash, as the cache writes it (a file whose bytes do not match
    # its manifest is rebuilt instead: tests/test_cache_verify.py)
    from place3d_kernels.manifest import content_hash, write_manifest

    write_manifest(path.with_suffix(".json"), subset_records_path(spec)[1], content_hash(path.read_bytes()))
    after, count = run()
    assert len(after["seg"].samples) == n - 1 and count >= n - 1
    assert after["seg"].point.tobytes() != before["seg"].point.tobytes()


@pytest.mark.parametrize("spec", ["warp:cpu"], indirect=True)
def test_the_memo_keeps_its_bound(spec, prepared):
    b = get_backend(spec.backend)
    records, _ = keyed_subset_records(spec, b)
    n, grid, rigs = len(records), spec.grid.grid(), _rigs()

    def run(key):
        del prepared[:]
        jackknife_records(records, grid, LIDAR, rigs, ("seg",), "none", b, pool_key=key)
        return len(prepared) - 1                          # the point's grid: no reference, built each time

    for key in ("a", "b", "c"):
        assert run(key) == n
        assert len(HANDLES) <= KEEP_LEFT_OUT
    assert run("c") == 0 and run("b") == 0
    assert run("a") == n                                  # the oldest went first
    HANDLES.keep(1)
    assert len(HANDLES) == 1 and run("a") == 0 and run("b") == n
    with pytest.raises(ValueError, match="n >= 0"):
        HANDLES.keep(-1)


@pytest.mark.parametrize("name", BACKENDS)
def test_a_prepared_grid_is_a_copy_of_its_inputs(built, name):
    """The jackknife prepares every left-out grid from one working array it patches in place: a handle
    that aliased its inputs would change under the kept ones (the reference backend's once did)."""
    b = get_backend(name)
    ps = _spec(built).build(cache=str(built)).for_task("seg")
    w, stop = ps.weights.copy(), ps.stop_mask.copy()
    lidar, rig = LidarModel.load(LIDAR), Placement.load("center").poses[None]
    local = rig.copy()
    local[..., :3] = ps.grid.to_local(rig[..., :3])
    h = b.prepare_grid(ps.grid.spec, w, stop)
    want = b.score_placements(h, lidar.elevations, lidar.azimuths, lidar.max_range, local)
    assert want[0][0] > 0
    w[:] = 0
    stop[:] = 1 - stop
    got = b.score_placements(h, lidar.elevations, lidar.azimuths, lidar.max_range, local)
    assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()


@pytest.mark.parametrize("spec", ["warp:cpu", "opencl:pocl"], indirect=True)
def test_grids_prepared_in_background_give_the_same_intervals(spec, prepared):
    """``place3d_app.prefetch.prepare_in_background`` (``place3d optimize`` runs it during the search): the jackknife
    that follows prepares no grid of its own and gives the intervals of a jackknife without it, bit for bit."""
    from place3d_app.prefetch import prepare_in_background

    b, scene, run = _intervals_of(spec)

    HANDLES.keep(0)
    want = run()                                          # nothing kept, nothing ahead: the plain jackknife
    HANDLES.keep(KEEP_LEFT_OUT)
    n = len(keyed_subset_records(spec, b)[0])
    del prepared[:]
    ahead = prepare_in_background(spec, scene, LidarModel.load(LIDAR), "seg", "sog", b)
    handles = ahead.result(timeout=300)
    assert len(handles) == n and len(prepared) == n       # every left-out grid, once, on the thread
    del prepared[:]
    assert run() == want
    assert len(prepared) == 0                             # the jackknife took the thread's grids


def test_prepare_in_background_skips_what_the_jackknife_would_not_use(tmp_path):
    from place3d_app.prefetch import prepare_in_background

    spec = _spec(tmp_path)
    L = LidarModel.load(LIDAR)
    assert prepare_in_background(spec, None, L, "seg", "sog", "warp:cpu", normalisation="minmax") is None
    assert prepare_in_background(spec, None, L, "seg", "ray", "warp:cpu") is None
    HANDLES.keep(0)
    try:
        assert prepare_in_background(spec, None, L, "seg", "sog", "warp:cpu") is None
    finally:
        HANDLES.keep(KEEP_LEFT_OUT)


def test_a_set_being_prepared_is_waited_for_not_prepared_twice():
    """``PreparedLeftOut.get``: a caller that finds another preparing the same set waits for its list; when
    that preparation fails, the waiting caller prepares the set itself (and meets any error itself)."""
    import threading
    import time

    from place3d_kernels.left_out import PreparedLeftOut

    memo = PreparedLeftOut(keep=2)
    grid = spec_grid = _spec("/tmp").grid.grid()
    started, release, calls = threading.Event(), threading.Event(), []

    def slow(fail=False):
        calls.append(1)
        started.set()
        release.wait(10)
        if fail:
            raise RuntimeError("preparation failed")
        yield from ("h0", "h1")

    got = {}
    t = threading.Thread(target=lambda: got.setdefault("first", memo.get("k", grid, "seg", "sog", None, slow)))
    t.start()
    started.wait(10)
    second = threading.Thread(target=lambda: got.setdefault("second", memo.get("k", spec_grid, "seg", "sog", None,
                                                                               slow)))
    second.start()
    time.sleep(0.2)
    release.set()
    t.join(10), second.join(10)
    assert got["first"] == ["h0", "h1"] and got["second"] is got["first"] and len(calls) == 1

    # the first preparation fails: the waiting caller prepares on its own and gets its list
    started.clear(), release.clear()
    del calls[:]
    errors = []

    def failing():
        try:
            memo.get("k2", grid, "seg", "sog", None, lambda: slow(fail=True))
        except RuntimeError as e:
            errors.append(e)

    t = threading.Thread(target=failing)
    t.start()
    started.wait(10)
    waiter = threading.Thread(target=lambda: got.setdefault("after", memo.get("k2", grid, "seg", "sog", None,
                                                                              lambda: iter(["ok"]))))
    waiter.start()
    time.sleep(0.2)
    release.set()
    t.join(10), waiter.join(10)
    assert len(errors) == 1 and got["after"] == ["ok"]
    assert memo.get("k2", grid, "seg", "sog", None, lambda: iter(["never"])) == ["ok"]   # kept


@pytest.mark.parametrize("spec", ["opencl:pocl"], indirect=True)
def test_a_set_over_the_byte_budget_is_not_kept(spec, prepared, monkeypatch):
    """A set of left-out grids larger than KEEP_SET_BYTES (a 0.1 m grid's: 2.9 GB for 10 subsets) is not kept:
    the jackknife patches one working grid per task instead, with the same intervals."""
    import place3d_kernels.left_out_memo as memo

    b = get_backend(spec.backend)
    scene = spec.build(cache=spec.cache)
    records, key = keyed_subset_records(spec, b)
    grid = spec.grid.grid()
    rigs = _rigs()
    computed = jackknife_records(records, grid, LIDAR, rigs, ("seg", "det"), "sog", b)
    assert HANDLES.fits(grid, len(records))
    from place3d_kernels.grid import DENSE_BYTES_PER_VOXEL

    monkeypatch.setattr(memo, "KEEP_SET_BYTES", DENSE_BYTES_PER_VOXEL * grid.n_voxels * len(records) - 1)
    assert not HANDLES.fits(grid, len(records))
    got = jackknife_records(records, grid, LIDAR, rigs, ("seg", "det"), "sog", b, reference=scene, pool_key=key)
    assert len(HANDLES) == 0
    _same(got, computed)
