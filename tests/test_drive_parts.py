"""A drive built in parts (``PSOGSpec.build_part``, merged with ``DriveRecord.merge``) is the drive built whole:
the same record, the same P-SOG and the same cache file, on every backend; and the cold commands' split of the
missing drives (``routes.build_missing``) gives the records and files of whole builds."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from place3d_kernels.lidar import LidarModel
from place3d_kernels.pipeline import drive_subsets, part_psog
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.sog import PSOG
from place3d_kernels.spec import ConditionSpec, PSOGSpec, SceneSpec


#: a small sensor, and a tiny one for the reference backend (it tests every ray against every triangle)
SMALL = LidarModel.uniform(16, fov_deg=(-25.0, 2.0), azimuth_steps=128, max_range=60.0, name="small16")
TINY = LidarModel.uniform(4, fov_deg=(-25.0, 2.0), azimuth_steps=24, max_range=60.0, name="tiny4")


def _same_record(a: DriveRecord, b: DriveRecord) -> None:
    assert a.label == b.label and a.n_subsets == b.n_subsets
    for f in ("voxels", "classes", "counts"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and np.array_equal(x, y), f


def _same_file(a, b) -> None:
    """Two cache entries hold the same arrays, and their manifests the same inputs (the zip members carry the
    time they were written, so the bytes differ)."""
    with np.load(a) as x, np.load(b) as y:
        assert x.files == y.files
        for k in x.files:
            assert x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k]), k
    ma, mb = (json.loads(p.with_suffix(".json").read_text()) for p in (a, b))
    assert ma["spec"] == mb["spec"] and ma["sha256"] == mb["sha256"]


def test_parts_merge_to_the_whole_drive(backend, tmp_path):
    spec = PSOGSpec(SceneSpec("town", 3, 9), backend=backend, grid=0.8, frames_per_subset=2,
                    lidar=TINY if backend == "reference" else SMALL)
    assert spec.subsets() == 4                       # 9 frames, k = 2: the trailing frame is dropped
    whole = spec.build(cache=str(tmp_path / "whole"))
    splits = [(0, 1, 4)] if backend == "reference" else [(0, 1, 4), (0, 2, 4), (0, 1, 2, 3, 4)]
    for i, cuts in enumerate(splits):
        folder = str(tmp_path / f"parts{i}")
        parts = [spec.build_part(range(a, b), cache=folder) for a, b in zip(cuts, cuts[1:])]
        assert [p.n_subsets for p in parts] == [b - a for a, b in zip(cuts, cuts[1:])]
        merged = DriveRecord.merge([DriveRecord.from_psog(p, "d") for p in parts])
        _same_record(merged, DriveRecord.from_psog(whole, "d"))
        psog = PooledPSOG(spec.grid.grid(), [merged]).psog()
        assert np.array_equal(psog.voxels, whole.voxels) and np.array_equal(psog.counts, whole.counts)
        assert psog.counts.dtype == whole.counts.dtype and psog.probs.tobytes() == whole.probs.tobytes()
        # the merged drive written to the cache: the file and manifest a whole build writes, found by build()
        assert spec.cached(cache=folder) is None                 # parts are never cached
        _same_file(spec.save(psog, cache=folder), spec.cache_file(cache=str(tmp_path / "whole")))
        found = spec.cached(cache=folder)
        assert found is not None and np.array_equal(found.counts, whole.counts)


def test_parts_under_a_condition_take_each_frame_index_of_the_drive(tmp_path):
    # a condition draws its noise per frame index: a part's frames keep their index in the drive
    spec = PSOGSpec(SceneSpec("town", 3, 8), backend="warp:cpu", grid=0.8, frames_per_subset=2,
                    condition=ConditionSpec("snow", seed=5))
    whole = spec.build(cache=False)
    parts = [spec.build_part(r, cache=str(tmp_path)) for r in (range(0, 3), range(3, 4))]
    _same_record(DriveRecord.merge([DriveRecord.from_psog(p, "d") for p in parts]), DriveRecord.from_psog(whole, "d"))
    # a part of the last subset alone is not the first subset's frames
    first = DriveRecord.from_psog(spec.build_part(range(0, 1), cache=str(tmp_path)), "d")
    last = DriveRecord.from_psog(parts[1], "d")
    assert not (len(first.voxels) == len(last.voxels) and np.array_equal(first.voxels, last.voxels))


def test_part_ranges_are_checked():
    scene = SceneSpec("town", 3, 6).build()
    assert drive_subsets(6, 2) == 3 and drive_subsets(6, 4) == 1 and drive_subsets(3, 4) == 1
    for bad in (range(0, 0), range(2, 4), range(-1, 1), range(0, 3, 2), (0, 1)):
        with pytest.raises(ValueError, match="subsets must be range"):
            part_psog(scene, bad, frames_per_subset=2, backend="warp:cpu")
    assert PSOGSpec(SceneSpec("mesh:x.obj")).subsets() == 1
    with pytest.raises(ValueError, match="built whole"):
        PSOGSpec(SceneSpec("mesh:x.obj")).build_part(range(0, 1))


def test_merge_sums_equal_entries_and_keeps_the_order():
    a = DriveRecord("d", 2, np.array([1, 1, 5], np.int64), np.array([2, 7, 3], np.int16), np.array([2, 1, 2], np.int32))
    b = DriveRecord("d", 3, np.array([0, 1, 5, 9], np.int64), np.array([4, 7, 3, 1], np.int16),
                    np.array([3, 2, 1, 3], np.int32))
    m = DriveRecord.merge([a, b])
    assert m.n_subsets == 5 and m.label == "d"
    assert m.voxels.tolist() == [0, 1, 1, 5, 9] and m.classes.tolist() == [4, 2, 7, 3, 1]
    assert m.counts.tolist() == [3, 2, 3, 3, 3]
    assert (m.voxels.dtype, m.classes.dtype, m.counts.dtype) == (np.int64, np.int16, np.int32)
    assert DriveRecord.merge([a]) is a
    with pytest.raises(ValueError):
        DriveRecord.merge([])
    p = PooledPSOG(__import__("place3d_kernels.grid", fromlist=["Grid"]).Grid((0, 0, 0), (1, 1, 10), 0.1), [m]).psog()
    assert isinstance(p, PSOG) and p.voxels.tolist() == [0, 1, 5, 9]
    assert p.counts[1].tolist()[:8] == [0, 0, 2, 0, 0, 0, 0, 3] and p.counts[:, 0].tolist() == [2, 0, 2, 2]


def test_drive_parts_leaves_a_quarter_of_the_cores():
    from place3d_app.commands.routes import DRIVE_PARTS, drive_parts

    assert DRIVE_PARTS == 2
    # the workers are DRIVE_PARTS per drive of the larger group (the later drives' parts queue behind)
    assert drive_parts(4, 4, 16) == 2 and drive_parts(4, 6, 16) == 2 and drive_parts(4, 7, 16) == 1
    assert drive_parts(4, 0, 11) == 2 and drive_parts(4, 0, 10) == 1 and drive_parts(8, 0, 16) == 1
    assert drive_parts(4, 0, 2) == 1 and drive_parts(0, 4, 16) == 1


def test_drive_plan_builds_whole_drives_with_later_ones_queued():
    from place3d_app.commands.routes import drive_plan

    # optimize's searched and held-out drives: whole, the held-out ones queued behind (one worker a drive)
    assert drive_plan(4, 4, 16) == (1, True) and drive_plan(2, 1, 8) == (1, True) and drive_plan(4, 7, 16) == (1, True)
    # no later drives (evaluate): parts where the cores allow them, else every drive whole at once
    assert drive_plan(4, 0, 16) == (2, True) and drive_plan(8, 0, 16) == (1, False)
    # too few cores for a worker a drive of the larger group: every drive whole at once, as many as the cores
    assert drive_plan(4, 4, 2) == (1, False) and drive_plan(4, 13, 16) == (1, False)


@pytest.mark.parametrize("held_out", [True, False], ids=["whole-with-held-out", "parts"])
def test_missing_drives_built_with_held_out_ones_later(tmp_path, monkeypatch, held_out):
    # eight cores: two searched drives whole (two workers) and the held-out drive queued behind them; without a
    # held-out drive, the two searched drives in two parts each (four workers). The command has the searched
    # drives' records when build_missing returns, the held-out one later, and the cache files are those of
    # whole builds
    import argparse

    from place3d_app import executors
    from place3d_app.commands.routes import build_missing, built_records

    made = []

    class Recorded(executors.ProcessExecutor):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

        def shutdown(self, wait=True, cancel=True):
            self.workers_at_end = list((getattr(self._pool, "_processes", None) or {}).values())
            super().shutdown(wait, cancel)

    monkeypatch.setattr(executors, "ProcessExecutor", Recorded)
    monkeypatch.delenv("PLACE3D_WORKERS", raising=False)
    monkeypatch.setattr("place3d_app.executors.usable_cores", lambda: 8)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "workers"))
    specs = [PSOGSpec(SceneSpec("town", s, 8), grid=0.8, frames_per_subset=2) for s in (3, 4)]
    later = [PSOGSpec(SceneSpec("town", 7, 8), grid=0.8, frames_per_subset=2)] if held_out else []
    opts = argparse.Namespace(no_cache=False, quiet=True, backend="warp:cpu")
    assert build_missing(opts, specs, "warp:cpu", later=later) == len(specs) + len(later)
    (ex,) = made
    assert ex.workers == (2 if held_out else 4) and set(opts.built) == set(specs) and set(opts.building) == set(later)
    held = built_records(opts, later)
    end = time.monotonic() + 120
    while not hasattr(ex, "workers_at_end") or any(p.is_alive() for p in ex.workers_at_end):
        assert time.monotonic() < end, "drive workers still running"
        time.sleep(0.05)
    for s in specs + later:
        whole = s.build(cache=str(tmp_path / "whole"), backend="warp:cpu")
        _same_record(({**opts.built, **held})[s], DriveRecord.from_psog(whole, s.scene.label))
        _same_file(s.cache_file(cache=str(tmp_path / "workers")), s.cache_file(cache=str(tmp_path / "whole")))
    assert build_missing(opts, specs, "warp:cpu", later=later) == 0        # warm: nothing missing


def test_later_drives_are_merged_as_they_come_back_and_a_failure_reaches_their_future():
    # routes._finish_later on the thread build_missing leaves: each later drive's parts merged into its Future
    # (the merged drive's write sent to the executor), a part's failure set on that drive's Future, and the pool
    # let go once every later drive is done, without dropping the writes
    from concurrent.futures import Future

    from place3d_app.commands import routes

    class Ex:
        def __init__(self):
            self.sent, self.ended = [], None

        def submit(self, fn, task):
            self.sent.append((fn.__name__, task[0]))
            f = Future()
            f.set_result(None)
            return f

        def shutdown(self, wait=True, cancel=True):
            self.ended = (wait, cancel)

    def done(value=None, error=None):
        f = Future()
        f.set_exception(error) if error else f.set_result(value)
        return f

    a = DriveRecord("a", 4, np.array([1, 2], np.int64), np.array([3, 3], np.int16), np.array([1, 2], np.int32))
    b = DriveRecord("a", 4, np.array([2, 5], np.int64), np.array([3, 1], np.int16), np.array([1, 1], np.int32))
    ex, building = Ex(), {"s1": Future(), "s2": Future()}
    later = [("s1", ("spec1", [done(a), done(b)])), ("s2", ("spec2", [done(a), done(error=RuntimeError("gpu lost"))]))]
    routes._finish_later(ex, later, building)
    _same_record(building["s1"].result(), DriveRecord.merge([a, b]))
    with pytest.raises(RuntimeError, match="gpu lost"):
        building["s2"].result()
    assert ex.sent == [("_save_drive", "spec1")] and ex.ended == (False, False)


def test_profiled_drive_workers_report_their_sections(tmp_path, monkeypatch):
    # under `place3d --profile` each drive task records its sections in its worker process (profiling.traced)
    # and the command's table gets them, placed by their start on the shared monotonic clock; the records are
    # those of a run without the profile
    import argparse

    from place3d_app.commands.routes import build_missing
    from place3d_kernels import profiling

    monkeypatch.delenv("PLACE3D_WORKERS", raising=False)
    monkeypatch.setattr("place3d_app.executors.usable_cores", lambda: 2)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "workers"))
    specs = [PSOGSpec(SceneSpec("town", s, 8), grid=0.8, frames_per_subset=2) for s in (5, 6)]
    opts = argparse.Namespace(no_cache=False, quiet=True, backend="warp:cpu")
    with profiling.profile(print_table=False) as p:
        assert build_missing(opts, specs, "warp:cpu") == 2
    task = ("drive worker task",)
    assert p.totals[task][1] == 2 and p.totals[task + ("P-SOG build: simulate",)][1] == 2
    assert p.totals[task + ("P-SOG build: aggregate", "P-SOG vote: keys and vote")][1] == 2 * 4
    first, last = p.spans[task]
    assert 0.0 <= first <= last <= p.wall
    back = ("drive worker task: result taken here",)         # each task's end to the command holding its record
    assert p.totals[back][1] == 2 and 0.0 <= p.totals[back][0] and p.spans[back][1] <= p.wall
    for s in specs:
        whole = s.build(cache=str(tmp_path / "whole"), backend="warp:cpu")
        _same_record(opts.built[s], DriveRecord.from_psog(whole, s.scene.label))


def test_traced_results_outside_a_profile_are_plain():
    from place3d_kernels import profiling

    t = profiling.traced("task", sum, [1, 2, 3])
    assert isinstance(t, profiling.Traced) and t.value == 6 and [c[0] for c in t.calls] == [("task",)]
    assert profiling.untraced(t) == 6 and profiling.untraced(7) == 7      # no profile here: nothing recorded
    with profiling.profile(print_table=False) as p:
        assert profiling.untraced(t) == 6
    assert p.totals[("task",)][1] == 1 and p.totals[("task: result taken here",)][1] == 1
    assert profiling.task("task", sum) is sum                          # sent as it is without a profile
    with profiling.profile(print_table=False) as p:
        assert profiling.untraced(profiling.traced("task", sum, [4])) == 4
        assert profiling.untraced(profiling.task("task", sum)([5])) == 5
    assert p.totals[("task",)][1] == 2 and p.spans[("task",)][0] >= 0.0


#: run in a fresh interpreter (one thread, as a worker's first task: forking is safe there): a worker's task for
#: drive A that also builds held-out drive B's scene, then its task for B; prints what the worker saw
PAIRED_TASKS = """
import json, sys
from place3d_app import prefetch
from place3d_app.commands import routes
from place3d_kernels import profiling
from place3d_kernels.spec import PSOGSpec, SceneSpec

a, b = (PSOGSpec(SceneSpec("town", s, 8), grid=0.8, frames_per_subset=2, backend="warp:cpu", cache=sys.argv[1])
        for s in (3, 7))
first = profiling.traced("task", routes._build_spec_then, (a, b))
pending = sorted(k.seed for k in prefetch._pending)        # B's scene, still in its child or waiting there
second = profiling.traced("task", routes._build_spec_then, (b, None))
rows = lambda t: sorted({" / ".join(path[1:]) for path, _, _ in t.calls if "scene: " in path[-1]})
print(json.dumps({"pending": pending, "first": rows(first), "second": rows(second),
                  "left": len(prefetch._pending)}))
import pickle
with open(sys.argv[2], "wb") as f:
    pickle.dump([first.value, second.value], f)
"""


def test_a_worker_builds_the_next_drives_scene_in_a_child_and_then_takes_it(tmp_path):
    # routes._build_spec_then((A, B)): A's scene and B's are built in forked children (prefetch) while the
    # worker's backend starts; the worker's next task, B, takes B's scene from its child instead of building it
    # (no new child: B's was pending after the first task, nothing is left after the second). The records are
    # those of builds in this process (no child), and so are the cache files
    import os
    import pickle
    import subprocess
    import sys
    from pathlib import Path

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("forked scene builds need 2+ cores")
    root = Path(__file__).resolve().parents[1]
    env = {k: v for k, v in os.environ.items() if k != "PLACE3D_SCENE_PREFETCH"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))
    p = subprocess.run([sys.executable, "-c", PAIRED_TASKS, str(tmp_path / "workers"), str(tmp_path / "records.pkl")],
                       capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["pending"] == [7] and got["left"] == 0
    built_in_child = ["P-SOG build: scene / scene: child: scene", "P-SOG build: scene / scene: forked build (wait)"]
    assert all(r in got["first"] for r in built_in_child) and all(r in got["second"] for r in built_in_child)
    with open(tmp_path / "records.pkl", "rb") as f:
        records = pickle.load(f)
    for s, rec in zip([PSOGSpec(SceneSpec("town", s, 8), grid=0.8, frames_per_subset=2) for s in (3, 7)], records):
        whole = s.build(cache=str(tmp_path / "whole"), backend="warp:cpu")
        _same_record(rec, DriveRecord.from_psog(whole, s.scene.label))
        _same_file(s.cache_file(cache=str(tmp_path / "workers")), s.cache_file(cache=str(tmp_path / "whole")))


def test_a_later_drive_is_sent_once_its_paired_task_is_done():
    # routes._after: the later drive's task goes to the executor only when the searched drive's task is done (its
    # worker is then the idle one), and its Future takes that task's result or error; a pool already shut down
    # (the command failed) reaches the Future as an error
    from concurrent.futures import Future, ThreadPoolExecutor

    from place3d_app.commands import routes

    sent = []

    class Counting(ThreadPoolExecutor):
        def submit(self, fn, *args):
            sent.append(args)
            return super().submit(fn, *args)

    def square(x):
        if x < 0:
            raise ValueError("no drive")
        return x * x

    with Counting(2) as ex:
        first = Future()
        out = routes._after(ex, first, square, 3)
        assert not out.done() and sent == []
        first.set_result("searched drive")
        assert out.result(timeout=10) == 9 and sent == [(3,)]
        failing = Future()
        bad = routes._after(ex, failing, square, -1)
        failing.set_exception(RuntimeError("its paired task failed"))     # the later drive is still built
        with pytest.raises(ValueError, match="no drive"):
            bad.result(timeout=10)
    late = Future()
    gone = routes._after(ex, late, square, 2)
    late.set_result(None)
    with pytest.raises(RuntimeError, match="shutdown"):
        gone.result(timeout=10)
