"""The reference backend: NumPy float64, simple and exact; the executable specification."""

from place3d_kernels.backends.reference.host import ReferenceBackend, ReferenceCore

__all__ = ["ReferenceBackend", "ReferenceCore"]
