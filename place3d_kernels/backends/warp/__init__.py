"""Warp backend: the kernels of ``kernels.py`` on Warp's CPU device or a CUDA GPU (host code: ``host.py``; its
prepared grids and M-SOG scores: ``scoring.py``; its CPU thread split: ``cpu_split.py``).

Importing this package raises ImportError when warp-lang is not installed.
"""

from place3d_kernels.backends.warp.host import WarpBackend, WarpCore, cpu_threads, startup_note, warp_devices

__all__ = ["WarpBackend", "WarpCore", "warp_devices", "cpu_threads", "startup_note"]
