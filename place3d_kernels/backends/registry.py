"""Backend selection: the table of backend families, availability, a scoped default.

Names: ``reference``, ``warp:cpu``, ``warp:cuda:N``, ``opencl:<platform>`` (``opencl:pocl``,
``opencl:nvidia``, ...). Short forms: ``warp`` and ``opencl`` pick that backend's default device
(CUDA / GPU first), ``auto`` picks the fastest available (warp:cuda, opencl GPU, opencl:pocl, warp:cpu,
reference). The default backend comes from ``use_backend`` scopes, else the ``PLACE3D_BACKEND``
environment variable, else ``auto``.

Adding a backend is one ``FAMILIES`` entry and one folder beside ``reference/``, ``warp/``, ``opencl/``
whose ``__init__.py`` exports the host class and, for a family with devices, its probe function.
"""

from __future__ import annotations

import contextlib
import contextvars
import importlib
import os
import re
import sys
import threading
from dataclasses import dataclass
from functools import lru_cache

__all__ = ["Family", "FAMILIES", "available_backends", "default_name", "get_backend", "use_backend", "resolve",
           "backend_report", "forget"]


@dataclass(frozen=True)
class Family:
    """One backend family as data: where it lives and how to find its devices.

    Attributes:
        module: package of the backend (imported lazily: importing it imports the runtime).
        host: name of the host class in ``module``; constructed as ``host(device)`` for a family with
            devices, ``host()`` otherwise.
        devices: name of the probe function in ``module`` returning the device names (``"cpu"``,
            ``"cuda:0"``, ``"pocl"``); ``None`` for a family that is one backend named as the family.
        unusable: name of a function in ``module`` returning ``(device, reason)`` pairs for devices found
            but unusable (reported as missing); ``None`` if the family has none.
        install: the command that installs the family's runtime, quoted in errors.
        no_device: the reason reported when the runtime imports but finds no device (``{install}`` is
            replaced by ``install``); ``None`` reports nothing.
        startup_note: name of a function in ``module`` returning what the runtime said at start-up
            (e.g. Warp's missing CUDA driver), quoted when a device of the family is asked for but
            missing; ``None`` if the family has none.
    """

    module: str
    host: str
    devices: str | None = None
    unusable: str | None = None
    install: str = ""
    no_device: str | None = None
    startup_note: str | None = None


#: Every backend family, in the order ``available_backends`` lists them.
FAMILIES: dict[str, Family] = {
    "reference": Family("place3d_kernels.backends.reference", "ReferenceBackend"),
    "warp": Family("place3d_kernels.backends.warp", "WarpBackend", devices="warp_devices",
                   install="pip install warp-lang", startup_note="startup_note"),
    "opencl": Family("place3d_kernels.backends.opencl", "OpenCLBackend", devices="opencl_devices",
                     unusable="unusable_platforms",
                     install="pip install 'place3d-kernels[opencl]'  (PyOpenCL + PoCL CPU driver)",
                     no_device="no OpenCL platform with a usable device; install a driver such as PoCL: {install}"),
}

_current: contextvars.ContextVar = contextvars.ContextVar("place3d_backend", default=None)
_instances: dict[str, object] = {}
#: Held while a backend is resolved and made: a thread asking for a backend another thread is making waits
#: for that one instead of making a second (a worker process makes its backend on a thread while its first
#: task builds a scene; ``place3d_app.executors``). Re-entrant: making a backend may resolve another.
_making = threading.RLock()


def _probe_family(fam: str, spec: Family) -> tuple[list[str], list[tuple[str, str]]]:
    """(backend names, (family, reason-unavailable) pairs) of one family."""
    if spec.devices is None:
        return [fam], []
    try:
        mod = importlib.import_module(spec.module)
    except ImportError as e:
        return [], [(fam, f"{e}; install with: {spec.install}")]
    except Exception as e:  # noqa: BLE001 - a broken install (e.g. the empty folder an uninstall leaves) fails
        # its import with another error; the family is then unavailable, not every command ("auto" probes it)
        return [], [(fam, f"its runtime failed to import ({type(e).__name__}: {e}); reinstall with: {spec.install}")]
    try:
        devs = getattr(mod, spec.devices)()
        bad = getattr(mod, spec.unusable)() if spec.unusable else []
    except ImportError as e:
        return [], [(fam, f"{e}; install with: {spec.install}")]
    missing = [(fam, f"platform {dev}: {why}") for dev, why in bad]
    if not devs and not bad and spec.no_device:
        missing.append((fam, spec.no_device.format(install=spec.install)))
    return [f"{fam}:{d}" for d in devs], missing


@lru_cache(maxsize=None)
def _probe_cached(fam: str) -> tuple[tuple[str, ...], tuple[tuple[str, str], ...]]:
    """``_probe_family`` of one family, cached: probing imports that family's runtime (Warp: a visible
    part of a command's start; OpenCL: PyOpenCL plus a probe kernel build), which a command naming another
    backend never needs."""
    names, missing = _probe_family(fam, FAMILIES[fam])
    return tuple(names), tuple(missing)


def _probe(families=None) -> tuple[tuple[str, ...], tuple[tuple[str, str], ...]]:
    """(available names, (family, reason-unavailable) pairs) of ``families`` (default: all), in
    ``FAMILIES`` order."""
    names: list[str] = []
    missing: list[tuple[str, str]] = []
    for fam in FAMILIES:
        if families is None or fam in families:
            n, m = _probe_cached(fam)
            names += n
            missing += m
    return tuple(names), tuple(missing)


def available_backends() -> list[str]:
    """Names of the backends usable on this machine, e.g. ``['reference', 'warp:cpu', 'opencl:pocl']``."""
    return list(_probe()[0])


def backend_report() -> list[tuple[str, bool, str]]:
    """(name, available, note) rows: every available backend, and each missing family with the reason."""
    names, missing = _probe()
    rows = [(n, True, "") for n in names]
    rows += [(fam, False, why) for fam, why in missing]
    # a family that imports but finds no CUDA device says why only in its start-up output (Warp: "Could
    # not find or load the NVIDIA CUDA driver"); the report quotes it so that a missing GPU is explained
    for fam, spec in FAMILIES.items():
        if not spec.startup_note or spec.module not in sys.modules:
            continue
        note = getattr(sys.modules[spec.module], spec.startup_note)()
        if note and "cuda" in note.lower() and not any(n.startswith(f"{fam}:cuda") for n in names):
            rows.append((f"{fam}:cuda", False, f"no CUDA device usable ({fam} said at start-up: {note})"))
    return rows


def _cuda_driver_loadable() -> bool:
    """Whether the NVIDIA driver library loads (cheap), so "auto" on a machine without one never imports
    Warp only to learn that it has no CUDA device (a visible part of every CPU command)."""
    import ctypes

    for lib in ("libcuda.so.1", "libcuda.so", "nvcuda.dll", "libcuda.dylib"):
        try:
            ctypes.CDLL(lib)
            return True
        except OSError:
            continue
    return False


def _cpu_name(name: str) -> bool:
    """Whether a backend name is a CPU device: ``warp:cpu`` and every PoCL platform (a second PoCL install,
    e.g. PyPI's beside Debian's, is ``opencl:pocl2``: still the CPU, never taken for a GPU)."""
    return name.endswith(":cpu") or re.fullmatch(r"opencl:pocl\d*", name) is not None


def _auto() -> str:
    """The backend "auto" names: a CUDA GPU through Warp, then an OpenCL GPU, then PoCL (all cores) before
    Warp's CPU device (PoCL's walk keeps 16 rays in vector lanes and ran the M-SOG faster than Warp's CPU
    kernels: bench/README.md, "What the studies found", M-SOG walk on the CPU), then the reference.
    Families are probed in that order and only until one answers (each probe imports a runtime)."""
    if _cuda_driver_loadable():
        cuda = [x for x in _probe(("warp",))[0] if x.startswith("warp:cuda")]
        if cuda:
            return cuda[0]
    cl_names = _probe(("opencl",))[0]
    gpu = [x for x in cl_names if x.startswith("opencl:") and not _cpu_name(x)]
    if gpu:
        return gpu[0]
    pocl = [x for x in cl_names if _cpu_name(x)]
    if pocl:
        return pocl[0]
    if "warp:cpu" in _probe(("warp",))[0]:
        return "warp:cpu"
    return "reference"


def _canonical(name: str) -> str:
    n = name.strip().lower()
    family = n.split(":")[0]
    # a name of one family probes that family only ("opencl:pocl" never imports Warp); "auto" probes in
    # its order until one answers (_auto); unknown names probe them all
    if n == "auto":
        return _auto()
    names = list(_probe(None if family not in FAMILIES else (family,))[0])
    if n in FAMILIES and FAMILIES[n].devices is not None:
        fam = [x for x in names if x.startswith(n + ":")]
        gpu = [x for x in fam if not _cpu_name(x)]
        if fam:
            return (gpu or fam)[0]
    if n == "warp:cuda":
        n = "warp:cuda:0"
    if n in names:
        return n
    missing = dict(_probe()[1])
    names = available_backends()
    hint = f" ({missing[family]})" if family in missing else ""
    spec = FAMILIES.get(family)
    if not hint and spec is not None and spec.startup_note and spec.module in sys.modules:
        note = getattr(sys.modules[spec.module], spec.startup_note)()
        hint = f" ({family} said at start-up: {note})" if note else ""
    raise ValueError(f"Unknown or unavailable backend {name!r}{hint}. Available here: {names}. "
                     f"Names: 'auto', 'reference', 'warp[:cpu|:cuda:N]', 'opencl[:platform]'. "
                     f"Install the rest with: {FAMILIES['warp'].install}; {FAMILIES['opencl'].install}")


def _construct(full: str):
    """A new backend for a canonical name: the family's host class, given the device if it has any."""
    fam, _, device = full.partition(":")
    spec = FAMILIES[fam]
    cls = getattr(importlib.import_module(spec.module), spec.host)
    return cls(device) if spec.devices is not None else cls()


def default_name() -> str:
    """The name ``get_backend(None)`` resolves: the innermost ``use_backend`` scope's, else ``$PLACE3D_BACKEND``,
    else ``"auto"``."""
    return _current.get() or os.environ.get("PLACE3D_BACKEND") or "auto"


def get_backend(name: str | object | None = None):
    """The Backend for a name (``None`` = the current default, ``default_name``); instances are cached per name."""
    if name is None:
        name = default_name()
    if not isinstance(name, str):
        return name  # already a Backend
    inst = _instances.get(name)
    if inst is not None:
        return inst
    with _making:
        if name not in _instances:
            # a cold start of a Warp CUDA backend: the driver starts on a thread while Warp is imported, or, where
            # Warp is imported but not initialised (a forked worker), while Warp's start imports its kernels
            # (cuda_early.py)
            from place3d_kernels.backends import cuda_early

            cuda_early.start(name)
        full = _canonical(name)
        inst = _instances.get(full)
        if inst is None:
            inst = _instances[full] = _construct(full)
    return inst


resolve = get_backend


def forget() -> None:
    """Probe the families again on next use and drop the cached instances (after installing a driver,
    or in tests that change ``FAMILIES``)."""
    _probe_cached.cache_clear()
    _instances.clear()


@contextlib.contextmanager
def use_backend(name):
    """Scoped default backend: ``with use_backend("opencl"): ...``."""
    b = get_backend(name)
    token = _current.set(b.name)
    try:
        yield b
    finally:
        _current.reset(token)
