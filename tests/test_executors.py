"""The process executor (issue 36): drives built in worker processes give the pool the local executor gives,
bit for bit and in drive order; ``--executor auto`` picks it only where there are several drives and cores."""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from place3d_app import executors, forkserver
from place3d_app.executors import LocalExecutor, ProcessExecutor, executor_from_args
from place3d_kernels.pooled import Drive, PoolSettings, build_pooled


def _same_records(a, b) -> None:
    assert a.labels == b.labels
    for ra, rb in zip(a.records, b.records):
        assert ra.n_subsets == rb.n_subsets
        for field in ("voxels", "classes", "counts"):
            x, y = getattr(ra, field), getattr(rb, field)
            assert x.dtype == y.dtype and np.array_equal(x, y), (ra.label, field)


@pytest.mark.parametrize("start_method", ["spawn", "forkserver"])
def test_process_pool_is_the_local_pool_bit_for_bit(device_backend, start_method):
    # three routes of the embedded town, of different lengths, so that a pool put together in another order
    # than the drives' would differ; a fresh build in every worker (no cache to read); workers spawned, or forked
    # from a server that imported the package, SciPy and Warp first (the commands' default on Linux)
    settings = PoolSettings(0.8, "collection_64ch", 4, device_backend, False)
    drives = [Drive("town", seed=s, frames=f) for s, f in ((0, 8), (1, 4), (2, 8))]
    local = build_pooled(drives, settings, executor=LocalExecutor())
    with ProcessExecutor(2, backend=device_backend, start_method=start_method) as ex:
        procs = build_pooled(drives, settings, executor=ex)
        assert ex.submitted == 2          # two routes of one town a task (scene_groups)
    _same_records(procs, local)
    (va, ca, ta), (vb, cb, tb) = procs.counts(), local.counts()
    assert ta == tb == 5 and np.array_equal(va, vb) and np.array_equal(ca, cb)
    assert np.array_equal(procs.psog().probs, local.psog().probs)


def test_a_profiled_process_pool_reports_its_workers_steps():
    # under --profile (a profile running here) each worker task records its steps (profiling.traced) and the
    # table here gets them: one "drive worker task" call a task, the simulation nested; the same pool as without
    from place3d_kernels import profiling

    settings = PoolSettings(0.8, "collection_64ch", 4, "warp:cpu", False)
    drives = [Drive("town", seed=s, frames=f) for s, f in ((0, 8), (1, 4), (2, 8))]
    with profiling.profile(print_table=False) as p:
        with ProcessExecutor(2, backend="warp:cpu") as ex:
            procs = build_pooled(drives, settings, executor=ex)
    task = ("drive worker task",)
    assert p.totals[task][1] == 2 and p.totals[task + ("P-SOG build: simulate",)][1] == 3
    assert 0.0 <= p.spans[task][0] <= p.spans[task][1] <= p.wall
    _same_records(procs, build_pooled(drives, settings, executor=LocalExecutor()))


@pytest.mark.parametrize("wait", [True, False])
def test_the_workers_cache_files_are_whole_when_the_workers_end(device_backend, tmp_path, monkeypatch, wait):
    # the workers compress each drive's P-SOG into the cache on a thread while they build the next drive, and
    # return the last one's record before its file is written; a worker ends only once its files are whole,
    # leaving after its tasks (wait or not), so a command run next reads them all, simulating none
    settings = PoolSettings(0.8, "collection_64ch", 4, device_backend, str(tmp_path))
    drives = [Drive("town", seed=s, frames=f) for s, f in ((0, 8), (1, 4), (2, 8))]
    ex = ProcessExecutor(2, backend=device_backend)
    built = build_pooled(drives, settings, executor=ex)
    workers = list(ex._pool._processes.values())
    ex.shutdown(wait=wait)
    _wait_until_gone(workers)
    assert len(list(tmp_path.glob("psog-*.json"))) == 3          # the manifests, each written after its file

    def no_simulation(*a, **k):
        raise AssertionError("a drive was simulated again: its cache file was missing or unreadable")

    monkeypatch.setattr("place3d_kernels.pipeline.simulate", no_simulation)
    _same_records(build_pooled(drives, settings, executor=LocalExecutor()), built)


def test_idle_workers_ended_by_shutdown_finish_their_cache_writes_first(tmp_path, monkeypatch):
    # a write that takes a second, left on a worker's saver thread by a task that has returned: ending the idle
    # workers (shutdown(wait=False)) waits for it: they leave once it is written
    (tmp_path / "slowsave.py").write_text(
        "import time\n"
        "from pathlib import Path\n"
        "from place3d_kernels import pipeline\n"
        "def write_later(path):\n"
        "    def save():\n"
        "        time.sleep(1.0)\n"
        "        Path(path).write_text('whole')\n"
        "    pipeline._saves.append(pipeline._saver().submit(save))\n"
        "    return pipeline.saves_outlive_tasks()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import slowsave

    paths = [str(tmp_path / f"file{i}") for i in range(2)]
    ex = ProcessExecutor(2)
    assert ex.map(slowsave.write_later, paths) == [True, True]
    workers = list(ex._pool._processes.values())
    ex.shutdown(wait=False)                                  # returns at once; the workers finish on their own
    _wait_until_gone(workers)
    assert [Path(p).read_text() for p in paths] == ["whole", "whole"]


def _wait_until_gone(processes, timeout: float = 60.0) -> None:
    # the pool's own thread reaps them (a join here may race it for the exit status), so poll for them gone
    end = time.monotonic() + timeout
    while any(p.is_alive() for p in processes):
        assert time.monotonic() < end, "worker processes still running"
        time.sleep(0.05)


def test_process_executor_keeps_task_order_and_raises_the_task_error():
    with ProcessExecutor(2) as ex:
        assert ex.map(abs, [-5, 4, -3, 2, -1]) == [5, 4, 3, 2, 1]
        assert ex.map(abs, []) == []
        with pytest.raises(ValueError, match="math domain error"):
            ex.map(math.sqrt, [4.0, -1.0, 9.0])
        assert ex.map(abs, [-7]) == [7]                     # the pool survives a task's own error
        assert ex.submitted == 9


def _args(executor="auto", ray_address=None):
    return argparse.Namespace(executor=executor, ray_address=ray_address, gpu_actors=0, cpu_actors=0)


@pytest.fixture
def no_spawn(monkeypatch):
    """ProcessExecutors that start no process (what is checked here is the choice, not the workers)."""
    monkeypatch.setattr(ProcessExecutor, "_ensure", lambda self, n: None)


def test_auto_picks_processes_for_several_drives_on_several_cores(monkeypatch, no_spawn):
    monkeypatch.delenv(executors.WORKERS_ENV, raising=False)
    monkeypatch.setattr(executors, "usable_cores", lambda: 4)
    assert isinstance(executor_from_args(_args(), tasks=1), LocalExecutor)        # one drive: nothing to split
    ex = executor_from_args(_args(), tasks=8, backend="reference")
    assert ex.kind == "process" and ex.workers == 4 and ex.backend == "reference"
    assert executor_from_args(_args(), tasks=3).workers == 3                    # no more workers than drives
    assert isinstance(executor_from_args(_args("local"), tasks=8), LocalExecutor)
    assert executor_from_args(_args("process"), tasks=1).kind == "process"       # asked for: given
    monkeypatch.setattr(executors, "usable_cores", lambda: 1)
    assert isinstance(executor_from_args(_args(), tasks=8), LocalExecutor)        # one core
    with pytest.raises(ValueError, match="--ray-address needs --executor ray"):
        executor_from_args(_args("process", ray_address="auto"), tasks=8)


def test_workers_env_caps_the_workers(monkeypatch, no_spawn):
    monkeypatch.setattr(executors, "usable_cores", lambda: 16)
    monkeypatch.setenv(executors.WORKERS_ENV, "3")
    assert executors.default_workers() == 3 and executor_from_args(_args(), tasks=32).workers == 3
    monkeypatch.setenv(executors.WORKERS_ENV, "1")
    assert isinstance(executor_from_args(_args(), tasks=32), LocalExecutor)
    for bad in ("0", "two"):
        monkeypatch.setenv(executors.WORKERS_ENV, bad)
        with pytest.raises(ValueError, match=executors.WORKERS_ENV):
            executors.default_workers()


def test_reproduce_defaults_to_auto_and_takes_process():
    from place3d_app.commands import reproduce

    p = argparse.ArgumentParser()
    reproduce.add_arguments(p)
    assert p.parse_args([]).executor == "auto"
    assert p.parse_args(["--executor", "process"]).executor == "process"


def test_commands_start_workers_from_a_forkserver_unless_told(monkeypatch, no_spawn):
    monkeypatch.setattr(executors, "usable_cores", lambda: 4)
    monkeypatch.delenv(executors.START_METHOD_ENV, raising=False)
    monkeypatch.setattr(executors.sys, "platform", "linux")
    assert executors.command_start_method() == "forkserver"
    monkeypatch.setattr(executors.sys, "platform", "darwin")          # spawned where forks of frameworks crash
    assert executors.command_start_method() == "spawn"
    monkeypatch.setattr(executors.sys, "platform", "linux")
    assert executor_from_args(_args(), tasks=8, backend="warp:cpu").start_method == "forkserver"
    monkeypatch.setenv(executors.START_METHOD_ENV, "spawn")
    assert executor_from_args(_args(), tasks=8).start_method == "spawn"
    for bad in ("fork", "threads"):                 # a plain fork copies a started CUDA or OpenCL: refused
        monkeypatch.setenv(executors.START_METHOD_ENV, bad)
        with pytest.raises(ValueError, match=executors.START_METHOD_ENV):
            executor_from_args(_args(), tasks=8)


def test_the_forkserver_preloads_warp_only_for_warp_backends_and_opencl_for_opencl_ones():
    import importlib.util

    assert "place3d_kernels.backends.warp" in forkserver.preload_for("warp:cuda:0")
    assert "place3d_kernels.backends.warp" in forkserver.preload_for("auto")
    for name in ("opencl:pocl", "reference", None):
        mods = forkserver.preload_for(name)
        assert "place3d_kernels.backends.warp" not in mods and "place3d_kernels.pooled" in mods
    for name in ("warp:cuda:0", "auto", "reference", None):
        assert "place3d_kernels.backends.opencl" not in forkserver.preload_for(name)
    has_cl = importlib.util.find_spec("pyopencl") is not None
    for name in ("opencl:pocl", "opencl:nvidia", "opencl"):
        assert ("place3d_kernels.backends.opencl" in forkserver.preload_for(name)) is has_cl


def test_the_forkserver_preloads_scipy_only_for_workers_that_may_build_opendrive_scenes(tmp_path):
    """A server whose workers build only drives of the embedded town leaves SciPy's parts out of its imports;
    by default (any scene) they are in. Such a drive, built in a fresh interpreter that imported only the light
    preload, imports no SciPy module: what the light server leaves out, no town drive needs."""
    import subprocess
    import sys
    import textwrap

    for name in ("warp:cuda:0", "opencl:pocl", None):
        assert set(forkserver.OPENDRIVE_PRELOAD) <= set(forkserver.preload_for(name))
        light = forkserver.preload_for(name, opendrive=False)
        assert not set(forkserver.OPENDRIVE_PRELOAD) & set(light) and set(forkserver.FORKSERVER_PRELOAD) <= set(light)
    code = textwrap.dedent(f"""
        import dataclasses, importlib, sys
        from place3d_app import forkserver
        for m in forkserver.preload_for("warp:cpu", opendrive=False):
            importlib.import_module(m)
        from place3d_app.cli import build_parser
        from place3d_app.commands.routes import _build_spec_then, drive_specs
        from place3d_kernels.spec import specs_from_args
        args = build_parser().parse_args(["optimize", "--frames", "8", "--voxel-size", "0.8", "--backend", "warp:cpu"])
        d = drive_specs(args, specs_from_args(args))[0]
        record = _build_spec_then((dataclasses.replace(d, cache={str(tmp_path)!r}), None))
        print(d.scene.kind, record.n_subsets, sorted(m for m in sys.modules if m == "scipy" or m.startswith("scipy.")))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[-2] == "town 2 []"


@pytest.mark.parametrize("argv, preload", [
    (["reproduce"], "auto"),
    (["--profile", "reproduce", "--routes", "8", "--backend", "opencl:pocl"], "opencl:pocl"),
    (["reproduce", "--executor=process", "--backend=warp:cuda:0"], "warp:cuda:0"),
    (["reproduce", "--executor", "local"], None),
    (["reproduce", "--executor", "ray"], None),
    (["reproduce", "--ray-address", "ray://head:10001"], None),
    (["reproduce", "--help"], None),
    (["study"], None),
])
def test_the_launcher_starts_reproduces_server_early_only_where_it_will_fork_from_it(monkeypatch, argv, preload):
    started = []
    monkeypatch.setattr(forkserver, "start", lambda b, opendrive=True: started.append(b))   # the decision alone
    monkeypatch.delenv(forkserver.START_METHOD_ENV, raising=False)
    monkeypatch.delenv(forkserver.WORKERS_ENV, raising=False)
    monkeypatch.setattr(forkserver, "_usable_cores", lambda: 4)
    monkeypatch.setattr(forkserver.sys, "platform", "linux")
    assert forkserver.start_early(argv) is (preload is not None)
    assert started == ([] if preload is None else [preload])
    if preload is not None:
        for env, value in ((forkserver.WORKERS_ENV, "1"), (forkserver.START_METHOD_ENV, "spawn")):
            monkeypatch.setenv(env, value)
            assert not forkserver.start_early(argv)
            monkeypatch.delenv(env)
        monkeypatch.setattr(forkserver, "_usable_cores", lambda: 1)
        assert not forkserver.start_early(argv) and len(started) == 1


@pytest.mark.parametrize("argv, preload", [
    (["evaluate"], ("auto", False)),
    (["--profile", "optimize", "--max-evals", "20", "--backend=warp:cuda:0"], ("warp:cuda:0", False)),
    (["optimize", "--scene", "town", "--scene", "opendrive:Town01"], ("auto", True)),
    (["evaluate", "--routes", "1"], None),
    (["evaluate", "--scene", "mesh:city.obj"], None),
    (["optimize", "--scene=semantickitti:seq00"], None),
    (["optimize", "--no-cache"], None),
    (["optimize", "--executor", "ray"], None),
    (["evaluate", "--ray-address", "ray://head:10001"], None),
])
def test_the_launcher_starts_the_server_early_for_evaluate_and_optimize_only_on_an_empty_cache(
        monkeypatch, tmp_path, argv, preload):
    # evaluate and optimize fork workers only for the drives the cache lacks: the server is started ahead while
    # the cache holds no P-SOG file (the first run on a machine), without SciPy's parts for town drives
    started = []
    monkeypatch.setattr(forkserver, "start", lambda b, opendrive=True: started.append((b, opendrive)))
    monkeypatch.delenv(forkserver.START_METHOD_ENV, raising=False)
    monkeypatch.delenv(forkserver.WORKERS_ENV, raising=False)
    monkeypatch.setattr(forkserver, "_usable_cores", lambda: 4)
    monkeypatch.setattr(forkserver.sys, "platform", "linux")
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))      # not made yet: empty
    assert forkserver.start_early(argv) is (preload is not None) and started == ([] if preload is None else [preload])
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "keymemo.json").write_text("{}")             # other files: still no drive
    assert forkserver.start_early(argv) is (preload is not None)
    (tmp_path / "cache" / "psog-town-0123.npz").write_bytes(b"")       # a drive cached: none started
    started.clear()
    assert not forkserver.start_early(argv) and started == []


def test_the_launchers_cache_guess_reads_the_folder_and_files_the_package_writes(monkeypatch, tmp_path):
    # the launcher cannot import the package: its cache folder and file pattern are written again in
    # forkserver, held here to backends.base.cache_dir and to a drive's cache file as the workers write it
    import dataclasses

    from place3d_app.cli import build_parser
    from place3d_app.commands.routes import _build_spec_then, drive_specs
    from place3d_kernels.backends.base import cache_dir
    from place3d_kernels.spec import specs_from_args

    monkeypatch.delenv("PLACE3D_CACHE", raising=False)
    assert Path(forkserver._cache_folder()) == cache_dir()
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "c"))
    assert Path(forkserver._cache_folder()) == cache_dir() == tmp_path / "c"
    assert forkserver._no_drive_cached()                                   # no folder yet
    args = build_parser().parse_args(["optimize", "--frames", "8", "--voxel-size", "0.8", "--backend", "warp:cpu"])
    d = drive_specs(args, specs_from_args(args))[0]
    _build_spec_then((dataclasses.replace(d, cache=str(cache_dir())), None))
    assert d.cache_file() is not None and d.cache_file().exists()
    assert not forkserver._no_drive_cached()


def test_reproduces_workers_are_forked_from_the_server_the_launcher_started(tmp_path):
    # in a process of its own, as the console script: the server started before the command's executor is made
    # is the one its workers come from (their parent), with the workers' environment
    code = (
        "import multiprocessing.forkserver as fs, operator, os\n"
        "from place3d_app import forkserver\n"
        "assert forkserver.start_early(['reproduce', '--backend', 'warp:cpu'])\n"
        "server = fs._forkserver._forkserver_pid\n"
        "from place3d_app.executors import ProcessExecutor, command_start_method\n"
        "ex = ProcessExecutor(2, backend='warp:cpu', start_method=command_start_method())\n"
        "assert set(ex.map(operator.call, [os.getppid] * 4)) == {server}, server\n"
        "assert ex.map(os.getenv, ['OPENBLAS_NUM_THREADS']) == ['1']\n"
        "ex.shutdown()\n"
        "print('ok')\n")
    if executors.usable_cores() < 2:
        pytest.skip("one usable core: reproduce builds its drives in this process")
    _run_as_console_script(code, tmp_path)


def _run_as_console_script(code: str, tmp_path) -> None:
    """Run ``code`` in a process of its own, as the console script would (none of this test run's start method,
    worker cap or BLAS threads in its environment; modules in ``tmp_path`` importable), and expect it to print ok."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items()
           if k not in (forkserver.START_METHOD_ENV, forkserver.WORKERS_ENV, "OPENBLAS_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(tmp_path), env.get("PYTHONPATH", "")) if p)
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]


def test_workers_forked_from_a_server_that_imported_pyopencl_use_opencl(tmp_path):
    # an OpenCL command's server imports PyOpenCL and the backend's modules (no platform asked for): its
    # workers find them imported and make the backend and run its kernels, as this process does
    pytest.importorskip("pyopencl")
    import place3d_kernels as p3k

    if "opencl:pocl" not in p3k.available_backends():
        pytest.skip("needs PoCL")
    if executors.usable_cores() < 2:
        pytest.skip("one usable core: reproduce builds its drives in this process")
    (tmp_path / "cltask.py").write_text(
        "import sys\n"
        "def fields(_):\n"
        "    pre = 'pyopencl' in sys.modules and 'place3d_kernels.backends.opencl.host' in sys.modules\n"
        "    import numpy as np\n"
        "    from place3d_kernels.backends.registry import get_backend\n"
        "    from place3d_kernels.classes import N_CLASSES, VEHICLE\n"
        "    from place3d_kernels.left_out import FieldTables\n"
        "    tb = FieldTables(3, 'seg')\n"
        "    c = np.zeros((4, N_CLASSES), np.int32)\n"
        "    c[:, 1] = np.arange(4)\n"
        "    w, _ = get_backend('opencl:pocl').left_out_fields(c, np.arange(4), np.zeros(5, np.int32),\n"
        "        np.zeros(1, np.int32), np.zeros(1, np.int32), np.zeros(4, np.int32), np.array([3]), tb.term[None],\n"
        "        tb.stop[None].astype(np.uint8), np.zeros((1, 1, 1)), False, VEHICLE, 1e6)\n"
        "    return pre, w.numpy().tolist()\n")
    code = (
        "from place3d_app import forkserver\n"
        "assert forkserver.start_early(['reproduce', '--backend', 'opencl:pocl'])\n"
        "from place3d_app.executors import ProcessExecutor, command_start_method\n"
        "import cltask\n"
        "ex = ProcessExecutor(2, backend='opencl:pocl', start_method=command_start_method())\n"
        "got = ex.map(cltask.fields, [0, 1])\n"
        "ex.shutdown()\n"
        "here = cltask.fields(0)[1]\n"
        "assert all(pre for pre, _ in got) and all(w == here for _, w in got), (got, here)\n"
        "print('ok')\n")
    _run_as_console_script(code, tmp_path)


def test_forkserver_workers_have_the_worker_environment_and_this_process_keeps_its_own(monkeypatch):
    # the workers are started on a thread (prestart): the server, started before, holds their environment
    for k in executors.WORKER_ENV:
        monkeypatch.delenv(k, raising=False)
    with ProcessExecutor(2, start_method="forkserver", prestart=True) as ex:
        assert all(os.environ.get(k) is None for k in executors.WORKER_ENV)
        assert ex.map(os.getenv, list(executors.WORKER_ENV)) == list(executors.WORKER_ENV.values())
        assert all(os.environ.get(k) is None for k in executors.WORKER_ENV)


@pytest.mark.parametrize("method", ["forkserver", "spawn"])
def test_an_idle_pool_is_ended_at_once_and_a_busy_one_finishes(method):
    ex = ProcessExecutor(2, start_method=method)
    assert ex.map(abs, [-1, -2]) == [1, 2]
    procs = list(ex._pool._processes.values())
    signalled = []
    for p in procs:                                     # a signal to an idle worker could leave another waiting
        for name in ("terminate", "kill"):              # forever for the task queue's lock (shutdown's docstring)
            setattr(p, name, lambda name=name, pid=p.pid: signalled.append((name, pid)))
    ex.shutdown(wait=False)                             # returns at once; the workers read their exit sentinels
    _wait_until_gone(procs)                             # (polled: a join here races the pool's own for the status)
    assert signalled == []
    f = ex.submit(time.sleep, 0.5)                      # a later submit starts new workers
    ex.shutdown(wait=False)                             # a task still runs: it is let finish
    assert f.result(timeout=30) is None


DRIVE_TASK = """
import dataclasses, json, sys
from place3d_app import executors
from place3d_app.cli import build_parser
from place3d_app.commands import routes
from place3d_app.commands.routes import drive_specs
from place3d_kernels.spec import specs_from_args

args = build_parser().parse_args(["optimize", "--frames", "8", "--voxel-size", "0.8", "--backend", "warp:cpu"])
d = dataclasses.replace(drive_specs(args, specs_from_args(args))[0], backend="warp:cpu", cache=sys.argv[1])
record = getattr(routes, sys.argv[2])((d, None))
print(json.dumps({"started": sorted(executors._backends_started), "entries": len(record.voxels)}))
"""


@pytest.mark.parametrize("task", ["_build_spec_then", "_build_part"])
def test_a_drive_task_starts_its_backend_ahead(tmp_path, task):
    # a drive's task (whole or a part) starts its worker's backend on a thread as it starts, beside the scene
    # (optimize's held-out drives are parts too, queued behind the searched ones). A fresh process each: the set
    # is per process
    import json
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    program = DRIVE_TASK if task != "_build_part" else DRIVE_TASK.replace(
        "getattr(routes, sys.argv[2])((d, None))", "routes._build_part((d, range(0, 1)))")
    p = subprocess.run([sys.executable, "-c", program, str(tmp_path), task], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))},
                       timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["entries"] > 0                          # the drive was built
    assert got["started"] == ["warp:cpu"]
