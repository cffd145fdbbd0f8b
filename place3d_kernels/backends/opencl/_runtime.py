"""OpenCL platforms, short names, and the per-context program cache.

Imports PyOpenCL at module import: ``ImportError`` here means the OpenCL backend is not installed.
"""

from __future__ import annotations

import logging
import re
import threading
from functools import lru_cache
from pathlib import Path

from place3d_kernels.backends.warnfilters import ignoring

try:
    import pyopencl as cl
except ImportError as e:  # pragma: no cover - depends on the environment
    raise ImportError(f"PyOpenCL is not installed ({e})") from e

__all__ = ["INSTALL_HINT", "platform_table", "unusable_platforms", "short_name", "build_program", "kernel_source"]

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'place3d-kernels[opencl]'  (PyOpenCL + the PoCL CPU driver)"

#: substrings of CL platform names -> the short names used in backend names (``opencl:<short>``)
_KNOWN = (
    ("portable computing language", "pocl"),
    ("pocl", "pocl"),
    ("nvidia", "nvidia"),
    ("amd", "amd"),
    ("intel", "intel"),
    ("apple", "apple"),
    ("rusticl", "rusticl"),
    ("clover", "clover"),
    ("oclgrind", "oclgrind"),
    ("arm", "arm"),
    ("qualcomm", "qualcomm"),
)

_HERE = Path(__file__).resolve().parent


def short_name(platform_name: str) -> str:
    """``'Portable Computing Language'`` -> ``'pocl'``; unknown vendors -> first word, lower case."""
    low = platform_name.strip().lower()
    for key, short in _KNOWN:
        if key in low:
            return short
    words = re.findall(r"[a-z0-9]+", low)
    return words[0] if words else "cl"


_PROBE_SOURCE = "__kernel void probe(__global int *a) { a[get_global_id(0)] = 1; }"
_unusable: list[tuple[str, str]] = []

#: what to do when a platform cannot compile; the PyPI PoCL wheel (3.0, LLVM 14) does not know AMD Zen 5
#: (CPU family 26) and asks its compiler for target CPU 'generic', which LLVM rejects (pocl issue #1049)
POCL_CPU_HINT = ("this PoCL's LLVM does not know the host CPU; install a PoCL whose LLVM does (Debian: "
                 "apt-get install pocl-opencl-icd) and make it visible: export OCL_ICD_VENDORS=/etc/OpenCL/vendors")


def _compiles(ctx: "cl.Context") -> str | None:
    """None if the platform builds a one-line kernel, else the compiler's first error line."""
    try:
        with ignoring(cl.CompilerWarning):
            cl.Program(ctx, _PROBE_SOURCE).build()
    except cl.Error as e:  # RuntimeError subclasses: BUILD_PROGRAM_FAILURE and the like
        lines = [ln.strip() for ln in str(e).splitlines() if "error" in ln.lower() and "clBuild" not in ln]
        return lines[0] if lines else str(e).splitlines()[0]
    return None


@lru_cache(maxsize=None)
def _platforms() -> tuple:
    """((platform, available devices), ...) of every ICD platform with a device, the older of two PoCLs left
    out (``unusable_platforms`` says so); nothing compiled yet."""
    _open_drivers()
    try:
        plats = cl.get_platforms()
    except cl.Error:  # PLATFORM_NOT_FOUND_KHR: the ICD loader found no driver
        return ()
    # Two PoCL installs (Debian's and PyPI's wheel, as .ci/run has them) are the same CPU twice: keep the
    # newest PoCL only. PyPI's 3.0 passes the one-line probe on CPUs its LLVM 14 does not know, then
    # builds the real programs without kernels.
    pocls = sorted((p for p in plats if short_name(p.name) == "pocl"), key=_pocl_version, reverse=True)
    for p in pocls[1:]:
        _unusable.append((f"{p.name} ({p.version.strip()})",
                          f"a second PoCL on the same CPU; using {pocls[0].version.strip()}"))
    out = []
    for p in plats:
        if p in pocls[1:]:
            continue
        try:
            devs = p.get_devices()
        except cl.Error:
            devs = []
        devs = [d for d in devs if d.available]
        if devs:
            out.append((p, devs))
    return tuple(out)


# PyOpenCL calls clGetPlatformIDs (whose first call opens every vendor driver) and clCreateContext holding the
# GIL. Through ctypes, which lets go of it during a foreign call, the same ICD loader opens the drivers and makes
# the context, and PyOpenCL takes the context over. opencl:nvidia's `reproduce --routes 8` on an H200 host
# (three leases, 3 runs each, alternated, the same study numbers): 17.1 -> 14.3, 17.8 -> 15.4, 18.5 -> 16.3 s,
# the pool 1.5-2 s shorter. The pool alone (bench/pool_trace.py, its main process making the backend before the
# map) did not move: the gain is most likely the command's, whose backend starts while a thread of it starts
# the sixteen workers (bench/results/ab-2026-11-30-s33/README.md).
@lru_cache(maxsize=None)
def _icd_loader():
    """PyOpenCL's own ICD loader (the ``libOpenCL`` its extension module loaded, read from /proc/self/maps)
    opened by ctypes, or None where there is not exactly one (not Linux, or something unexpected)."""
    import ctypes

    try:
        with open("/proc/self/maps") as f:
            paths = {ln.split()[-1] for ln in f if "/libOpenCL" in ln}
    except OSError:
        return None
    if len(paths) != 1:
        return None
    try:
        lib = ctypes.CDLL(paths.pop())
        lib.clGetPlatformIDs.restype = ctypes.c_int
        lib.clGetPlatformIDs.argtypes = [ctypes.c_uint, ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint)]
        lib.clCreateContext.restype = ctypes.c_void_p
        lib.clCreateContext.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.POINTER(ctypes.c_void_p),
                                        ctypes.c_void_p, ctypes.c_void_p, ctypes.POINTER(ctypes.c_int)]
    except (OSError, AttributeError):
        return None
    return lib


def _open_drivers() -> None:
    """The ICD loader's first clGetPlatformIDs (it opens every vendor driver) made through ctypes."""
    import ctypes

    lib = _icd_loader()
    if lib is not None:
        lib.clGetPlatformIDs(0, None, ctypes.byref(ctypes.c_uint(0)))


def new_context(dev: "cl.Device") -> "cl.Context":
    """A context on ``dev`` alone, made through ctypes where PyOpenCL's loader is found (the GIL let go while
    the driver works), else by PyOpenCL; either way a ``cl.Context`` that owns its one reference."""
    import ctypes

    lib = _icd_loader()
    if lib is not None:
        err = ctypes.c_int(0)
        handle = lib.clCreateContext(None, 1, (ctypes.c_void_p * 1)(dev.int_ptr), None, None, ctypes.byref(err))
        if handle and err.value == 0:
            return cl.Context.from_int_ptr(handle, retain=False)
    return cl.Context([dev])        # PyOpenCL's own call, and its error where the driver refuses


#: whether each probed device's platform compiles (device pointer -> bool), once per process
_probed: dict = {}
#: the compile probe's context on a device, kept where a backend is about to be made there (``platform_table``
#: with a vendor) and handed to it (``probe_context``): a worker process making opencl:nvidia then makes one
#: context there, not two. A listing of every platform keeps none (a context holds device memory).
_probe_contexts: dict = {}


def _probe(p: "cl.Platform", dev: "cl.Device", keep: bool) -> bool:
    """Whether platform ``p`` compiles the one-line kernel on ``dev`` (else ``unusable_platforms`` says why);
    probed once per process, its context kept for ``probe_context`` with ``keep``."""
    known = _probed.get(dev.int_ptr)
    if known is not None:
        return known
    ctx = new_context(dev)
    why = _compiles(ctx)
    if why is not None:
        hint = POCL_CPU_HINT if "unknown target cpu" in why.lower() else "check the OpenCL driver"
        _unusable.append((f"{p.name} ({p.version.strip()})", f"cannot compile: {why}; {hint}"))
    elif keep:
        _probe_contexts[dev.int_ptr] = ctx
    _probed[dev.int_ptr] = why is None
    return why is None


def probe_context(dev: "cl.Device") -> "cl.Context | None":
    """The compile probe's context on ``dev`` if nothing has taken it yet (then it is given once), else None;
    the probe contexts of other devices are let go (a backend on another device of the platform keeps none)."""
    with _lock:
        ctx = _probe_contexts.pop(dev.int_ptr, None)
        _probe_contexts.clear()
        return ctx


@lru_cache(maxsize=None)
def platform_table(vendor: str | None = None) -> dict[str, tuple["cl.Platform", list["cl.Device"]]]:
    """Usable platforms by unique short name (a second platform of the same vendor gets a suffix 2, 3...).

    Platforms without a device are left out, and so are platforms that cannot compile a one-line kernel
    (``unusable_platforms()`` says why). No ICD platform at all gives an empty dict. ``vendor``: only the
    platforms of that short name (``short_name``; its suffixed names too) are probed and listed: a backend
    named ``opencl:nvidia`` does not start PoCL's compiler and thread pool (with the probe's context handed
    on, sixteen processes starting opencl:nvidia at once on a 16-core H200 host took 0.49-2.55 s each against
    4.60-5.94 s before; bench/results/ab-2026-11-30-s32/README.md, section 2). Cached: each platform is probed
    once per process.
    """
    table: dict[str, tuple[cl.Platform, list[cl.Device]]] = {}
    for p, devs in _platforms():
        base = short_name(p.name)
        if vendor is not None and base != vendor:
            continue
        if not _probe(p, devs[0], keep=vendor is not None):
            continue
        name, k = base, 2
        while name in table:
            name, k = f"{base}{k}", k + 1
        table[name] = (p, devs)
    return table


def _pocl_version(p: "cl.Platform") -> tuple[int, ...]:
    m = re.search(r"PoCL (\d+)\.(\d+)", p.version)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def unusable_platforms() -> list[tuple[str, str]]:
    """(platform, reason) for platforms that have a device but failed the compile probe (every platform probed)."""
    platform_table()
    return list(_unusable)


def kernel_source(*files: str) -> str:
    return "\n".join((_HERE / f).read_text() for f in files)


_programs: dict[tuple, "cl.Program"] = {}
_lock = threading.Lock()


#: Devices this process has said it compiles for (the note is printed once per device).
_noted: set = set()


def _built_marker(ctx: "cl.Context", src: str, options: tuple[str, ...]) -> Path:
    """The file that records that this process's user built ``src`` with ``options`` for ``ctx``'s devices
    (driver versions included) before. PyOpenCL keeps the binaries itself, or leaves it to the driver (PoCL,
    NVIDIA), whose caches cannot be asked; a build that is not recorded here is about to compile."""
    import hashlib

    from pyopencl.cache import get_device_cache_id

    from place3d_kernels.backends.base import cache_dir

    ident = repr(([get_device_cache_id(d) for d in ctx.devices], tuple(options), src))
    return cache_dir() / "opencl-built" / hashlib.sha256(ident.encode()).hexdigest()[:32]


def _note_first_build(ctx: "cl.Context", marker: Path) -> None:
    dev = ctx.devices[0]
    name = f"{dev.name.strip()} ({short_name(dev.platform.name)})"
    if marker.exists() or name in _noted:
        return
    _noted.add(name)
    # INFO: the command prints it (place3d_app.messages) unless --quiet; a library user sees it with logging on
    log.info("compiling OpenCL kernels for %s (first use; cached afterwards)", name)


def _mark_built(marker: Path) -> None:
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
    except OSError:
        pass                    # a read-only cache: the note shows again next time, nothing else changes


def build_program(ctx: "cl.Context", files: tuple[str, ...], options: tuple[str, ...]) -> "cl.Program":
    """Compile once per (context, sources, options); later calls return the cached Program.

    PyOpenCL (or the driver) also keeps compiled binaries on disk, so a new process skips the compiler as
    well. The first build of a program on a device can take a minute or more (PoCL compiles for the host
    CPU); before it, one INFO line says so on the ``place3d_kernels.backends.opencl._runtime`` logger.
    """
    key = (ctx.int_ptr, files, options)
    with _lock:
        prg = _programs.get(key)
        if prg is None:
            src = kernel_source(*files)
            marker = _built_marker(ctx, src, options)
            _note_first_build(ctx, marker)
            with ignoring(cl.CompilerWarning):
                prg = cl.Program(ctx, src).build(options=list(options))
            if not prg.all_kernels():
                # seen with PyPI's PoCL 3.0 (LLVM 14) on AVX-512 CPUs it does not know: the build "succeeds"
                # with no kernels, and the first launch would fail with a bare KeyError
                dev = ctx.devices[0]
                raise RuntimeError(f"OpenCL platform {dev.platform.name} ({dev.platform.version.strip()}) built "
                                   f"{'+'.join(files)} without any kernel; {POCL_CPU_HINT}")
            _programs[key] = prg
            _mark_built(marker)
        return prg
