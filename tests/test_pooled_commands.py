"""Pooled answers in the commands (issue 34, item 3): --routes, --route-seeds, repeated --scene, shipped
CARLA maps by name, and a tiny pooled evaluate / optimize on the embedded town."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from place3d_app.cli import build_parser, main
from place3d_app.commands.routes import SINGLE_ROUTE_WARNING, drive_specs
from place3d_kernels.pooled import DEFAULT_ROUTES, parse_route_seeds
from place3d_kernels.spec import SceneSpec, specs_from_args

TINY = ["--frames", "8", "--voxel-size", "0.8", "--quiet"]


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path_factory.getbasetemp() / "pooled-cache"))


# ------------------------------------------------------------------------------ parsing
@pytest.mark.parametrize("text, want", [("100-107", list(range(100, 108))), ("1,2,5", [1, 2, 5]),
                                        ("0-2, 10", [0, 1, 2, 10]), ("7", [7]), ("-1", [-1])])
def test_route_seeds_parse_ranges_and_lists(text, want):
    assert parse_route_seeds(text) == want


@pytest.mark.parametrize("text", ["7-3", "1,1", "0-2,2", "x", "", "1.5"])
def test_bad_route_seeds_are_refused(text):
    with pytest.raises(ValueError, match="route seeds"):
        parse_route_seeds(text)


def _drives(argv):
    args = build_parser().parse_args(argv)
    return args, drive_specs(args, specs_from_args(args))


def test_scenes_times_route_seeds_make_the_drives():
    args, drives = _drives(["evaluate", "--scene", "town", "--scene", "opendrive:Town06", "--route-seeds", "100-101"])
    assert args.scene == "town" and args.scenes == ["town", "opendrive:Town06"]
    assert [(d.scene.name, d.scene.seed) for d in drives] == [("town", 100), ("town", 101), ("opendrive:Town06", 100),
                                                              ("opendrive:Town06", 101)]
    _, drives = _drives(["evaluate", "--seed", "5", "--routes", "3"])
    assert [d.scene.seed for d in drives] == [5, 6, 7]
    _, drives = _drives(["optimize", "--condition", "fog"])         # the default: pooled, condition on each drive
    assert [d.scene.seed for d in drives] == list(range(DEFAULT_ROUTES)) and DEFAULT_ROUTES > 1
    assert all(d.condition is not None and d.condition.name == "fog" for d in drives)


def test_disagreeing_or_impossible_route_choices_are_refused(tmp_path):
    with pytest.raises(ValueError, match="disagree"):
        _drives(["evaluate", "--routes", "3", "--route-seeds", "1-2"])
    with pytest.raises(ValueError, match="--routes must be >= 1"):
        _drives(["evaluate", "--routes", "0"])
    mesh = tmp_path / "m.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="one fixed route"):
        _drives(["evaluate", "--scene", f"mesh:{mesh}", "--labels", "road", "--routes", "2"])
    _, drives = _drives(["evaluate", "--scene", f"mesh:{mesh}", "--labels", "road"])   # default: its one route
    assert len(drives) == 1


# ------------------------------------------------------------------------------ shipped maps by name
def test_shipped_carla_map_resolves_by_name_everywhere():
    from place3d_app.commands.reproduce import resolve_town
    from place3d_kernels.scene.keymemo import identity

    s = SceneSpec("opendrive:Town06").validate()
    assert s.path.is_file() and s.path.name == "Town06.xodr" and s.label == "Town06-s0-f40"
    # the scene key's identity reads the file: this raised "No such file or directory: 'Town06'"
    assert identity(s.to_dict(), s.kind, s.path) is not None
    assert resolve_town("Town06").endswith("Town06.xodr")
    with pytest.raises(FileNotFoundError, match="shipped maps by name"):
        SceneSpec("opendrive:Town99").validate()


# ------------------------------------------------------------------------------ pooled commands
def test_tiny_pooled_evaluate_scores_the_pool_of_its_routes(tmp_path, capsys):
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import Placement
    from place3d_kernels.pooled import pool_specs

    out = tmp_path / "e.json"
    assert main(["evaluate", *TINY, "--routes", "2", "center", "line-roll", "--output", str(out)]) == 0
    assert SINGLE_ROUTE_WARNING not in capsys.readouterr().err
    d = json.loads(out.read_text())
    assert d["drives"] == ["town-s0-f8", "town-s1-f8"] and d["route_seeds"] == [0, 1]
    assert d["bootstrap"]["unit"] == "drives" and d["bootstrap"]["n_units"] == 2 and d["bootstrap"]["df"] == 1
    _, drives = _drives(["evaluate", *TINY, "--routes", "2"])
    pooled = pool_specs(drives, backend=d["backend"])
    assert pooled.n_subsets == d["n_subsets"] == 4
    want = msog_batch(pooled.psog(), LidarModel.load("place3d_16ch"),
                      np.stack([Placement.load(r["placement"]).poses for r in d["rows"]]), "sog", "seg", d["backend"])
    assert [r["msog_seg"] for r in d["rows"]] == want.tolist()
    for r in d["rows"]:
        for t in ("seg", "det"):
            lo, hi = r["ci"][t]
            assert lo < r[f"msog_{t}"] < hi                    # the interval contains its own estimate


def test_one_route_is_explicit_and_warns(tmp_path, capsys):
    out = tmp_path / "one.json"
    assert main(["evaluate", *TINY, "--routes", "1", "center", "--interval", "none", "--output", str(out)]) == 0
    assert SINGLE_ROUTE_WARNING in capsys.readouterr().err
    assert json.loads(out.read_text())["drives"] == ["town-s0-f8"]
    assert main(["evaluate", *TINY, "--routes", "2", "--interval", "bootstrap", "center"]) == 2
    assert "jackknife" in capsys.readouterr().err


def test_tiny_pooled_optimize_reports_intervals_over_routes(tmp_path):
    out = tmp_path / "opt"
    # the paper's normalisation, named: under optimize's default (uncertain) these 8-frame drives leave
    # every left-out pool of T = 2 subsets, whose uncertain voxels all have H = ln 2, so the interval's lower
    # end meets the estimate
    assert main(["optimize", *TINY, "--route-seeds", "3,4", "--max-evals", "12", "--normalisation", "paper",
                 "--output", str(out)]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["drives"] == ["town-s3-f8", "town-s4-f8"] and r["n_subsets"] == 4
    assert r["intervals"]["unit"] == "drives" and r["intervals"]["n_units"] == 2
    assert [d["seed"] for d in r["setup"]["drives"]] == [3, 4]          # a resume must pool the same drives
    lo, hi = r["intervals"]["best"]["ci"]
    assert lo < r["best_score"] < hi
    # a held-out seed that the pool trained on validates nothing
    assert main(["optimize", *TINY, "--route-seeds", "3,4", "--max-evals", "12", "--holdout-seeds", "4"]) == 2


# ------------------------------------------------------------------------------ drives built in workers
def test_missing_drives_are_built_in_worker_processes_with_the_same_pool(tmp_path, monkeypatch, capsys):
    # the drives a cold cache lacks are built by worker processes; the pool read back from the cache is the
    # pool built one drive after another in this process, bit for bit; a warm cache starts no worker. The
    # workers come from the commands' server (a forkserver on Linux), started before the backend is known,
    # and are ended once every drive has returned
    import argparse
    from concurrent.futures import Future

    from place3d_app import executors
    from place3d_app.commands.routes import build_missing
    from place3d_kernels.pooled import pool_specs

    made = []

    class Recorded(executors.ProcessExecutor):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.backend_when_started = "never"
            made.append(self)

        def start_server(self):
            self.backend_when_started = self.backend
            super().start_server()

        def shutdown(self, wait=True, cancel=True):
            self.waited = wait
            self.workers_at_end = list((getattr(self._pool, "_processes", None) or {}).values())
            super().shutdown(wait, cancel)

    monkeypatch.setattr(executors, "ProcessExecutor", Recorded)
    monkeypatch.setenv("PLACE3D_WORKERS", "2")
    monkeypatch.setattr("place3d_app.executors.usable_cores", lambda: 2)
    args = build_parser().parse_args(["optimize", *TINY, "--route-seeds", "3,4", "--backend", "warp:cpu"])
    specs = drive_specs(args, specs_from_args(args))
    assert len(specs) == 2
    # the workers' server started before this command's cache folder was set: the folder travels with the drives
    executors.ProcessExecutor(1, start_method=executors.command_start_method()).start_server()
    made.clear()
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "workers"))
    assert [s.cache_file() for s in specs] == [None, None]       # scene keys never remembered here
    opts = argparse.Namespace(no_cache=False, quiet=True, backend="warp:cpu")
    probe = Future()                                                  # optimize's probe, answered later
    probe.set_result("warp:cpu")
    assert build_missing(opts, specs, probe) == 2
    (ex,) = made
    # a worker returns its drive's record while the file is still written, and ends once it is: the files are
    # whole when the workers are gone (the command's exit waits for that)
    end = time.monotonic() + 60
    while any(p.is_alive() for p in ex.workers_at_end):
        assert time.monotonic() < end, "drive workers still running"
        time.sleep(0.05)
    assert ex.workers_at_end and all(s.cache_file() is not None and s.cache_file().exists() for s in specs)
    assert ex.start_method == executors.command_start_method() and ex.preload == "warp:cpu"
    # no backend at a worker's start: each drive task starts its worker's (a held-out drive's after its scene)
    assert ex.backend_when_started is None and ex.backend is None and ex.waited is False
    assert build_missing(opts, specs, "warp:cpu") == 0               # warm: nothing missing, no workers
    a = pool_specs(specs, backend="warp:cpu").psog()
    # the workers' records, pooled without reading the files, are the records read back
    assert set(opts.built) == set(specs)
    capsys.readouterr()
    sent = pool_specs(specs, backend="broken-if-used", known=opts.built, progress=True)
    # a worker's drive is not reported as taking the pooling's 0.0 s
    assert capsys.readouterr().err.count(": built by a worker\n") == len(specs)
    read = pool_specs(specs, backend="warp:cpu")
    for x, y in zip(sent.records, read.records):
        assert x.label == y.label and x.n_subsets == y.n_subsets
        for f in ("voxels", "classes", "counts"):
            assert getattr(x, f).dtype == getattr(y, f).dtype and np.array_equal(getattr(x, f), getattr(y, f))
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "here"))
    b = pool_specs(specs, backend="warp:cpu").psog()
    assert np.array_equal(a.voxels, b.voxels) and np.array_equal(a.counts, b.counts) and a.n_subsets == b.n_subsets
    assert build_missing(argparse.Namespace(no_cache=True, quiet=True), specs, "warp:cpu") == 0


def test_drive_workers_do_not_wait_for_a_running_probe(tmp_path, monkeypatch):
    # optimize's probe (a Future) still running: the workers take the name the command was given and resolve it
    # themselves, so build_missing returns with the drives built while the probe has not answered (it would
    # answer in 60 s: code that waited for it returns after that)
    import argparse
    import threading
    from concurrent.futures import Future

    from place3d_app.commands.routes import _workers_backend, build_missing
    from place3d_kernels.backends.registry import get_backend

    monkeypatch.setenv("PLACE3D_WORKERS", "2")
    monkeypatch.setattr("place3d_app.executors.usable_cores", lambda: 2)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "c"))
    _, specs = _drives(["optimize", *TINY, "--route-seeds", "3,4", "--backend", "warp:cpu"])
    opts = argparse.Namespace(no_cache=False, quiet=True, backend="warp:cpu")
    probe = Future()
    late = threading.Timer(60, probe.set_result, (get_backend("warp:cpu"),))
    late.start()
    try:
        assert build_missing(opts, specs, probe) == 2
        assert not probe.done() and set(opts.built) == set(specs)
    finally:
        late.cancel()
    # the name the workers take: the one given, else $PLACE3D_BACKEND, else auto; a finished probe's own
    monkeypatch.delenv("PLACE3D_BACKEND", raising=False)
    assert _workers_backend(argparse.Namespace(backend=None), Future()) == "auto"
    monkeypatch.setenv("PLACE3D_BACKEND", "reference")
    assert _workers_backend(argparse.Namespace(backend=None), Future()) == "reference"
    assert _workers_backend(argparse.Namespace(backend=" warp:cpu "), Future()) == "warp:cpu"
    done = Future()
    done.set_result(get_backend("warp:cpu"))
    assert _workers_backend(argparse.Namespace(backend="auto"), done) == "warp:cpu"


def test_optimize_with_drives_to_build_and_a_backend_that_does_not_resolve_says_so_once(tmp_path):
    # the workers start on the name given while the probe runs (_workers_backend): a name that resolves nowhere is
    # still reported once, exit 2, no traceback
    import os
    import subprocess
    import sys

    env = {**os.environ, "PLACE3D_CACHE": str(tmp_path / "c"), "PLACE3D_WORKERS": "2"}
    r = subprocess.run([sys.executable, "-m", "place3d_app", "optimize", *TINY, "--route-seeds", "3,4",
                        "--max-evals", "12", "--backend", "nosuch"], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert r.stderr.count("Unknown or unavailable backend 'nosuch'") == 1


def test_evaluate_with_drives_to_build_and_a_backend_that_does_not_resolve_says_so_once(tmp_path):
    # with drives to build in worker processes, a backend name that does not resolve is reported once, in
    # the probe's own words (no worker traceback), exit 2
    import os
    import subprocess
    import sys

    env = {**os.environ, "PLACE3D_CACHE": str(tmp_path / "c"), "PLACE3D_WORKERS": "2"}
    r = subprocess.run([sys.executable, "-m", "place3d_app", "evaluate", *TINY, "--routes", "2",
                        "--backend", "nosuch"], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert r.stderr.count("Unknown or unavailable backend 'nosuch'") == 1


def test_evaluate_cold_warm_and_in_process_give_one_table(tmp_path, capsys, monkeypatch):
    # cold (worker processes build the drives), then warm (read from the cache), then the drives one after
    # the other in this process: one table
    monkeypatch.setattr("place3d_app.executors.usable_cores", lambda: 2)
    argv = ["evaluate", *TINY, "--routes", "2", "--backend", "warp:cpu", "--interval", "none"]
    tables = []
    for cache, workers in (("c", "2"), ("c", "2"), ("here", "1")):
        monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / cache))
        monkeypatch.setenv("PLACE3D_WORKERS", workers)
        assert main(argv) == 0
        tables.append([line for line in capsys.readouterr().out.splitlines() if not line.endswith(" s")])
    assert tables[0] == tables[1] == tables[2] and len(tables[0]) > 5


def test_cached_drives_are_read_side_by_side_before_the_probe_is_waited_for(tmp_path, monkeypatch, capsys):
    # the drives the cache holds are read (pooled.cached_records, on threads) before optimize's backend probe is
    # waited for; a drive the cache lacks is built afterwards on the probed backend; the pool is the one
    # pool_specs makes reading the files one by one
    from concurrent.futures import Future

    from place3d_app.commands.routes import pooled_psog
    from place3d_kernels import pooled
    from place3d_kernels.pooled import cached_records, pool_specs

    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "c"))
    args, specs = _drives(["optimize", *TINY, "--route-seeds", "3-5", "--backend", "warp:cpu"])
    args.quiet = False
    first = pool_specs(specs[:2], backend="warp:cpu")                 # two of the three drives cached
    got = cached_records(specs)
    assert list(got) == specs[:2] and cached_records(specs, cache=False) == {}
    for x, y in zip(got.values(), first.records):
        assert x.label == y.label and x.n_subsets == y.n_subsets
        assert all(np.array_equal(getattr(x, f), getattr(y, f)) for f in ("voxels", "classes", "counts"))
    probe, seen, real = Future(), [], pooled.cached_records

    def spy(todo, cache=True):
        seen.append((probe.done(), [s.scene.seed for s in todo]))
        out = real(todo, cache)
        if not probe.done():
            probe.set_result("warp:cpu")
        return out

    monkeypatch.setattr(pooled, "cached_records", spy)
    import threading

    late = threading.Timer(5.0, lambda: probe.done() or probe.set_result("warp:cpu"))   # a reader that waits
    late.start()                                                  # for the probe first ends, and fails below
    capsys.readouterr()
    _, _, psog = pooled_psog(args, specs_from_args(args), probe, specs)
    err = capsys.readouterr().err
    late.cancel()
    assert seen[0] == (False, [3, 4, 5])              # read before the probe had answered
    lines = [line for line in err.splitlines() if line.startswith("  drive ")]
    assert [line.endswith(": read from the cache") for line in lines] == [True, True, False]
    assert lines[2].startswith("  drive 3/3 ") and lines[2].endswith(" s")          # built here, timed
    want = pool_specs(specs, backend="warp:cpu").psog()
    assert np.array_equal(psog.voxels, want.voxels) and np.array_equal(psog.counts, want.counts)
    assert psog.n_subsets == want.n_subsets


def test_a_damaged_cached_drive_is_reported_once_and_rebuilt(tmp_path, monkeypatch):
    # the side-by-side reads (cached_records) leave a file that fails its check to the build, which reports it
    # (one warning, not one from each reader) and rebuilds the same P-SOG
    from place3d_kernels.manifest import StaleCacheWarning
    from place3d_kernels.pooled import pool_specs

    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "c"))
    _, specs = _drives(["evaluate", *TINY, "--route-seeds", "7-8", "--backend", "warp:cpu"])
    want = pool_specs(specs, backend="warp:cpu").psog()
    f = specs[1].cache_file()
    f.write_bytes(f.read_bytes() + b"damage")
    with pytest.warns(StaleCacheWarning) as seen:
        got = pool_specs(specs, backend="warp:cpu").psog()
    assert [f.name in str(w.message) for w in seen if issubclass(w.category, StaleCacheWarning)] == [True]
    assert np.array_equal(got.voxels, want.voxels) and np.array_equal(got.counts, want.counts)
