"""What the two downstream test files share: the simulation backend, one PyTorch thread, a two-LiDAR rig."""

from __future__ import annotations

import pytest

import place3d_kernels as p3k
from place3d_kernels.downstream.dataset import Rig

# the reference backend casts one frame of the embedded town in minutes; any device backend does it at once
BACKEND = next((b for b in p3k.available_backends() if b != "reference"), None)
needs_backend = pytest.mark.skipif(BACKEND is None, reason="no device backend (warp/opencl) for the simulation")


@pytest.fixture(autouse=True)
def _one_thread():
    # the CI and dev machines are small and shared: two PyTorch threads there run many times slower than one
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _rig(lidar, name="two"):
    return Rig(name, ((0.5, 0.3, 2.0, 0.0, 0.0, 0.0), (-0.5, -0.3, 1.8, 0.2, 0.0, 0.0)), lidar)


def tiny_lidar_file(folder, channels: int, fov_deg: tuple, azimuth_steps: int) -> str:
    """A small spinning LiDAR's TOML file in ``folder`` (60 m range, 360 degrees): the tests' sensors."""
    path = folder / "tiny.toml"
    path.write_text(f'name = "tiny"\nchannels = {channels}\nvertical_fov_deg = [{fov_deg[0]}, {fov_deg[1]}]\n'
                    f'horizontal_fov_deg = 360.0\nazimuth_steps = {azimuth_steps}\nmax_range_m = 60.0\n')
    return str(path)
