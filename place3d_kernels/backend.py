"""Backend selection: names, availability, a scoped default.

Names: ``reference``, ``warp:cpu``, ``warp:cuda:N``, ``opencl:<platform>`` (``opencl:pocl``,
``opencl:nvidia``, ...). Short forms: ``warp`` and ``opencl`` pick that backend's default device
(CUDA / GPU first), ``auto`` picks the fastest available (warp:cuda, opencl GPU, opencl:pocl, warp:cpu,
reference). The default backend comes from ``use_backend`` scopes, else the ``PLACE3D_BACKEND``
environment variable, else ``auto``.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
from functools import lru_cache

__all__ = ["available_backends", "get_backend", "use_backend", "resolve", "backend_report"]

_current: contextvars.ContextVar = contextvars.ContextVar("place3d_backend", default=None)
_instances: dict[str, object] = {}

_INSTALL = {
    "warp": "pip install warp-lang",
    "opencl": "pip install 'place3d-kernels[opencl]'  (PyOpenCL + PoCL CPU driver)",
}


@lru_cache(maxsize=None)
def _probe() -> tuple[tuple[str, ...], tuple[tuple[str, str], ...]]:
    """(available names, (family, reason-unavailable) pairs). Cached: probing imports runtimes."""
    names = ["reference"]
    missing: list[tuple[str, str]] = []
    try:
        from place3d_kernels.backends.warp import warp_devices

        names += [f"warp:{d}" for d in warp_devices()]
    except ImportError as e:
        missing.append(("warp", f"{e}; install with: {_INSTALL['warp']}"))
    try:
        from place3d_kernels.backends.opencl import opencl_devices, unusable_platforms

        devs = opencl_devices()
        names += [f"opencl:{d}" for d in devs]
        missing += [("opencl", f"platform {plat}: {why}") for plat, why in unusable_platforms()]
        if not devs and not unusable_platforms():
            missing.append(("opencl", "no OpenCL platform with a usable device; install a driver such as PoCL: "
                                      + _INSTALL["opencl"]))
    except ImportError as e:
        missing.append(("opencl", f"{e}; install with: {_INSTALL['opencl']}"))
    return tuple(names), tuple(missing)


def available_backends() -> list[str]:
    """Names of the backends usable on this machine, e.g. ``['reference', 'warp:cpu', 'opencl:pocl']``."""
    return list(_probe()[0])


def backend_report() -> list[tuple[str, bool, str]]:
    """(name, available, note) rows: every available backend, and each missing family with the reason."""
    names, missing = _probe()
    rows = [(n, True, "") for n in names]
    rows += [(fam, False, why) for fam, why in missing]
    return rows


def _canonical(name: str) -> str:
    names = available_backends()
    n = name.strip().lower()
    if n == "auto":
        # GPUs first; on the CPU, PoCL (all cores) measured 3-10x faster than Warp's one-thread CPU device
        order = [x for x in names if x.startswith("warp:cuda")] + \
                [x for x in names if x.startswith("opencl:") and x != "opencl:pocl"] + \
                [x for x in names if x == "opencl:pocl"] + [x for x in names if x == "warp:cpu"] + ["reference"]
        return order[0]
    if n in ("warp", "opencl"):
        fam = [x for x in names if x.startswith(n + ":")]
        gpu = [x for x in fam if not x.endswith(":cpu") and x != "opencl:pocl"]
        if fam:
            return (gpu or fam)[0]
    if n == "warp:cuda":
        n = "warp:cuda:0"
    if n in names:
        return n
    missing = dict(_probe()[1])
    fam = n.split(":")[0]
    hint = f" ({missing[fam]})" if fam in missing else ""
    raise ValueError(f"Unknown or unavailable backend {name!r}{hint}. Available here: {names}. "
                     f"Names: 'auto', 'reference', 'warp[:cpu|:cuda:N]', 'opencl[:platform]'. "
                     f"Install the rest with: {_INSTALL['warp']}; {_INSTALL['opencl']}")


def get_backend(name: str | object | None = None):
    """The Backend for a name (``None`` = the current default); instances are cached per name."""
    if name is None:
        name = _current.get() or os.environ.get("PLACE3D_BACKEND") or "auto"
    if not isinstance(name, str):
        return name  # already a Backend
    full = _canonical(name)
    inst = _instances.get(full)
    if inst is None:
        if full == "reference":
            from place3d_kernels.backends.reference import ReferenceBackend as cls

            inst = cls()
        elif full.startswith("warp:"):
            from place3d_kernels.backends.warp import WarpBackend

            inst = WarpBackend(full.split(":", 1)[1])
        else:
            from place3d_kernels.backends.opencl import OpenCLBackend

            inst = OpenCLBackend(full.split(":", 1)[1])
        _instances[full] = inst
    return inst


resolve = get_backend


@contextlib.contextmanager
def use_backend(name):
    """Scoped default backend: ``with use_backend("opencl"): ...``."""
    b = get_backend(name)
    token = _current.set(b.name)
    try:
        yield b
    finally:
        _current.reset(token)
