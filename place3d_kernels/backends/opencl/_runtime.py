"""OpenCL platforms, short names, and the per-context program cache.

Imports PyOpenCL at module import: ``ImportError`` here means the OpenCL backend is not installed.
"""

from __future__ import annotations

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
def platform_table() -> dict[str, tuple["cl.Platform", list["cl.Device"]]]:
    """Usable platforms by unique short name (a second platform of the same vendor gets a suffix 2, 3...).

    Platforms without a device are left out, and so are platforms that cannot compile a one-line kernel
    (``unusable_platforms()`` says why). No ICD platform at all gives an empty dict. Cached: the probe
    compiles once per process.
    """
    try:
        plats = cl.get_platforms()
    except cl.Error:  # PLATFORM_NOT_FOUND_KHR: the ICD loader found no driver
        return {}
    table: dict[str, tuple[cl.Platform, list[cl.Device]]] = {}
    # Two PoCL installs (Debian's and PyPI's wheel, as .ci/run has them) are the same CPU twice: keep the
    # newest PoCL only. PyPI's 3.0 passes the one-line probe on CPUs its LLVM 14 does not know, then
    # builds the real programs without kernels.
    pocls = sorted((p for p in plats if short_name(p.name) == "pocl"), key=_pocl_version, reverse=True)
    for p in pocls[1:]:
        _unusable.append((f"{p.name} ({p.version.strip()})",
                          f"a second PoCL on the same CPU; using {pocls[0].version.strip()}"))
    plats = [p for p in plats if p not in pocls[1:]]
    for p in plats:
        try:
            devs = p.get_devices()
        except cl.Error:
            devs = []
        devs = [d for d in devs if d.available]
        if not devs:
            continue
        why = _compiles(cl.Context(devs[:1]))
        if why is not None:
            hint = POCL_CPU_HINT if "unknown target cpu" in why.lower() else "check the OpenCL driver"
            _unusable.append((f"{p.name} ({p.version.strip()})", f"cannot compile: {why}; {hint}"))
            continue
        base = short_name(p.name)
        name, k = base, 2
        while name in table:
            name, k = f"{base}{k}", k + 1
        table[name] = (p, devs)
    return table


def _pocl_version(p: "cl.Platform") -> tuple[int, ...]:
    m = re.search(r"PoCL (\d+)\.(\d+)", p.version)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def unusable_platforms() -> list[tuple[str, str]]:
    """(platform, reason) for platforms that have a device but failed the compile probe."""
    platform_table()
    return list(_unusable)


def kernel_source(*files: str) -> str:
    return "\n".join((_HERE / f).read_text() for f in files)


_programs: dict[tuple, "cl.Program"] = {}
_lock = threading.Lock()


def build_program(ctx: "cl.Context", files: tuple[str, ...], options: tuple[str, ...]) -> "cl.Program":
    """Compile once per (context, sources, options); later calls return the cached Program.

    PyOpenCL also keeps compiled binaries on disk, so a new process skips the compiler as well.
    """
    key = (ctx.int_ptr, files, options)
    with _lock:
        prg = _programs.get(key)
        if prg is None:
            src = kernel_source(*files)
            with ignoring(cl.CompilerWarning):
                prg = cl.Program(ctx, src).build(options=list(options))
            if not prg.all_kernels():
                # seen with PyPI's PoCL 3.0 (LLVM 14) on AVX-512 CPUs it does not know: the build "succeeds"
                # with no kernels, and the first launch would fail with a bare KeyError
                dev = ctx.devices[0]
                raise RuntimeError(f"OpenCL platform {dev.platform.name} ({dev.platform.version.strip()}) built "
                                   f"{'+'.join(files)} without any kernel; {POCL_CPU_HINT}")
            _programs[key] = prg
        return prg
