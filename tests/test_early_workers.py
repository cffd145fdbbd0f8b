"""Drive workers spawned at the console script's start (``place3d_app.early_workers``): when the launcher spawns
them instead of starting the forkserver, how many, that the drives' step takes them and builds the drives a whole
build makes, and that a pool nobody takes ends."""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

import pytest

from place3d_app import early_workers, forkserver
from place3d_kernels.pooled import DEFAULT_ROUTES, DriveRecord
from place3d_kernels.spec import PSOGSpec, SceneSpec

from test_drive_parts import _same_file, _same_record


@pytest.fixture
def launcher(monkeypatch, tmp_path):
    """The launcher's decision alone, on a 16-core Linux host with an empty cache: what it started."""
    started = []
    monkeypatch.setattr(forkserver, "start", lambda b, opendrive=True: started.append(("server", b, opendrive)))
    monkeypatch.setattr(early_workers, "start", lambda n, b, preload: started.append(("early", n, b, preload)))
    monkeypatch.setattr(early_workers, "wanted", lambda b: b in ("auto", "warp:cuda:0"))
    for env in (forkserver.START_METHOD_ENV, forkserver.WORKERS_ENV, "PLACE3D_BACKEND"):
        monkeypatch.delenv(env, raising=False)
    monkeypatch.setattr(forkserver, "_usable_cores", lambda: 16)
    monkeypatch.setattr(forkserver.sys, "platform", "linux")
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    return started


@pytest.mark.parametrize("argv, workers", [
    (["optimize"], 8),                                      # 4 searched + 4 held-out drives, two parts each
    (["--profile", "optimize", "--max-evals", "20", "--backend=warp:cuda:0"], 8),
    (["evaluate"], 8),
    (["optimize", "--no-holdout", "--routes", "2"], 4),
    (["optimize", "--routes=8"], 16),                        # 16 drives whole: one worker a core
    (["evaluate", "--scene", "town", "--scene", "opendrive:Town01"], 8),     # 8 drives whole
])
def test_the_launcher_spawns_the_drive_workers_for_a_cuda_backend(launcher, argv, workers):
    assert forkserver.start_early(argv)
    ((kind, n, backend, preload),) = launcher
    assert kind == "early" and n == workers
    assert backend == (argv[-1].partition("=")[2] if "--backend" in argv[-1] else "auto")
    opendrive = any(a.startswith("opendrive:") for a in argv)
    assert preload == forkserver.preload_for(backend, opendrive=opendrive)


@pytest.mark.parametrize("argv", [
    ["optimize", "--backend", "opencl:nvidia"],                 # not Warp's CUDA: the forkserver, as before
    ["optimize", "--backend", "warp:cpu"],
    ["optimize", "--route-seeds", "0-3"],                       # a count this guess does not read
    ["optimize", "--holdout-seeds", "100-101"],
    ["optimize", "--holdout-scenes", "Town03"],
])
def test_the_launcher_keeps_the_forkserver_where_it_does_not_spawn(launcher, argv):
    assert forkserver.start_early(argv)
    assert [s[0] for s in launcher] == ["server"]


def test_the_start_method_or_a_backend_in_the_environment_decide_too(launcher, monkeypatch):
    monkeypatch.setenv(forkserver.START_METHOD_ENV, "forkserver")
    assert forkserver.start_early(["optimize"]) and launcher[-1] == ("server", "auto", False)
    monkeypatch.delenv(forkserver.START_METHOD_ENV)
    monkeypatch.setenv("PLACE3D_BACKEND", "opencl:nvidia")
    assert forkserver.start_early(["optimize"]) and launcher[-1] == ("server", "opencl:nvidia", False)
    monkeypatch.setenv("PLACE3D_BACKEND", "warp:cuda:0")
    assert forkserver.start_early(["optimize"]) and launcher[-1][:3] == ("early", 8, "warp:cuda:0")


def test_the_guess_is_the_count_build_missing_starts():
    # the launcher's guess and build_missing share drive_workers; the default routes are written twice
    from place3d_app.commands.routes import drive_parts

    assert forkserver.DEFAULT_ROUTES == DEFAULT_ROUTES
    for first, later, cores in ((4, 4, 16), (4, 0, 16), (8, 0, 16), (4, 4, 8), (16, 16, 16), (2, 2, 2)):
        parts, n = forkserver.drive_workers(first, later, cores)
        assert parts == drive_parts(first, later, cores)
        # build_missing: whole drives take one worker each, parts queue the later drives behind the first
        assert n == (min(cores, first + later) if parts == 1 else min(cores, max(first, later) * parts))
    assert forkserver._drive_workers_guess("optimize", ["optimize", "--routes", "1"], ["town"], 16) == 2
    assert forkserver._drive_workers_guess("evaluate", ["evaluate", "--routes", "1"], ["town"], 16) == 0


def test_wanted_needs_a_warp_cuda_name_and_can_be_turned_off(monkeypatch):
    monkeypatch.setenv(early_workers.ENV, "0")
    assert not early_workers.wanted("warp:cuda:0")
    monkeypatch.delenv(early_workers.ENV)
    for name in ("warp:cpu", "opencl:nvidia", "reference", "opencl:pocl"):
        assert not early_workers.wanted(name)
    monkeypatch.setenv("PLACE3D_START_METHOD", "forkserver")
    assert not early_workers.wanted("warp:cuda:0")


def test_cuda_early_loads_without_the_package_and_is_the_packages_module():
    # in a fresh interpreter, as a spawned worker: the module from its file, NumPy and the library not imported,
    # and the package's own import of it then finds that module (Warp's start reads its record of the thread)
    code = ("import sys\n"
            "from place3d_app import early_workers\n"
            "m = early_workers.cuda_early()\n"
            "assert m is not None and 'numpy' not in sys.modules and 'place3d_kernels' not in sys.modules\n"
            "assert m.ordinal_of('warp:cuda:1') == 1 and m.ordinal_of('warp:cpu') is None\n"
            "from place3d_kernels.backends import cuda_early\n"
            "import place3d_kernels.backends.cuda_early as again\n"
            "assert cuda_early is m and again is m\n"
            "print('ok')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_the_drives_step_takes_the_spawned_workers(tmp_path, monkeypatch):
    # two workers spawned as the launcher spawns them (on Warp's CPU here: the same start, without a context to
    # make), taken by build_missing as its pool: the drives come back, and their files are those of whole builds
    from place3d_app import executors
    from place3d_app.commands.routes import build_missing, built_records

    monkeypatch.delenv("PLACE3D_WORKERS", raising=False)
    monkeypatch.setattr("place3d_app.executors.usable_cores", lambda: 2)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "workers"))
    early_workers.start(2, "warp:cpu", forkserver.preload_for("warp:cpu", opendrive=False))
    (pool, n, backend) = early_workers._pool[-1]
    assert (n, backend) == (2, "warp:cpu")
    end = time.monotonic() + 60
    while len(pool._processes or ()) < 2:
        assert time.monotonic() < end, "workers not spawned"
        time.sleep(0.02)
    spawned = dict(pool._processes)
    made = []

    class Recorded(executors.ProcessExecutor):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

        def shutdown(self, wait=True, cancel=True):
            self.workers_at_end = dict(getattr(self._pool, "_processes", None) or {})
            super().shutdown(wait, cancel)

    monkeypatch.setattr(executors, "ProcessExecutor", Recorded)
    specs = [PSOGSpec(SceneSpec("town", s, 6), grid=0.8, frames_per_subset=2) for s in (3, 4)]
    later = [PSOGSpec(SceneSpec("town", 7, 6), grid=0.8, frames_per_subset=2)]
    opts = argparse.Namespace(no_cache=False, quiet=True, backend="warp:cpu")
    assert build_missing(opts, specs, "warp:cpu", later=later) == 3
    (ex,) = made
    assert ex._pool in (pool, None)               # the spawned pool (None once let go after the later drive)
    assert ex.workers == 2 and ex.start_method == "spawn" and early_workers.take() is None
    held = built_records(opts, later)
    end = time.monotonic() + 120
    while not hasattr(ex, "workers_at_end"):
        assert time.monotonic() < end, "the pool was not let go"
        time.sleep(0.05)
    assert ex.workers_at_end == spawned           # no other process started: the drives ran on the spawned two
    while any(p.is_alive() for p in spawned.values()):
        assert time.monotonic() < end, "spawned drive workers still running"
        time.sleep(0.05)
    for s in specs + later:
        whole = s.build(cache=str(tmp_path / "whole"), backend="warp:cpu")
        _same_record(({**opts.built, **held})[s], DriveRecord.from_psog(whole, s.scene.label))
        _same_file(s.cache_file(cache=str(tmp_path / "workers")), s.cache_file(cache=str(tmp_path / "whole")))


def test_a_pool_nobody_takes_is_let_go(tmp_path, monkeypatch):
    # a command that needs no workers after all (its drives cached meanwhile, an error first): the workers end
    from place3d_app.commands.routes import build_missing

    early_workers.start(2, "warp:cpu", [])
    pool = early_workers._pool[-1][0]
    end = time.monotonic() + 60
    while len(pool._processes) < 2:
        assert time.monotonic() < end, "workers not spawned"
        time.sleep(0.02)
    procs = list(pool._processes.values())
    assert build_missing(argparse.Namespace(no_cache=True), [], "warp:cpu") == 0     # --no-cache: none needed
    assert early_workers.take() is None
    end = time.monotonic() + 60
    while any(p.is_alive() for p in procs):
        assert time.monotonic() < end, "an untaken worker still running"
        time.sleep(0.05)
