"""A scene built in a forked process (``scene_prefetch``) is the scene built here, bit for bit, and its
P-SOG is the same; a failed or unwanted child leaves the in-process build as before.

``scene_prefetch`` forks only in a process with one thread, and a test process has others once earlier
tests ran (backend pools, servers), so each check that forks runs in a fresh interpreter of its own
(``_isolated``): the ``_check_*`` functions below, whose failures fail the test."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from place3d_app import prefetch as scene_prefetch
from place3d_kernels.grid import Grid
from place3d_kernels.pipeline import scene_psog
from place3d_kernels.scene.keymemo import identity, remember
from place3d_kernels.spec import PSOGSpec, SceneSpec

GRID = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), 0.4)

needs_fork = pytest.mark.skipif(not sys.platform.startswith("linux") or len(os.sched_getaffinity(0)) < 2,
                                reason="forked scene builds need Linux and 2+ cores")


def _isolated(check: str, *args) -> None:
    """Run ``_check_<check>(*args)`` of this module in a fresh interpreter (one thread); fail on its error."""
    here = Path(__file__).resolve().parent
    code = (f"import sys; sys.path[:0] = [{str(here.parent)!r}, {str(here)!r}]; import test_scene_prefetch as t; "
            f"assert t.scene_prefetch.enabled(), 'forking is off in a fresh interpreter'; t._check_{check}(*sys.argv[1:])")
    env = {k: v for k, v in os.environ.items() if k != scene_prefetch.ENV}
    # the project first, then what the environment had (a host whose Warp lives on PYTHONPATH keeps it, so
    # "auto" there is the backend it would be in the test process, not the slow reference)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(here.parent), os.environ.get("PYTHONPATH")]))
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=env,
                         timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]


def _same_mesh(a, b) -> None:
    for name in ("vertices", "faces", "labels", "valid_faces", "shift", "normals"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


def _same_value(a, b) -> None:
    """Equal nested dicts / lists / arrays / numbers, arrays and floats bit for bit."""
    assert type(a) is type(b), (type(a), type(b))
    if isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            _same_value(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _same_value(x, y)
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    elif isinstance(a, (float, np.floating)):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    else:
        assert a == b


def _same_scene(a, b) -> None:
    assert a.key == b.key and a.name == b.name and a.seed == b.seed
    _same_value(a.meta, b.meta)
    _same_mesh(a.static, b.static)
    assert a.ego_poses.tobytes() == b.ego_poses.tobytes()
    assert len(a.actors) == len(b.actors)
    for x, y in zip(a.actors, b.actors):
        assert x.kind == y.kind and x.poses.tobytes() == y.poses.tobytes()
        _same_mesh(x.mesh, y.mesh)


def _check_forked_scene_and_actor_meshes_equal_the_local_build():
    spec = SceneSpec("town", 3, 12)
    from place3d_kernels import scene as scenes

    assert scene_prefetch.start(("t1", spec), lambda: scenes.town(seed=3, n_frames=12))
    got = scene_prefetch.take(("t1", spec))
    want = scenes.town(seed=3, n_frames=12)
    assert got is not None
    _same_scene(got, want)
    dyn = got.take_prebuilt()
    assert sorted(dyn) == list(range(want.n_frames))
    for f, mesh in dyn.items():
        _same_mesh(mesh, want.dynamic(f))
    assert got.take_prebuilt() == {}          # handed out once
    assert scene_prefetch.take(("t1", spec)) is None        # taken once


def _check_psog_of_a_forked_scene_equals_the_local_one():
    from place3d_kernels import scene as scenes

    assert scene_prefetch.start("t2", lambda: scenes.town(seed=1, n_frames=8))
    forked = scene_prefetch.take("t2")
    local = scenes.town(seed=1, n_frames=8)
    a = scene_psog(forked, grid=GRID, backend=None, cache=False)
    b = scene_psog(local, grid=GRID, backend=None, cache=False)
    assert a.voxels.tobytes() == b.voxels.tobytes() and a.counts.tobytes() == b.counts.tobytes()
    assert a.probs.tobytes() == b.probs.tobytes() and a.n_subsets == b.n_subsets


def _check_payload_through_the_pipe_without_a_memory_file():
    # no /dev/shm file to be had: the payload goes through the pipe itself, the same scene
    from place3d_kernels import scene as scenes

    def no_file(*a, **k):
        raise OSError("no memory file here")

    scene_prefetch.tempfile.TemporaryFile = no_file
    assert scene_prefetch.start("t6", lambda: scenes.town(seed=2, n_frames=4))
    assert scene_prefetch._pending["t6"][3] is None
    _same_scene(scene_prefetch.take("t6"), scenes.town(seed=2, n_frames=4))


def _check_failed_child_gives_none_and_is_reaped():
    def broken():
        raise RuntimeError("no scene")

    assert scene_prefetch.start("t3", broken)
    pid = scene_prefetch._pending["t3"][0]
    assert scene_prefetch.take("t3") is None
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)


def _check_untaken_child_is_stopped_at_exit():
    import time

    assert scene_prefetch.start("t4", lambda: time.sleep(60))
    pid = scene_prefetch._pending["t4"][0]
    scene_prefetch._discard()
    assert "t4" not in scene_prefetch._pending
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)


def test_off_with_other_threads_or_the_variable(monkeypatch):
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert not scene_prefetch.enabled()
        assert not scene_prefetch.start("t5", lambda: None)
    finally:
        stop.set()
        t.join()
    monkeypatch.setenv(scene_prefetch.ENV, "0")
    assert not scene_prefetch.enabled()
    assert scene_prefetch.take("t5") is None


def _check_prefetch_only_when_the_build_needs_the_scene(tmp):
    spec = PSOGSpec(SceneSpec("town", 5, 8))
    folder = Path(tmp) / "c"
    ident = identity(spec.scene.to_dict(), spec.scene.kind, spec.scene.path)
    remember(folder, ident, "town", "some-key")
    assert not scene_prefetch.start_for_spec(spec, cache=str(folder))         # key remembered: a cached P-SOG needs no scene
    assert not scene_prefetch.start_for_spec(PSOGSpec(SceneSpec("semantickitti:/nowhere")), cache=False)
    assert not scene_prefetch.start_for_spec(spec, cache=False, drives=4)     # several drives: workers build them
    assert scene_prefetch.start_for_spec(spec, cache=False)                    # --no-cache always builds the scene
    try:
        got = spec.scene.build()                               # spec._build_scene takes the forked scene
        assert scene_prefetch.take(spec.scene) is None
        from place3d_kernels import scene as scenes

        _same_scene(got, scenes.town(seed=5, n_frames=8))
        assert len(got.take_prebuilt()) == 8
    finally:
        scene_prefetch._discard()


@needs_fork
def test_forked_scene_and_actor_meshes_equal_the_local_build():
    _isolated('forked_scene_and_actor_meshes_equal_the_local_build')


@needs_fork
def test_psog_of_a_forked_scene_equals_the_local_one():
    _isolated('psog_of_a_forked_scene_equals_the_local_one')


@needs_fork
def test_payload_through_the_pipe_without_a_memory_file():
    _isolated('payload_through_the_pipe_without_a_memory_file')


@needs_fork
def test_failed_child_gives_none_and_is_reaped():
    _isolated('failed_child_gives_none_and_is_reaped')


@needs_fork
def test_untaken_child_is_stopped_at_exit():
    _isolated('untaken_child_is_stopped_at_exit')


@needs_fork
def test_prefetch_only_when_the_build_needs_the_scene(tmp_path):
    _isolated("prefetch_only_when_the_build_needs_the_scene", tmp_path)
