"""``simulate`` with the actors' BVHs built ahead on a thread (``ActorsAhead``) gives the frames the inline
builds give, bit for bit, on every local backend; a failing build reaches the caller; the thread is gone
when ``simulate`` returns."""

from __future__ import annotations

import sys
import threading

import numpy as np
import pytest

from place3d_kernels import scene as scenes
from place3d_kernels.backends.registry import available_backends, get_backend
from place3d_kernels.lidar import LidarModel
from place3d_kernels.profiling import profile
from place3d_kernels.simulate import AHEAD_ENV, ActorsAhead, simulate


@pytest.fixture(scope="module")
def town():
    return scenes.town(seed=3, n_frames=11)


def _lidar():
    full = LidarModel.load("collection_64ch")
    # a sparser sweep of the same sensor keeps the test quick; 11 frames with 3 per call give 4 calls
    return LidarModel(name="sparse", elevations=full.elevations[::4], azimuths=full.azimuths[::8],
                      max_range=full.max_range)


def _frames(town, backend, ahead: str, monkeypatch, **kw):
    monkeypatch.setenv(AHEAD_ENV, ahead)
    return simulate(town, _lidar(), backend=get_backend(backend), **kw)


# the reference backend's ray casts take minutes on this town; the builds ahead are the same code on it
@pytest.mark.parametrize("name", [b for b in available_backends() if b != "reference"])
def test_frames_equal_inline_builds(town, name, monkeypatch):
    sim = sys.modules["place3d_kernels.simulate"]     # the package exports a function of that name
    assert town.actors, "the test needs a scene with actors"
    monkeypatch.setattr(sim, "SWEEP_BATCH_RAYS", 3 * len(_lidar().elevations) * len(_lidar().azimuths))
    with profile(print_table=False) as p0:
        inline = _frames(town, name, "0", monkeypatch)
    pre = {f: town.dynamic(f) for f in (0, 4, 7)}          # as scene_psog hands over prebuilt meshes
    with profile(print_table=False) as p1:
        ahead = _frames(town, name, "1", monkeypatch, dynamic=pre)
    assert pre == {}, "each prebuilt mesh is taken"
    built = ("simulate: BVHs ahead (thread)",)
    assert built not in p0.totals and p1.totals[built][1] == 1 + town.n_frames   # the static mesh, each frame
    assert len(inline) == len(ahead) == town.n_frames
    for a, b in zip(inline, ahead):
        for x, y in ((a.points, b.points), (a.labels, b.labels), (a.intensity, b.intensity),
                     (a.origins, b.origins), (a.sweep_origin, b.sweep_origin), (a.ego_pose, b.ego_pose)):
            x, y = np.asarray(x), np.asarray(y)
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    assert not [t for t in threading.enumerate() if t.name.startswith("place3d-actors")]


def test_a_failing_build_reaches_the_caller(town, monkeypatch):
    calls = []
    real = type(town).dynamic

    def broken(self, frame):
        calls.append(frame)
        if frame == 5:
            raise ValueError("actor mesh of frame 5 is broken")
        return real(self, frame)

    monkeypatch.setattr(type(town), "dynamic", broken)
    with pytest.raises(ValueError, match="frame 5 is broken"):
        _frames(town, "warp:cpu", "1", monkeypatch)
    assert 5 in calls
    assert not [t for t in threading.enumerate() if t.name.startswith("place3d-actors")]


def test_builds_stay_a_bounded_distance_ahead(town):
    b = get_backend("warp:cpu")
    frames = list(range(town.n_frames))
    ahead = ActorsAhead(town, frames, None, b, ahead=2)
    try:
        assert sorted(ahead.futures) == [0, 1]
        ahead.wait_static()
        first = ahead.take(0)
        assert sorted(ahead.futures) == [1, 2]
        assert first is not None and b in first._handles
    finally:
        ahead.close()
