"""The backend registry: families are data, so a new backend is one FAMILIES entry and one folder."""

from __future__ import annotations

import sys
import types

import pytest

from place3d_kernels.backends import registry
from place3d_kernels.backends.reference import ReferenceBackend


class _FakeBackend(ReferenceBackend):
    def __init__(self, device: str):
        self.name = f"fake:{device}"


@pytest.fixture
def fake_family(monkeypatch):
    """A family 'fake' with devices 'a' and 'b' (one unusable 'c'), served by a module made on the fly."""
    mod = types.ModuleType("fake_backend_pkg")
    mod.FakeBackend = _FakeBackend
    mod.fake_devices = lambda: ["a", "b"]
    mod.fake_unusable = lambda: [("c", "driver too old; upgrade it")]
    monkeypatch.setitem(sys.modules, "fake_backend_pkg", mod)
    fams = dict(registry.FAMILIES)
    fams["fake"] = registry.Family("fake_backend_pkg", "FakeBackend", devices="fake_devices",
                                   unusable="fake_unusable", install="pip install fake")
    monkeypatch.setattr(registry, "FAMILIES", fams)
    registry.forget()
    yield
    registry.forget()


def test_a_new_family_is_one_entry(fake_family):
    assert {"fake:a", "fake:b"} <= set(registry.available_backends())
    assert ("fake", False, "platform c: driver too old; upgrade it") in registry.backend_report()
    b = registry.get_backend("fake")          # the family's default device: its first
    assert isinstance(b, _FakeBackend) and b.name == "fake:a"
    assert registry.get_backend("fake:b").name == "fake:b"
    assert registry.get_backend("fake:a") is b   # cached per name


def test_a_family_whose_runtime_is_missing_is_reported_with_its_install_command(monkeypatch):
    fams = dict(registry.FAMILIES)
    fams["ghost"] = registry.Family("no_such_module_for_place3d", "Ghost", devices="ghost_devices",
                                    install="pip install ghost")
    monkeypatch.setattr(registry, "FAMILIES", fams)
    registry.forget()
    try:
        rows = [r for r in registry.backend_report() if r[0] == "ghost"]
        assert len(rows) == 1 and rows[0][1] is False and "pip install ghost" in rows[0][2]
        with pytest.raises(ValueError, match=r"'ghost:x'.*pip install ghost"):
            registry.get_backend("ghost:x")
    finally:
        registry.forget()


def test_a_family_whose_runtime_fails_to_import_is_unavailable_not_fatal(monkeypatch, tmp_path):
    # what `pip uninstall pyopencl` can leave: a folder that imports as an empty namespace package, so the
    # backend's own import fails with an AttributeError (cl.mem_flags) instead of an ImportError
    (tmp_path / "broken_runtime_for_place3d.py").write_text("import sys\nsys.modules[__name__].mem_flags\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    fams = {"broken": registry.Family("broken_runtime_for_place3d", "Broken", devices="broken_devices",
                                      install="pip install broken"), "reference": registry.FAMILIES["reference"]}
    monkeypatch.setattr(registry, "FAMILIES", fams)
    registry.forget()
    try:
        rows = [r for r in registry.backend_report() if r[0] == "broken"]
        assert len(rows) == 1 and rows[0][1] is False
        assert "AttributeError" in rows[0][2] and "pip install broken" in rows[0][2]
        assert "reference" in registry.available_backends()
    finally:
        registry.forget()


def test_a_second_pocl_platform_is_a_cpu_not_a_gpu():
    # PyPI's PoCL beside Debian's is named opencl:pocl2; "auto" once took it for an OpenCL GPU and chose it
    from place3d_kernels.backends.registry import _cpu_name

    assert _cpu_name("opencl:pocl") and _cpu_name("opencl:pocl2") and _cpu_name("warp:cpu")
    assert not _cpu_name("opencl:nvidia") and not _cpu_name("warp:cuda:0") and not _cpu_name("opencl:poclx")


def test_a_second_pocl_install_is_left_out_for_the_newest():
    from place3d_kernels.backends.opencl._runtime import _pocl_version

    class P:
        def __init__(self, version):
            self.version = version

    assert _pocl_version(P("OpenCL 3.0 PoCL 3.1+debian  Linux")) > _pocl_version(P("OpenCL 3.0 PoCL 3.0-rc2  Linux"))
    assert _pocl_version(P("OpenCL 3.0 PoCL 5.0 Linux")) > _pocl_version(P("OpenCL 3.0 PoCL 3.1+debian"))
    assert _pocl_version(P("OpenCL 1.2 something else")) == (0, 0)


def test_threads_asking_at_once_share_the_one_backend_being_made(fake_family, monkeypatch):
    # a worker process makes its backend on a thread while its first task runs (place3d_app.executors): a task
    # asking meanwhile must wait for that backend, not make a second one (a second CUDA context and module load)
    import threading
    import time

    made = []

    def slow(self, device):
        made.append(device)
        time.sleep(0.2)                       # long enough for every thread below to ask while it is made
        self.name = f"fake:{device}"

    monkeypatch.setattr(_FakeBackend, "__init__", slow)
    got = []
    threads = [threading.Thread(target=lambda: got.append(registry.get_backend(n))) for n in ("fake:a", "fake", "fake:a")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert made == ["a"] and len(got) == 3 and all(g is got[0] for g in got)
