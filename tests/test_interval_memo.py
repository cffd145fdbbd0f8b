"""The baselines' interval scores remembered on disk (issue 17, goal 1): a warm run rescores only the
optimised rig and gives the same intervals bit for bit; a code change, another setting or a broken file
never reuses an entry. Tiny settings (0.8 m voxels, 16 frames) as in test_intervals.py."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels.interval_memo as im
import place3d_kernels.subset_records as sr
import place3d_kernels.uncertainty as unc
from place3d_kernels.lidar import LidarModel
from place3d_kernels.placement import Placement
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec

BASE = ("center", "line", "pyramid")


@pytest.fixture
def spec(tmp_path):
    # its own cache folder, so the first call in each test is cold
    return PSOGSpec(SceneSpec("town", 0, 16), "warp:cpu", RoiSpec(0.8), cache=str(tmp_path)).resolved()


@pytest.fixture
def scored(monkeypatch):
    """Records the rig names each resampled scoring call was given."""
    calls = []
    for name in ("jackknife_records", "bootstrap_records"):
        real = getattr(unc, name)

        def spy(records, grid, lidar, placements, *a, _real=real, **kw):
            calls.append(list(placements))
            return _real(records, grid, lidar, placements, *a, **kw)

        monkeypatch.setattr(unc, name, spy)
    return calls


def _run(spec, best, method="jackknife", **kw):
    base = {n: Placement.load(n) for n in BASE}
    return unc.rig_vs_baselines_intervals(spec, "place3d_16ch", best, base, "seg", method=method,
                                          n_resamples=12, seed=3, best_name="optimised", backend="warp:cpu", **kw)


@pytest.mark.parametrize("method", ["jackknife", "bootstrap"])
def test_warm_run_scores_only_the_optimised_rig_and_matches(spec, scored, method):
    best = Placement.load("square").poses
    cold = _run(spec, best, method)
    assert scored == [["optimised", *BASE]]
    files = list(im.Path(spec.cache).glob("subsets-*-intervals-*.json"))
    assert len(files) == 1 and im.code_digest() in files[0].name
    warm = _run(spec, best, method)
    assert scored[1] == ["optimised"]
    assert warm == cold                                   # every score and interval, bit for bit
    # another optimised rig: the baselines come from the memo, the new rig is scored
    other = _run(spec, Placement.load("trapezoid").poses, method)
    assert scored[2] == ["optimised"]
    assert [r["score"] for r in other["baselines"]] == [r["score"] for r in cold["baselines"]]
    full = unc.rig_vs_baselines_intervals(spec, "place3d_16ch", Placement.load("trapezoid").poses,
                                          {n: Placement.load(n) for n in BASE}, "seg", method=method,
                                          n_resamples=12, seed=3, best_name="optimised", backend="warp:cpu")
    assert other == full


def test_other_settings_and_code_are_not_reused(spec, scored, monkeypatch):
    best = Placement.load("square").poses
    _run(spec, best)
    _run(spec, best, normalisation="evidence")           # another denominator: every rig scored again
    assert scored[1] == ["optimised", *BASE]
    _run(spec, best, method="bootstrap")                  # another method
    assert scored[2] == ["optimised", *BASE]
    monkeypatch.setattr(im, "code_digest", lambda: "0" * 16)   # as after a code change
    again = _run(spec, best)
    assert scored[3] == ["optimised", *BASE]
    names = sorted(p.name for p in im.Path(spec.cache).glob("subsets-*-intervals-*.json"))
    assert len(names) == 1 and names[0].endswith("-intervals-" + "0" * 16 + ".json")   # the old one removed
    assert again["baselines"] == _run(spec, best)["baselines"]


def test_a_broken_memo_is_recomputed(spec, scored):
    best = Placement.load("square").poses
    want = _run(spec, best)
    (f,) = im.Path(spec.cache).glob("subsets-*-intervals-*.json")
    f.write_text("{not json")
    assert _run(spec, best) == want and scored[1] == ["optimised", *BASE]


def test_rig_key_covers_lidar_poses_and_setting():
    lidar = LidarModel.load("place3d_16ch")
    poses = Placement.load("line").poses
    k = im.rig_key(lidar, poses, task="seg", method="jackknife")
    assert k == im.rig_key(LidarModel.load("place3d_16ch"), poses.copy(), method="jackknife", task="seg")
    moved = poses.copy()
    moved[0, 0] = np.nextafter(moved[0, 0], 1.0)          # one ulp
    assert im.rig_key(lidar, moved, task="seg", method="jackknife") != k
    assert im.rig_key(lidar, poses, task="det", method="jackknife") != k
    assert im.rig_key(lidar.subsample(azimuth_step=2), poses, task="seg", method="jackknife") != k


def test_nan_and_exact_floats_round_trip(tmp_path):
    memo = im.IntervalMemo(tmp_path / "subsets-x.npz")
    s = np.array([np.nan, 0.1 + 0.2, -1e-300, np.nextafter(1.0, 2.0)])
    memo.put("k", -0.0312345678901234, s)
    memo.save()
    point, back = im.IntervalMemo(tmp_path / "subsets-x.npz").get("k")
    assert point == -0.0312345678901234
    assert np.array_equal(back, s, equal_nan=True) and back.tobytes() == s.tobytes()


def test_a_cold_build_keeps_the_subset_records_and_the_same_psog(spec, monkeypatch):
    """On a P-SOG cache miss the P-SOG is pooled from per-subset records written beside it, so the
    intervals do not simulate the drive again; the P-SOG is the one ``PSOG.from_frames`` gives."""
    import sys

    sim = sys.modules["place3d_kernels.simulate"]       # the package exports a function of that name
    built = spec.build(aggregate=sr.records_aggregator(spec))   # cold: simulates, keeps the records
    direct = spec.build(cache=False)                      # PSOG.from_frames on freshly simulated frames
    assert np.array_equal(built.voxels, direct.voxels) and built.probs.tobytes() == direct.probs.tobytes()
    assert np.array_equal(built.counts, direct.counts) and built.n_subsets == direct.n_subsets
    assert built.counts.dtype == direct.counts.dtype
    monkeypatch.setattr(sim, "simulate", lambda *a, **k: pytest.fail("the records were simulated again"))
    recs = sr.spec_subset_records(spec)
    assert len(recs) == built.n_subsets
    best = Placement.load("square").poses
    res = _run(spec, best)                                # the intervals find the records: no simulation
    assert res["n_units"] == built.n_subsets
