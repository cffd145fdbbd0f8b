"""Caches verified by content (issue 33, item 4).

The manifest beside a cached P-SOG (and subset-record file) records the sha256 of the file's bytes. A file
rewritten with other counts, one flipped byte, or a file without its manifest is not used: it is rebuilt
with one warning (``manifest.StaleCacheWarning``) naming the file and the cause. Before, the manifest
hashed the inputs only: a rewritten .npz, or one without a manifest, was used silently.
"""

from __future__ import annotations

import io
import json
import warnings

import numpy as np
import pytest

from place3d_kernels.grid import DEFAULT_GRID, Grid
from place3d_kernels.manifest import StaleCacheWarning
from place3d_kernels.pipeline import scene_psog

GRID = Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.8)


@pytest.fixture(scope="module")
def town():
    from place3d_kernels import scene as scenes

    return scenes.town(seed=0, n_frames=4)


def _build(town, folder):
    return scene_psog(town, GRID, "place3d_16ch", frames_per_subset=2, backend="warp:cpu", cache=folder)


def _quiet_build(town, folder):
    with warnings.catch_warnings():
        warnings.simplefilter("error", StaleCacheWarning)     # a good cache is read without a word
        return _build(town, folder)


def _same(a, b):
    assert a.voxels.tobytes() == b.voxels.tobytes() and a.counts.tobytes() == b.counts.tobytes()
    np.testing.assert_array_equal(a.probs, b.probs)


def _rebuilt(town, folder, cause):
    with pytest.warns(StaleCacheWarning) as w:
        p = _build(town, folder)
    msgs = [str(x.message) for x in w if issubclass(x.category, StaleCacheWarning)]
    assert len(msgs) == 1 and "\n" not in msgs[0] and ".npz" in msgs[0] and cause in msgs[0], msgs
    return p


def test_a_rewritten_psog_with_other_counts_is_rebuilt(town, tmp_path):
    first = _build(town, tmp_path)
    (npz,) = tmp_path.glob("psog-*.npz")
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["occupied_counts"] = arrays["occupied_counts"] + 1   # a valid file with other counts
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    npz.write_bytes(buf.getvalue())
    again = _rebuilt(town, tmp_path, "content differs from the sha256")
    _same(again, first)
    _same(_quiet_build(town, tmp_path), first)                 # the rebuilt file is good again


def test_a_flipped_byte_in_a_psog_is_rebuilt(town, tmp_path):
    first = _build(town, tmp_path)
    (npz,) = tmp_path.glob("psog-*.npz")
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0x04
    npz.write_bytes(bytes(data))
    _same(_rebuilt(town, tmp_path, "sha256"), first)


def test_a_psog_without_its_manifest_is_rebuilt(town, tmp_path):
    first = _build(town, tmp_path)
    (man,) = tmp_path.glob("psog-*.json")
    man.unlink()
    _same(_rebuilt(town, tmp_path, "without its manifest"), first)
    assert "content_sha256" in json.loads(man.read_text())


def test_a_manifest_without_a_content_hash_is_rebuilt(town, tmp_path):
    """A cache written by an earlier version (its manifest holds the inputs only) is rebuilt once."""
    _build(town, tmp_path)
    (man,) = tmp_path.glob("psog-*.json")
    m = json.loads(man.read_text())
    del m["content_sha256"]
    man.write_text(json.dumps(m))
    _rebuilt(town, tmp_path, "no content hash")


def test_subset_records_are_verified_too(tmp_path, monkeypatch):
    from place3d_kernels import subset_records as SR
    from place3d_kernels.pooled import DriveRecord

    recs = [DriveRecord("a", 2, np.arange(5, dtype=np.int64), np.ones(5, np.int16), np.ones(5, np.int32))]
    path = tmp_path / "subsets-x.npz"
    inputs = {"kind": "subset-records", "k": 2}
    SR._write_records(path, inputs, recs)
    monkeypatch.setattr(SR, "subset_records_path", lambda spec: (path, inputs))
    data = bytearray(path.read_bytes())
    data[-30] ^= 0x01
    path.write_bytes(bytes(data))

    class Spec:                                 # only what the rebuild path reads after the failed check
        backend, frames_per_subset = "reference", 2

    monkeypatch.setattr(SR, "frame_subset_records", lambda *a, **k: recs)
    import importlib

    monkeypatch.setattr(importlib.import_module("place3d_kernels.simulate"), "simulate", lambda *a, **k: [])
    spec = Spec()
    spec.scene = type("S", (), {"kind": "town", "label": "t", "build": lambda self: None})()
    spec.grid = type("G", (), {"grid": lambda self: GRID})()
    spec.lidar, spec.mount, spec.condition = "place3d_16ch", None, None
    spec.vehicle_body = lambda: None
    with pytest.warns(StaleCacheWarning, match="subsets-x.npz"):
        got = SR.spec_subset_records(spec)
    assert got[0].voxels.tolist() == list(range(5))
    with warnings.catch_warnings():
        warnings.simplefilter("error", StaleCacheWarning)
        assert SR.spec_subset_records(spec)[0].counts.tolist() == [1] * 5     # rewritten intact
