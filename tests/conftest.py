"""Shared fixtures: every kernel test runs once per available backend (ids like [warp:cpu])."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

import place3d_kernels as p3k

ALL_BACKENDS = p3k.available_backends()
#: backends under test against the reference (PLACE3D_TEST_BACKENDS narrows the set, comma-separated)
_only = os.environ.get("PLACE3D_TEST_BACKENDS")
DEVICE_BACKENDS = [b for b in ALL_BACKENDS if b != "reference" and (not _only or b in _only.split(","))]


def pytest_generate_tests(metafunc):
    if "backend" in metafunc.fixturenames:
        names = ["reference"] + DEVICE_BACKENDS
        metafunc.parametrize("backend", names, ids=names)
    if "device_backend" in metafunc.fixturenames:
        if DEVICE_BACKENDS:
            metafunc.parametrize("device_backend", DEVICE_BACKENDS, ids=DEVICE_BACKENDS)
        else:
            metafunc.parametrize("device_backend", [pytest.param(None, marks=pytest.mark.skip(
                reason="no device backend (warp/opencl) available here"))])


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path, monkeypatch):
    """P-SOG caches go to a per-test folder, never the user's."""
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))


_session = None


def pytest_sessionfinish(session, exitstatus):
    global _session
    _session = session


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """End the test process as the console script ends a command (``place3d_app.leave``): non-daemon threads
    joined and ``atexit`` handlers run, then ``os._exit`` with pytest's exit status, without the interpreter's
    last teardown (module namespaces, the loaded C libraries' destructors). A CI run (2026-11-30 22:41 UTC, main
    at d8a1cf3) passed every test and then died in that teardown: SIGSEGV on a thread other than the main one,
    executing heap memory (the kernel's log), as when a native thread outlives the library state it uses. A test
    process holds many such threads to its end (seen in a full run: Ray's gRPC threads after ``ray.shutdown``,
    Dr.Jit's pool, PoCL's and the BLAS's workers), none of them ours to stop. ``PLACE3D_FAST_EXIT=0`` keeps the
    full teardown. Only where pytest is the program (``pytest``, ``python -m pytest``), not inside another one
    that called ``pytest.main``."""
    prog = os.path.normpath(sys.argv[0] if sys.argv else "")
    is_program = os.path.basename(prog).startswith(("pytest", "py.test")) or prog.endswith(
        os.path.join("pytest", "__main__.py"))
    if _session is not None and is_program:
        from place3d_app import leave

        leave(int(_session.exitstatus))
