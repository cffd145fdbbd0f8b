"""A long simulation says how big it is, and one that cannot fit in memory is refused first (issue 33, item 6:
``--frames 100000`` started with no estimate).

Before, ``place3d evaluate --frames 100000`` started building a town of 100,000 frames (minutes alone), then
simulated frames whose returns (up to 342 GiB with the collection LiDAR) could never be held in memory.
"""

from __future__ import annotations

import importlib

import pytest

from place3d_app.cli import main
from place3d_kernels.lidar import LidarModel

simulate = importlib.import_module("place3d_kernels.simulate")      # the package exports a function of that name
pipeline = importlib.import_module("place3d_kernels.pipeline")

GIB = 2 ** 30


@pytest.fixture
def no_work(monkeypatch, tmp_path):
    """Any scene build or simulation fails the test at once (the old code started them)."""
    from place3d_kernels import spec as spec_mod

    def boom(*a, **k):
        raise AssertionError("work started before --frames was checked")

    monkeypatch.setattr(spec_mod, "_build_scene", boom)
    # the drives a cold cache lacks go to worker processes first, which this process's patches do not reach
    monkeypatch.setattr("place3d_app.commands.routes.build_missing", boom)
    monkeypatch.setattr(simulate, "simulate", boom)
    monkeypatch.setattr(pipeline, "simulate", boom)
    monkeypatch.setattr(simulate, "physical_memory", lambda: 16 * GIB, raising=False)
    monkeypatch.chdir(tmp_path)


@pytest.mark.parametrize("argv, lidar", [
    (["evaluate", "--frames", "100000", "--backend", "reference"], "collection_64ch"),
    (["optimize", "--frames", "100000", "--backend", "reference"], "collection_64ch"),
    (["simulate", "--frames", "100000", "--lidar", "place3d_16ch", "--output", "seq"], "place3d_16ch"),
])
def test_frames_beyond_memory_are_refused_naming_the_most(no_work, capsys, argv, lidar):
    assert main(argv + ["--quiet"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("place3d: error: --frames 100000 would hold up to"), err
    L = LidarModel.load(lidar)
    most = int(simulate.MEMORY_SHARE * 16 * GIB) // simulate.simulation_size(1, L)[1]
    assert f"use at most {most:,} frames" in err[0] and "this machine has 16 GiB" in err[0]
    assert f"x {len(L.elevations) * len(L.azimuths):,} rays of {lidar}" in err[0]


def test_a_long_simulation_is_announced_before_the_scene_is_built(no_work, monkeypatch, capsys):
    monkeypatch.setattr(simulate, "physical_memory", lambda: 1024 * GIB, raising=False)
    with pytest.raises(AssertionError, match="work started"):        # announced, then the scene build starts
        main(["evaluate", "--frames", "3000", "--backend", "reference"])
    err = capsys.readouterr().err
    assert "place3d: simulating 3,000 frames x 65,536 rays of collection_64ch" in err, err


def test_quiet_and_short_simulations_are_not_announced(no_work, monkeypatch, capsys):
    monkeypatch.setattr(simulate, "physical_memory", lambda: 1024 * GIB, raising=False)
    for argv in (["evaluate", "--frames", "3000", "--quiet"], ["evaluate", "--frames", "40"]):
        with pytest.raises(AssertionError, match="work started"):
            main(argv + ["--backend", "reference"])
        assert "simulating" not in capsys.readouterr().err
