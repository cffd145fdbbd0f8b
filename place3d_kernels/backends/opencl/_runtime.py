"""OpenCL platforms, short names, and the per-context program cache.

Imports PyOpenCL at module import: ``ImportError`` here means the OpenCL backend is not installed.
"""

from __future__ import annotations

import re
import threading
import warnings
from pathlib import Path

import pyopencl as cl

__all__ = ["INSTALL_HINT", "platform_table", "short_name", "build_program", "kernel_source"]

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


def platform_table() -> dict[str, tuple["cl.Platform", list["cl.Device"]]]:
    """Usable platforms by unique short name (a second platform of the same vendor gets a suffix 2, 3...).

    Platforms without a device are left out. No ICD platform at all gives an empty dict.
    """
    try:
        plats = cl.get_platforms()
    except cl.Error:  # PLATFORM_NOT_FOUND_KHR: the ICD loader found no driver
        return {}
    table: dict[str, tuple[cl.Platform, list[cl.Device]]] = {}
    for p in plats:
        try:
            devs = p.get_devices()
        except cl.Error:
            devs = []
        devs = [d for d in devs if d.available]
        if not devs:
            continue
        base = short_name(p.name)
        name, k = base, 2
        while name in table:
            name, k = f"{base}{k}", k + 1
        table[name] = (p, devs)
    return table


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
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cl.CompilerWarning)
                prg = cl.Program(ctx, src).build(options=list(options))
            _programs[key] = prg
        return prg
