"""Kernel backends, one sub-package each. Installed as ``place3d_kernels.backends``.

``base`` holds the kernel contract; ``reference`` (NumPy float64) is the executable specification;
``warp`` runs Warp kernels on the CPU or CUDA; ``opencl`` runs OpenCL C through PyOpenCL (PoCL on CPU).
Backends never import the domain package.
"""
