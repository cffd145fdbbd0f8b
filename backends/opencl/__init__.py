"""OpenCL backend (PyOpenCL; PoCL on CPU, any OpenCL GPU). Not written yet."""


def opencl_devices() -> list[str]:
    raise ImportError("the OpenCL backend is not implemented yet")


class OpenCLBackend:  # pragma: no cover - placeholder
    def __init__(self, platform: str):
        raise ImportError("the OpenCL backend is not implemented yet")
