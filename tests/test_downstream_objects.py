"""place3d downstream (issue 35), the second part on tiny data: the triangle each simulated return hit."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import place3d_kernels as p3k  # noqa: E402
from place3d_kernels.classes import CLASS_ID, VEHICLE  # noqa: E402
from place3d_kernels.downstream import metrics as dm  # noqa: E402
from place3d_kernels.downstream.dataset import (Rig, Splits, build_datasets, instance_tables,  # noqa: E402
                                                pack_labels, read_frames, sequence_folder, sequence_spec,
                                                unpack_labels, write_drive)

BACKEND = next((b for b in p3k.available_backends() if b != "reference"), None)
needs_backend = pytest.mark.skipif(BACKEND is None, reason="no device backend (warp/opencl) for the simulation")
PEDESTRIAN = CLASS_ID["pedestrian"]


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def tiny_lidar(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text('name = "tiny"\nchannels = 8\nvertical_fov_deg = [-25.0, 2.0]\nhorizontal_fov_deg = 360.0\n'
                    'azimuth_steps = 256\nmax_range_m = 60.0\n')
    return str(path)


def _rig(lidar, name="two"):
    return Rig(name, ((0.5, 0.3, 2.0, 0.0, 0.0, 0.0), (-0.5, -0.3, 1.8, 0.2, 0.0, 0.0)), lidar)


@needs_backend
def test_simulate_hit_faces_names_the_triangle_of_each_return(tiny_lidar):
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.pooled import Drive
    from place3d_kernels.simulate import simulate

    scene = Drive("town", 3, 2).build()
    lidar = LidarModel.load(tiny_lidar)
    plain = simulate(scene, lidar, backend=BACKEND)
    frames, faces = simulate(scene, lidar, backend=BACKEND, hit_faces=True)
    for f, (a, b, (on_actor, face)) in enumerate(zip(plain, frames, faces)):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.intensity, b.intensity)
        # the face's label is the return's label, in the mesh it came from
        dyn = scene.dynamic(f)
        lab = np.where(on_actor, dyn.labels[np.where(on_actor, face, 0)], scene.static.labels[np.where(on_actor, 0, face)])
        np.testing.assert_array_equal(lab, b.labels)
        assert on_actor.any() and not on_actor.all()


def _study_args(out, lidar, *extra):
    from place3d_app.commands import downstream as command

    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="command")
    command.add_parser(sub)
    return ap.parse_args(["downstream", "--rigs", "center,pyramid", "--lidar", lidar, "--towns", "town",
                          "--heldout-towns", "", "--train-routes", "0", "--test-routes", "9", "--frames", "2",
                          "--steps", "2", "--seeds", "0", "--bev-cells", "16", "--width", "4", "--depth", "2",
                          "--resamples", "20", "--device", "cpu", "--backend", BACKEND or "reference",
                          "--output", str(out), "--quiet", *extra])
