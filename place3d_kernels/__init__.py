"""place3d-kernels (work in progress)."""
