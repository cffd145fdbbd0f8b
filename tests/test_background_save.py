"""A P-SOG saved on the cache's thread (``scene_psog(save_in_background=True)``) is the file a direct save
writes, with its manifest; the CLI's command ends with it on disk; a failed background save is a warning."""

from __future__ import annotations

import logging
import sys
import zipfile

import numpy as np
import pytest

from place3d_kernels.grid import Grid
from place3d_kernels.manifest import read_manifest
from place3d_kernels.pipeline import scene_psog, wait_for_saves

GRID = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), 0.4)
PIPE = sys.modules["place3d_kernels.pipeline"]


@pytest.fixture(scope="module")
def town():
    from place3d_kernels import scene as scenes

    return scenes.town(seed=1, n_frames=8)


def _members(path) -> dict:
    with zipfile.ZipFile(path) as z:
        return {i.filename: z.read(i.filename) for i in z.infolist()}


def test_background_file_equals_the_direct_one(town, tmp_path):
    direct = scene_psog(town, grid=GRID, cache=tmp_path / "a")
    back = scene_psog(town, grid=GRID, cache=tmp_path / "b", save_in_background=True)
    wait_for_saves()
    assert not PIPE._saves
    (fa,), (fb,) = list((tmp_path / "a").glob("psog-*.npz")), list((tmp_path / "b").glob("psog-*.npz"))
    assert fa.name == fb.name
    assert _members(fa) == _members(fb)                  # the same bytes of every member
    ma, mb = read_manifest(fa.with_suffix(".json")), read_manifest(fb.with_suffix(".json"))
    assert ma["spec"] == mb["spec"] and ma["sha256"] == mb["sha256"]
    again = scene_psog(town, grid=GRID, cache=tmp_path / "b")          # read back from the cache
    assert again.voxels.tobytes() == direct.voxels.tobytes() and again.counts.tobytes() == direct.counts.tobytes()
    assert np.array_equal(back.probs, again.probs)


def test_failed_background_save_is_a_warning(town, tmp_path, monkeypatch, caplog):
    def refuse(self, path):
        raise PermissionError(f"read-only: {path}")

    monkeypatch.setattr(PIPE.PSOG, "save", refuse)
    with caplog.at_level(logging.WARNING, logger="place3d_kernels.pipeline"):
        psog = scene_psog(town, grid=GRID, cache=tmp_path / "c", save_in_background=True)
        wait_for_saves()
    assert psog.n_subsets == 2
    assert "not written" in caplog.text and "read-only" in caplog.text
    assert not list((tmp_path / "c").glob("psog-*.json"))   # no manifest without its P-SOG


def test_cli_command_ends_with_the_psog_on_disk(tmp_path, monkeypatch):
    from place3d_app.cli import main

    started = []
    real = PIPE._save

    def slow_save(*a):
        import time

        started.append(1)
        time.sleep(0.5)                                   # still writing when the command's work is done
        real(*a)

    monkeypatch.setattr(PIPE, "_save", slow_save)
    cache = tmp_path / "cache"
    monkeypatch.setenv("PLACE3D_CACHE", str(cache))
    out = tmp_path / "ev.json"
    assert main(["evaluate", "--quiet", "--routes", "1", "--frames", "8", "--voxel-size", "0.4", "--interval", "none", "center",
                 "--output", str(out)]) == 0
    assert started and list(cache.glob("psog-*.npz")) and list(cache.glob("psog-*.json"))
    assert not PIPE._saves
