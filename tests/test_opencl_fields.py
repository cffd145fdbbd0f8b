"""The OpenCL backend's left-out fields on the device (backends/opencl/fields.py, left_out.cl): the rows are the
host's ``FieldTables`` bit for bit, the jackknife's working grids written from them are the grids written from
the host's rows, and a P-SOG's grid from its device-made rows is the host's. On every OpenCL device with doubles
here (PoCL in CI, which makes the jackknife's rows so by default and is told to for a P-SOG's grid; an NVIDIA GPU
where one is lent), both score strategies, each against the same backend told to make its rows on the host."""

from __future__ import annotations

import numpy as np
import pytest

from field_cases import exact_terms, grid_arrays, same_arrays, wide_rows

from place3d_kernels.backends.base import ENTROPY_SCALE, GridSpec
from place3d_kernels.classes import N_CLASSES, VEHICLE
from place3d_kernels.left_out import FieldTables
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec

pytest.importorskip("pyopencl")


def _names():
    import place3d_kernels as p3k

    names = [n for n in p3k.available_backends() if n.startswith("opencl:")]
    return names + ([f"{names[0]}/atomic"] if names else [])


def _backend(name):
    """The named OpenCL backend (``/atomic``: the GPUs' score strategy on that device), skipped without doubles."""
    from place3d_kernels.backends.opencl.host import OpenCLBackend
    from place3d_kernels.backends.registry import get_backend

    if name.endswith("/atomic"):
        b = OpenCLBackend(name.split(":")[1].split("/")[0], score_strategy="atomic")
    else:
        b = get_backend(name)
    if not b.fp64:
        pytest.skip(f"{b.device.name} has no doubles")
    return b


def _fields_here(monkeypatch, b, here: bool = True) -> None:
    """Tell ``b``'s class to make fields on the device, or (``here=False``) on the host, as on a device without
    doubles: a P-SOG's grid and the jackknife's left-out rows both."""
    monkeypatch.setattr(type(b), "fields_on_device", property(lambda self: here))
    monkeypatch.setattr(type(b), "left_out_on_device", property(lambda self: here))


def _spec(seed=0, frames=16):
    return PSOGSpec(SceneSpec("town", seed, frames), "warp:cpu", RoiSpec(0.8)).resolved()


@pytest.fixture(scope="module")
def drives():
    # three drives of 4, 4 and 2 subsets: leaving one out gives T' = 6 or 8, two different bases
    recs = [DriveRecord.from_psog(_spec(s, f).build(), f"d{s}") for s, f in ((0, 16), (1, 16), (2, 8))]
    return PooledPSOG(_spec().grid.grid(), recs)


@pytest.mark.parametrize("name", _names())
@pytest.mark.parametrize("task", ["seg", "det"])
def test_left_out_fields_are_the_host_tables_bit_for_bit(name, task):
    """Backend.left_out_fields: FieldTables' weights and stop flags; at a scale of 2**60 every bit of the entropy
    shows, and it is NumPy's sum of the row's terms (the same order of addition, no multiply-add). A record's part,
    rows picked by an index and the "uncertain" indicator read back as the host's."""
    b = _backend(name)
    args, rows, tb = wide_rows(task, 3000)
    assert len(rows) > 1000
    ww, ws = tb(rows)
    w, s = b.left_out_fields(*args, float(ENTROPY_SCALE))
    assert w.numpy().tobytes() == ww.tobytes() and s.numpy().tobytes() == ws.astype(np.uint8).tobytes()
    w60, _ = b.left_out_fields(*args, 2.0**60)
    assert w60.numpy().tobytes() == exact_terms(task, rows, tb).tobytes()
    assert w[7:19].numpy().tobytes() == ww[7:19].tobytes()
    pick = np.array([11, 0, 3], dtype=np.int64)
    assert w[7:19].take(pick).numpy().tobytes() == ww[7:19][pick].tobytes()
    assert w.positive().numpy().tobytes() == (ww > 0).astype(np.int64).tobytes()


@pytest.mark.parametrize("name", _names())
@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("occlusion", ["sog", "none"])
@pytest.mark.parametrize("indicator", [None, "uncertain"])
def test_working_grids_written_from_device_rows_are_the_hosts(monkeypatch, drives, name, task, occlusion, indicator):
    """left_out.patched_in_place with the rows made on the device (every record's rows in one launch, each T's base
    rows too, the previous record's rows it does not touch put back from the base's by an index): after each
    record the working grid, and the "uncertain" indicator's, holds what the host's rows written in place give."""
    import place3d_kernels.left_out as left_out
    from place3d_kernels.left_out import LeftOutRows, patched_in_place

    rows = LeftOutRows(drives)
    first, second = rows.index(0)[1], rows.index(1)[1]       # both kinds of a previous record's rows occur:
    assert np.intersect1d(first, second).size and np.setdiff1d(first, second).size   # written again, put back
    assert rows.index(0)[0] == rows.index(1)[0]              # on the same working grid (one T)
    b = _backend(name)
    assert b.fields_on_device is not b.is_cpu   # a P-SOG's grid: GPUs with doubles, by default
    assert b.left_out_on_device                  # the jackknife's rows: every device with doubles

    def run():
        out = []
        for item in patched_in_place(drives, task, occlusion, b, indicator):     # valid until the next one
            out.append([grid_arrays(b, h) for h in (item if indicator else (item,))])
        return out

    _fields_here(monkeypatch, b, False)
    want = run()
    monkeypatch.undo()                      # the defaults again: the rows made on the device
    calls = []
    made = left_out.device_fields
    monkeypatch.setattr(left_out, "device_fields", lambda *a, **k: calls.append(1) or made(*a, **k))
    got = run()
    assert calls == [1]                     # every record's rows from one batch on the device
    assert len(got) == len(want) == len(drives)
    for i, (g, x) in enumerate(zip(got, want)):
        assert all(same_arrays(ga, xa) for ga, xa in zip(g, x)), i


@pytest.mark.parametrize("name", _names())
@pytest.mark.parametrize("normalisation", ["paper", "uncertain"])
def test_jackknife_scores_from_device_rows_are_the_hosts(monkeypatch, drives, name, normalisation):
    """The jackknife's samples (every drive left out, both tasks' rigs) with its rows made on the device: the same
    bits as with the host's rows."""
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.placement import Placement
    from place3d_kernels.uncertainty import jackknife_records

    lidar = LidarModel(np.radians([-20.0, -8.0, -2.0, 4.0]), np.radians(np.arange(0.0, 360.0, 15.0)), 30.0, "small")
    rigs = {n: Placement.load(n).poses for n in ("center", "line", "pyramid")}
    b = _backend(name)
    runs = []
    for here in (False, True):
        _fields_here(monkeypatch, b, here)
        runs.append(jackknife_records(drives.records, drives.grid, lidar, rigs, ("seg", "det"), "sog", b,
                                      normalisation=normalisation))
    for t in ("seg", "det"):
        assert runs[1][t].samples.tobytes() == runs[0][t].samples.tobytes(), t
        assert runs[1][t].point.tobytes() == runs[0][t].point.tobytes(), t


@pytest.mark.parametrize("name", _names())
@pytest.mark.parametrize("task", ["seg", "det"])
def test_a_psog_grid_from_device_rows_is_the_hosts(monkeypatch, drives, name, task):
    """PSOG.handle on a backend making fields on the device: its rows are made there from the count rows (not
    weight_rows), and the working grid is the one from the host's rows."""
    b = _backend(name)
    _fields_here(monkeypatch, b, False)
    want = grid_arrays(b, drives.psog().for_task(task).handle(b, "sog"))
    _fields_here(monkeypatch, b)
    got = drives.psog().for_task(task)          # a P-SOG of its own: handles are kept per P-SOG
    h = got.handle(b, "sog")
    assert ("device rows", b) in got._cache and "weight rows" not in got._cache
    assert same_arrays(grid_arrays(b, h), want)


@pytest.mark.parametrize("name", _names()[:1])
def test_device_rows_are_checked_before_any_write(name):
    """write_voxels with rows on the device refuses mismatched lengths, voxels off the grid, host stop flags
    beside device weights and weights and stop flags picked by different indexes; the grid is left as it was."""
    b = _backend(name)
    spec = GridSpec(voxel_size=0.5, shape=(4, 4, 4))
    tb = FieldTables(3, "seg")
    counts = np.zeros((6, N_CLASSES), dtype=np.int32)
    counts[:, 1] = np.arange(6) % 4
    w, s = b.left_out_fields(counts, np.arange(6), np.zeros(7, np.int32), np.zeros(1, np.int32),
                             np.zeros(1, np.int32), np.zeros(6, np.int32), np.array([3]), tb.term[None],
                             tb.stop[None].astype(np.uint8), np.zeros((1, 1, 1)), False, VEHICLE,
                             float(ENTROPY_SCALE))
    ids = np.arange(6, dtype=np.int64) * 5
    h = b.working_grid(spec, ids, w, s)
    before = grid_arrays(b, h)
    idx = np.array([0, 2])
    with pytest.raises(ValueError, match="one weight and one stop value per voxel"):
        b.write_voxels(h, ids[:4], w, s)
    with pytest.raises(ValueError, match=r"voxel indices must lie in \[0, 64\)"):
        b.write_voxels(h, ids + 40, w, s)
    with pytest.raises(TypeError, match="stop flags there too"):
        b.write_voxels(h, ids, w, np.zeros(6, dtype=bool))
    with pytest.raises(ValueError, match="same index"):
        b.write_voxels(h, ids[:2], w.take(idx), s.take(idx.copy()))
    with pytest.raises(ValueError, match="stop value per written voxel"):
        b.write_voxels(h, ids, w, None)
    with pytest.raises(IndexError):
        w.take(np.array([6]))
    assert same_arrays(grid_arrays(b, h), before)
    want = np.zeros(spec.n_voxels, dtype=np.int64)
    want[ids] = tb(np.c_[3 - counts[:, 1], counts[:, 1:]][:, :N_CLASSES])[0]
    assert b._read(h.weights, np.int64, spec.n_voxels).tobytes() == want.tobytes()


def test_a_gpu_keeps_device_copies_only_of_arrays_nobody_can_write():
    """OpenCLFields._resident on a GPU: a read-only array that owns its memory is sent once while it lives; a
    writable array or a view is sent again each time (a changed array is never read from a stale copy). Runs
    where an OpenCL GPU with doubles is lent; CPUs read the host memory itself."""
    import gc

    gpus = [n for n in _names() if "/" not in n and not _backend(n).is_cpu]
    if not gpus:
        pytest.skip("no OpenCL GPU here")
    b = _backend(gpus[0])

    def read(buf, n):
        return b._read(buf, np.int32, n)

    x = np.arange(10, dtype=np.int32)
    b._resident(x, np.int32)
    x[0] = 7
    assert read(b._resident(x, np.int32), 10)[0] == 7            # writable: sent again, with its new value
    x.setflags(write=False)
    kept = b._resident(x, np.int32)
    assert b._resident(x, np.int32) is kept and read(kept, 10).tolist() == x.tolist()
    view = x[2:]
    assert b._resident(view, np.int32) is not b._resident(view, np.int32)
    key = id(x)
    del x, view
    gc.collect()
    assert key not in b._resident_buffers                         # dropped with the host array
