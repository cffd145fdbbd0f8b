"""Shared fixtures: every kernel test runs once per available backend (ids like [warp:cpu])."""

from __future__ import annotations

import os

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
