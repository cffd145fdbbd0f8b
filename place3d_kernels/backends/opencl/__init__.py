"""OpenCL backend (PyOpenCL; PoCL on the CPU, any OpenCL GPU).

``opencl_devices()`` lists the usable platforms by short name (``"pocl"``, ``"nvidia"``, ...);
``unusable_platforms()`` the platforms found but unusable, with the reason and the fix;
``OpenCLBackend(name)`` runs the kernels of ``place3d_kernels/backends/base.py`` on one of them. Kernel
sources are the ``*.cl`` files next to ``host.py``; the ray caster's BVH is built on the host (``bvh.py``).

Importing this package raises ImportError when PyOpenCL is not installed.
"""

from place3d_kernels.backends.opencl._runtime import INSTALL_HINT, unusable_platforms
from place3d_kernels.backends.opencl.host import OpenCLBackend, opencl_devices

__all__ = ["OpenCLBackend", "opencl_devices", "unusable_platforms", "INSTALL_HINT"]
