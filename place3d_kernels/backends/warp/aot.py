"""Compiled CUDA kernels shipped with the package, so that a cold host does not wait for NVRTC.

On a CUDA device Warp compiles a module the first time one of its kernels runs, and keeps the result in
its kernel cache. On a host whose cache is empty (a fresh machine, container or CI runner) compiling
``kernels.py`` and the score kernel's module of its own was the largest part of a cold ``place3d
optimize``; loading the shipped CUBINs instead takes a small fraction of that, and the PTX, which the
driver compiles for the device, well under half the compile time, with the same result bits (figures:
bench/README.md, "What the studies found", cold command: kernels and start; docs/architecture.md says
why the binaries are committed).

What is shipped: for each of the modules of ``modules()``, CUBINs for the architectures in ``CUBIN_ARCHS`` and PTX
for ``PTX_ARCH`` (which every later GPU can run through the driver's compiler), under
``aot/warp-<Warp version>/``. A file is named by Warp from the module's content hash (its kernels'
source, the functions they call and the module options), so a binary of other code is never found:
after any change to the kernels, or with another Warp version, ``load`` finds nothing and Warp compiles
as usual. ``tests/test_warp_aot.py`` fails when the shipped files do not match the code, naming the
command that rebuilds them (no GPU needed: Warp's NVRTC compiles for any architecture)::

    python -m place3d_kernels.backends.warp.aot
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import warp as wp

__all__ = ["CUBIN_ARCHS", "PTX_ARCH", "folder", "modules", "binary_for", "load", "build"]

#: CUBINs shipped: A100 (80), RTX 30 / A10 (86), L4 / L40 / RTX 40 (89), H100 / H200 (90), B200 (100),
#: RTX 50 (120); compute capabilities from NVIDIA's CUDA GPU list
CUBIN_ARCHS = (80, 86, 89, 90, 100, 120)
#: PTX shipped for every other architecture from Turing (compute capability 7.5) on
PTX_ARCH = 75


def folder() -> Path:
    """Where the binaries for the installed Warp version live."""
    return Path(__file__).resolve().parent / "aot" / f"warp-{wp.config.version}"


def modules() -> list:
    """The Warp modules shipped compiled: ``kernels.py``, the score kernel's module of its own, the
    jackknife's left-out fields (``left_out_kernels.py``) and the simulation's returns (``returns_kernels.py``). They are what ``place3d optimize`` and
    ``evaluate`` run on a GPU (the left-out fields since pooled P-SOGs are the default: compiled on first
    use they took 1.7 s of a cold ``optimize`` on an H200, 2026-11-29); others (conditions, per-ray scores)
    compile on first use as before."""
    from place3d_kernels.backends.warp import kernels, left_out_kernels, returns_kernels, score_gpu

    return [kernels.raycast_query_kernel.module, score_gpu.score_kernel_gpu.module,
            left_out_kernels.left_out_fields_kernel.module, returns_kernels.returns_hit_kernel.module]


def binary_for(identifier: str, arch: int, where: Path | None = None) -> tuple[int, bool] | None:
    """``(arch, use_ptx)`` of the shipped binary for module ``identifier`` (``Module.get_module_identifier()``,
    name and content hash) on a device of compute capability ``arch``, or None when none fits: a CUBIN
    of that exact architecture, else the PTX of an older one."""
    where = folder() if where is None else where
    if not (where / f"{identifier}.meta").is_file():
        return None
    if (where / f"{identifier}.sm{arch}.cubin").is_file():
        return arch, False
    if arch >= PTX_ARCH and (where / f"{identifier}.sm{PTX_ARCH}.ptx").is_file():
        return PTX_ARCH, True
    return None


def load(device) -> str:
    """Load the shipped binaries of ``modules()`` on CUDA ``device`` (a ``warp.Device``); Warp then launches
    their kernels without compiling. Returns what was done, for logs and the backend's ``stats``: e.g.
    ``"cubin sm90"``, ``"ptx sm75"``, or why nothing was loaded (Warp compiles on first launch then)."""
    where = folder()
    if not where.is_dir():
        return f"none shipped for Warp {wp.config.version}"
    arch = device.arch
    done = []
    for m in modules():
        pick = binary_for(m.get_module_identifier(), arch, where)
        if pick is None:
            return f"none for {m.name} on sm{arch} (code changed since the binaries were built?)"
        a, ptx = pick
        wp.load_aot_module(m, device=device, arch=a, module_dir=str(where), use_ptx=ptx)
        done.append(f"{'ptx' if ptx else 'cubin'} sm{a}")
    return ", ".join(sorted(set(done)))


def build(where: Path | None = None) -> list[Path]:
    """(Re)build the shipped binaries for the installed Warp version into ``where`` (default ``folder()``),
    removing what was there. Needs Warp's NVRTC, not a GPU."""
    where = folder() if where is None else Path(where)
    if where.exists():
        shutil.rmtree(where)
    where.mkdir(parents=True)
    for m in modules():
        for arch, ptx in [(a, False) for a in CUBIN_ARCHS] + [(PTX_ARCH, True)]:
            wp.compile_aot_module(m, arch=arch, module_dir=str(where), use_ptx=ptx)
    for src in where.glob("*.cu"):      # the generated CUDA source: not needed to load
        src.unlink()
    return sorted(where.iterdir())


if __name__ == "__main__":
    import logging

    wp.config.log_level = logging.WARNING
    wp.init()
    for p in build():
        print(f"{p.stat().st_size:>9,d}  {p}")
    sys.exit(0)
