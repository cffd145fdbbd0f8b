"""OpenCL backend (PyOpenCL; PoCL on the CPU, any OpenCL GPU).

``opencl_devices()`` lists the usable platforms by short name (``"pocl"``, ``"nvidia"``, ...);
``OpenCLBackend(name)`` runs the kernels of ``place3d_kernels/backends/base.py`` on one of them. Kernel sources are the
``*.cl`` files next to this module; the ray caster's BVH is built on the host (``bvh.py``).

Importing this package raises ImportError when PyOpenCL is not installed.
"""

from __future__ import annotations

try:
    import pyopencl  # noqa: F401
except ImportError as e:  # pragma: no cover - depends on the environment
    raise ImportError(f"PyOpenCL is not installed ({e})") from e

from place3d_kernels.backends.opencl._runtime import INSTALL_HINT, platform_table, unusable_platforms
from place3d_kernels.backends.opencl.backend import OpenCLBackend


def opencl_devices() -> list[str]:
    """Short names of the OpenCL platforms that have a usable device, e.g. ``['pocl']``; ``[]`` if none.

    Raises:
        ImportError: PyOpenCL is not installed.
    """
    return list(platform_table())


__all__ = ["OpenCLBackend", "opencl_devices", "unusable_platforms", "INSTALL_HINT"]
