"""The reference backend: NumPy float64, simple and exact; the executable specification."""

from place3d_kernels.backends.reference.conditions import ReferenceConditions
from place3d_kernels.backends.reference.core import ReferenceCore


class ReferenceBackend(ReferenceCore, ReferenceConditions):
    name = "reference"


__all__ = ["ReferenceBackend"]
