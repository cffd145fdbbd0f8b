"""The package version, in one place (``place3d_kernels.__version__``, ``place3d --version``, manifests)."""

VERSION = "0.1.0"
