"""``backends.cuda_early``: which names start the CUDA driver early, and that starting it never changes
what ``get_backend`` gives (on a machine without the driver the thread finds no ``libcuda`` and ends)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import types
from pathlib import Path

import pytest

from place3d_kernels.backends import cuda_early

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name,ordinal", [("auto", 0), ("warp", 0), ("warp:cuda", 0), ("warp:cuda:0", 0),
                                          ("WARP:CUDA:3", 3), (" warp:cuda:1 ", 1), ("warp:cpu", None),
                                          ("opencl:nvidia", None), ("reference", None), ("opencl", None),
                                          ("warp:cuda:x", None)])
def test_which_names_take_a_cuda_device(name, ordinal):
    assert cuda_early.ordinal_of(name) == ordinal


def test_nothing_starts_once_warp_is_initialised_or_when_turned_off(monkeypatch):
    monkeypatch.setattr(cuda_early, "_started", set())
    monkeypatch.setitem(sys.modules, "warp", sys.modules.get("warp", object()))
    monkeypatch.setattr(cuda_early, "_warp_initialised", lambda: True)
    monkeypatch.setattr(cuda_early, "_retain", lambda ordinal: pytest.fail("retained after Warp's init"))
    assert cuda_early.start("warp:cuda:0") is None
    monkeypatch.delitem(sys.modules, "warp")
    monkeypatch.setenv(cuda_early.ENV, "0")
    assert cuda_early.start("warp:cuda:0") is None
    assert cuda_early.start("opencl:pocl") is None


def test_an_imported_warp_not_yet_initialised_gets_the_context_started(monkeypatch):
    # a worker forked from a server that imported Warp: the driver starts on a thread, as before an import
    monkeypatch.setattr(cuda_early, "_started", set())
    monkeypatch.setattr(cuda_early, "_threads", [])
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setitem(sys.modules, "warp", sys.modules.get("warp", object()))
    monkeypatch.setattr(cuda_early, "_warp_initialised", lambda: False)
    monkeypatch.setattr(cuda_early.importlib.util, "find_spec", lambda n: object())
    gate, retained = threading.Event(), []
    monkeypatch.setattr(cuda_early, "_retain", lambda ordinal: (retained.append(ordinal), gate.wait(30)))
    t = cuda_early.start("warp:cuda:2")
    assert t is not None and cuda_early.pending() == [t]
    assert cuda_early.start("warp:cuda:2") is None                 # once per device and process
    gate.set()
    t.join(30)
    assert retained == [2] and cuda_early.pending() == []


def test_warp_starts_after_the_context_with_its_kernels_imported(monkeypatch):
    # host._init: with a context being made on cuda_early's thread, the kernels' modules are imported and the
    # thread joined before Warp's init runs
    import importlib

    host = pytest.importorskip("place3d_kernels.backends.warp.host")
    calls, real_import = [], importlib.import_module

    class Making:
        def join(self):
            calls.append("join")

    def importing(name, *a):
        calls.append(name.rsplit(".", 1)[-1])
        return real_import(name, *a)

    monkeypatch.setattr(host, "_initialised", False)
    monkeypatch.setattr(cuda_early, "pending", lambda: [Making()])
    monkeypatch.setattr(importlib, "import_module", importing)
    monkeypatch.setattr(host.wp, "init", lambda: calls.append("init"))
    host._init()
    assert calls == ["kernels", "score_gpu", "left_out_kernels", "join", "init"]
    calls.clear()
    monkeypatch.setattr(host, "_initialised", False)
    monkeypatch.setattr(cuda_early, "pending", lambda: [])
    host._init()
    assert calls == ["init"]                    # nothing in flight: Warp's init as before


def test_whether_warp_is_initialised_is_read_from_its_runtime(monkeypatch):
    ctx = types.SimpleNamespace(runtime=None)
    monkeypatch.setitem(sys.modules, "warp._src.context", ctx)
    assert not cuda_early._warp_initialised()
    ctx.runtime = object()
    assert cuda_early._warp_initialised()
    monkeypatch.delitem(sys.modules, "warp._src.context")
    monkeypatch.delitem(sys.modules, "warp.context", raising=False)
    assert cuda_early._warp_initialised()          # a layout it cannot read: nothing is started


PROGRAM = """
import json, sys, threading
from place3d_kernels.backends import cuda_early
from place3d_kernels.backends.registry import available_backends, get_backend
t = cuda_early.start("auto")
started = t is not None
if t is not None:
    t.join(60)
again = cuda_early.start("auto")                      # once per device and process
b = get_backend("auto")
print(json.dumps({"started": started, "again": again is None, "name": b.name, "available": available_backends()}))
"""


PROGRAM_IMPORTED = """
import json, sys
import warp
from place3d_kernels.backends import cuda_early
from place3d_kernels.backends.registry import available_backends, get_backend
before = cuda_early._warp_initialised()
b = get_backend("auto")
print(json.dumps({"started": 0 in cuda_early._started, "before": before, "name": b.name,
                  "available": available_backends()}))
"""


@pytest.mark.parametrize("early", ["1", "0"])
def test_a_process_that_imported_warp_gets_the_same_backend_either_way(early):
    pytest.importorskip("warp")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           cuda_early.ENV: early}
    runs = {}
    for setting in (early, "0"):
        p = subprocess.run([sys.executable, "-c", PROGRAM_IMPORTED], capture_output=True, text=True, timeout=300,
                           env={**env, cuda_early.ENV: setting})
        assert p.returncode == 0, p.stderr
        runs[setting] = json.loads(p.stdout.strip().splitlines()[-1])
    got = runs[early]
    assert got["before"] is False                    # imported, not initialised: what a forked worker has
    assert got["started"] == (early == "1" and sys.platform.startswith("linux"))
    assert got["name"] in got["available"] and got["name"] == runs["0"]["name"]


@pytest.mark.parametrize("early", ["1", "0"])
def test_a_fresh_process_gets_the_same_backend_either_way(early):
    pytest.importorskip("warp")
    # the project first, then what the environment had (a host whose Warp lives on PYTHONPATH keeps it)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           cuda_early.ENV: early}
    p = subprocess.run([sys.executable, "-c", PROGRAM], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["started"] == (early == "1" and sys.platform.startswith("linux"))
    assert got["again"]
    assert got["name"] in got["available"]
    if early == "1":
        plain = subprocess.run([sys.executable, "-c", PROGRAM], capture_output=True, text=True, timeout=300,
                               env={**env, cuda_early.ENV: "0"})
        assert json.loads(plain.stdout.strip().splitlines()[-1])["name"] == got["name"]


def test_a_name_is_tried_once_per_process(monkeypatch):
    # get_backend("auto") calls start on every call while Warp is not imported (a machine without CUDA):
    # after the first try, start returns before looking for Warp
    monkeypatch.delitem(sys.modules, "warp", raising=False)
    monkeypatch.setattr(cuda_early, "_started", {0})
    looked = []
    monkeypatch.setattr(cuda_early.importlib.util, "find_spec", lambda n: looked.append(n))
    assert cuda_early.start("auto") is None and looked == []
