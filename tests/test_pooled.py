"""Pooled P-SOGs, the bootstrap over drives, and ``place3d reproduce`` (issue 13)."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from place3d_kernels.grid import Grid
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import covered_voxels
from place3d_kernels.pipeline import scene_psog
from place3d_kernels.pooled import Drive, DriveRecord, PooledPSOG, PoolSettings, build_pooled, subset_records
from place3d_kernels.sog import entropy
from place3d_kernels.uncertainty import (Bootstrap, bootstrap_drives, bootstrap_pooled, resample_multiplicities,
                                         within_noise)



def _bernoulli_records(grid, voxels, p, n_drives, seed):
    """n_drives records of one subset each; every voxel is class 1 with probability p, independently."""
    rng = np.random.default_rng(seed)
    recs = []
    for d in range(n_drives):
        on = np.asarray(voxels)[rng.random(len(voxels)) < p]
        recs.append(DriveRecord(f"d{d}", 1, on.astype(np.int64), np.ones(len(on), np.int16), np.ones(len(on), np.int32)))
    return recs


# ------------------------------------------------------------------ (a) bootstrap vs a known variance
def test_bootstrap_se_of_pooled_probability_matches_binomial_variance():
    # one voxel, D drives of T = 1: the pooled p is a mean of D Bernoulli(p) draws, Var = p (1 - p) / D
    grid = Grid((0, 0, 0), (1, 1, 1), 1.0)
    D, p = 400, 0.3
    pooled = PooledPSOG(grid, _bernoulli_records(grid, [0], p, D, seed=1))

    def score(psog):
        return np.array([psog.probs[0, 1] if len(psog.voxels) else 0.0])

    point, samples, mult = bootstrap_pooled(pooled, score, n_resamples=2000, seed=7)
    assert mult.shape == (2000, D) and np.all(mult.sum(axis=1) == D)
    se = samples[:, 0].std(ddof=1)
    plug_in = np.sqrt(point[0] * (1 - point[0]) / D)       # the bootstrap's own target
    truth = np.sqrt(p * (1 - p) / D)
    assert abs(se / plug_in - 1) < 0.06, (se, plug_in)
    assert abs(se / truth - 1) < 0.15, (se, truth)
    assert abs(samples[:, 0].mean() - point[0]) < 3 * truth / np.sqrt(2000) + 1e-3   # the mean is unbiased


def test_bootstrap_se_of_msog_matches_delta_method():
    # N covered voxels, each occupied with probability p per drive independently: by the delta method
    # Var(M-SOG) = H'(p)^2 p (1 - p) / (D N), H'(p) = ln((1 - p) / p) for the two-outcome entropy
    grid = Grid((-2.05, -2.05, -0.05), (1.95, 1.95, 1.95), 0.5)
    lidar = LidarModel.load("place3d_16ch")
    rig = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    D, p = 300, 0.3
    pooled_all = PooledPSOG(grid, _bernoulli_records(grid, np.arange(grid.n_voxels), p, D, seed=3))
    cov = covered_voxels(pooled_all.psog(), lidar, rig, occlusion="none")
    N = len(cov)
    assert N > 20
    pooled = PooledPSOG(grid, _bernoulli_records(grid, cov, p, D, seed=4))
    boot = bootstrap_drives(pooled, lidar, {"rig": rig}, occlusion="none", n_resamples=600, seed=5)
    truth = abs(np.log((1 - p) / p)) * np.sqrt(p * (1 - p) / (D * N))
    assert abs(boot.se[0] / truth - 1) < 0.2, (boot.se[0], truth)
    lo, hi = boot.ci[0]
    assert lo <= boot.point[0] + 1e-12 <= hi + 2 * truth


def test_order_frequencies_and_noise_pairs():
    s = np.array([[1.0, 0.0, 0.5], [1.0, 0.2, 0.6], [1.0, 0.7, 0.4], [1.0, 0.1, 0.5]])
    b = Bootstrap(["a", "b", "c"], np.array([1.0, 0.1, 0.5]), s)
    f = b.order_freq
    assert np.allclose(f + f.T, 1.0) and f[0, 1] == 1.0 and f[2, 1] == 0.75
    assert within_noise(b) == [("c", "b", 0.75)]
    m = resample_multiplicities(6, 50, seed=0, strata=[0, 0, 1, 1, 1, 2])
    assert np.all(m[:, :2].sum(1) == 2) and np.all(m[:, 2:5].sum(1) == 3) and np.all(m[:, 5] == 1)


# ------------------------------------------------------------------ (b) pooling is exact
@pytest.fixture(scope="module")
def two_drives(tmp_path_factory):
    cache = tmp_path_factory.mktemp("psog-cache")
    settings = PoolSettings(0.4, "collection_64ch", 2, None, str(cache))
    drives = [Drive("town", seed=s, frames=6) for s in (0, 1)]
    return drives, settings, build_pooled(drives, settings)


def test_pooled_of_one_drive_is_that_drive(two_drives):
    drives, settings, pooled = two_drives
    ref = scene_psog(drives[0].build(), grid=settings.grid, frames_per_subset=2, backend=settings.backend,
                     cache=settings.cache)
    one = pooled.subset([0]).psog()
    assert np.array_equal(one.voxels, ref.voxels)
    assert np.array_equal(one.probs, ref.probs)            # bit for bit, float64
    assert np.array_equal(one.counts, ref.counts) and one.n_subsets == ref.n_subsets == 3
    assert np.array_equal(one.weights, ref.weights)


def test_pooled_of_two_drives_sums_counts(two_drives):
    drives, settings, pooled = two_drives
    ps = [scene_psog(d.build(), grid=settings.grid, frames_per_subset=2, backend=settings.backend, cache=settings.cache)
          for d in drives]
    both = pooled.psog()
    dense = np.zeros((settings.grid.n_voxels, ps[0].counts.shape[1]), np.int64)
    for q in ps:
        dense[q.voxels, 1:] += q.counts[:, 1:]
    dense[:, 0] = 6 - dense[:, 1:].sum(1)                 # a voxel a drive never saw was empty in its subsets
    keep = dense[:, 1:].sum(1) > 0
    assert np.array_equal(both.voxels, np.flatnonzero(keep))
    assert np.array_equal(both.counts, dense[keep]) and both.n_subsets == 6
    assert np.array_equal(both.probs, dense[keep] / 6.0)
    twice = pooled.psog([2, 0])                           # a resample: drive 0 twice = drive 0's probabilities
    assert np.array_equal(twice.probs, ps[0].probs) and twice.n_subsets == 6
    assert np.allclose(entropy(both.probs).sum(), entropy(dense[keep] / 6.0).sum())


def test_subset_records_sum_to_the_drive(two_drives):
    drives, settings, pooled = two_drives
    subs = PooledPSOG(settings.grid, subset_records(drives[1], settings))
    assert len(subs) == 3
    whole = pooled.subset([1]).psog()
    assert np.array_equal(subs.psog().counts, whole.counts) and np.array_equal(subs.psog().probs, whole.probs)


class _PicklingExecutor:
    """Stands in for Ray: tasks and results cross a pickle boundary, as they do between processes."""

    kind = "pickling"
    submitted = 0

    def map(self, fn, tasks):
        import pickle

        self.submitted += len(tasks)
        return [pickle.loads(pickle.dumps(fn(pickle.loads(pickle.dumps(t))))) for t in tasks]


def test_pooled_through_an_executor_is_identical(two_drives):
    drives, settings, pooled = two_drives
    ex = _PicklingExecutor()
    other = build_pooled(drives, settings, executor=ex)
    assert ex.submitted == 2 and other.labels == pooled.labels
    a, b = other.psog(), pooled.psog()
    assert np.array_equal(a.voxels, b.voxels) and np.array_equal(a.probs, b.probs)


def test_a_pool_task_reads_cached_drives_without_building_their_scenes(tmp_path, monkeypatch):
    """``_records_task`` (a worker's drives): on an empty cache each scene is built once (the build that
    learns its cache key is the one simulated); on a warm cache no scene is built at all, and the records are
    those of the first pass, bit for bit."""
    from place3d_kernels import pooled as pooled_mod
    from place3d_kernels import spec as spec_mod

    built = []
    make = spec_mod.make_scene
    monkeypatch.setattr(spec_mod, "make_scene", lambda s: built.append(s.seed) or make(s))
    spec_mod._build_scene.cache_clear()            # the process's few remembered scenes
    settings = PoolSettings(0.4, "collection_64ch", 2, None, str(tmp_path))
    drives = [Drive("town", seed=s, frames=4) for s in (5, 6)]
    first = pooled_mod._records_task((drives, settings))
    assert sorted(built) == [5, 6]
    built.clear()
    spec_mod._build_scene.cache_clear()
    again = pooled_mod._records_task((drives, settings))
    assert built == []
    for a, b in zip(first, again):
        assert a.label == b.label and a.n_subsets == b.n_subsets
        assert np.array_equal(a.voxels, b.voxels) and np.array_equal(a.counts, b.counts)
    # without a cache every scene is built, once
    spec_mod._build_scene.cache_clear()
    off = PoolSettings(0.4, "collection_64ch", 2, None, False)
    pooled_mod._records_task((drives[:1], off))
    assert built == [5]


def test_bootstrap_over_subsets_of_one_drive(two_drives):
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import Placement
    from place3d_kernels.uncertainty import bootstrap_subsets

    drives, settings, pooled = two_drives
    pls = {n: Placement.load(n) for n in ("center", "line-roll")}
    b = bootstrap_subsets(drives[0], "place3d_16ch", pls, settings, n_resamples=20, seed=1)
    whole = pooled.subset([0]).psog()
    direct = msog_batch(whole, LidarModel.load("place3d_16ch"), np.stack([p.poses for p in pls.values()]))
    assert b.unit == "subsets" and b.n_units == 3 and b.samples.shape == (20, 2)
    assert np.array_equal(b.point, direct)               # the point estimate is the drive's own score
    assert np.all(b.se > 0)


# ------------------------------------------------------------------ (c) reproduce end to end
def test_reproduce_tiny_end_to_end(tmp_path):
    from place3d_app.cli import main

    out = tmp_path / "repro"
    rc = main(["reproduce", "--towns", "town", "--route-seeds", "100,101", "--frames", "4", "--voxel-size", "0.4",
               "--frames-per-subset", "2", "--placements", "2d-plane", "--output", str(out),
               "--quiet"])
    assert rc == 0
    res = json.loads((out / "reproduce.json").read_text())
    assert set(res) >= {"settings", "machine", "time_utc", "seconds", "drives", "tasks", "convergence"}
    assert res["settings"]["voxel_size"] == 0.4 and res["settings"]["routes"] == 2 and len(res["drives"]) == 2
    assert res["settings"]["route_seeds"] == [100, 101] and res["drives"] == ["town-s100-f4", "town-s101-f4"]
    for task in ("seg", "det"):
        t = res["tasks"][task]
        for k in ("placements", "msog", "ci_low", "ci_high", "se", "bias", "rank", "paper_msog_1e-6", "paper_rank",
                  "downstream", "samples", "tau_paper", "tau_paper_loo_range", "tau_downstream",
                  "tau_downstream_loo_range", "order_freq", "within_noise"):
            assert k in t, k
        # the user's rig ranked beside the paper's eight; every interval contains its own point
        assert t["placements"][-1] == "2d-plane" and len(t["msog"]) == 9 and t["paper_rank"][-1] is None
        assert all(lo <= x <= hi for lo, x, hi in zip(t["ci_low"], t["msog"], t["ci_high"]))
        assert t["df"] == 1 and len(t["samples"]) == 2          # two routes, each left out once
        assert -1.0 <= t["tau_paper"] <= 1.0
    assert res["convergence"][0]["n"] == 1 and "tau_seg" in res["convergence"][0]
    assert (out / "reproduce.png").stat().st_size > 10_000


def test_reproduce_outputs_keep_the_json_when_the_figure_drawn_beside_the_study_failed(tmp_path):
    # reproduce(draw_ahead=True) draws the figure into memory on a thread; write_outputs writes the JSON first,
    # then waits for the figure: a failed figure is reported once the study's numbers are on disk, and no
    # reproduce.png of this run (or half of one) is left
    from concurrent.futures import Future

    from place3d_app.commands.reproduce import write_outputs

    out = tmp_path / "o"
    failed = Future()
    failed.set_exception(MemoryError("the figure could not be drawn"))
    res = {"settings": {"towns": ["town"]}, "drives": ["town-s0-f4"], "_boots": None, "_figure": failed}
    with pytest.raises(MemoryError, match="could not be drawn"):
        write_outputs(res, out)
    assert json.loads((out / "reproduce.json").read_text()) == {"settings": {"towns": ["town"]},
                                                                "drives": ["town-s0-f4"]}
    assert not (out / "reproduce.png").exists()
    drawn = Future()
    drawn.set_result(b"\x89PNG drawn ahead")
    write_outputs({**res, "_figure": drawn}, out)
    assert (out / "reproduce.png").read_bytes() == b"\x89PNG drawn ahead"


def test_reproduce_same_study_in_process_and_on_workers(tmp_path):
    # the process executor builds the drives and scores the convergence table's pools on its workers (while
    # the jackknife runs here); the local one does both here: the same study to the last digit
    from place3d_app.cli import main

    res = {}
    for ex in ("local", "process"):
        out = tmp_path / ex
        assert main(["reproduce", "--towns", "town", "--route-seeds", "5,6,7,8", "--frames", "4", "--voxel-size",
                     "0.4", "--frames-per-subset", "2", "--executor", ex, "--output", str(out), "--quiet"]) == 0
        res[ex] = json.loads((out / "reproduce.json").read_text())
    assert res["process"]["settings"]["executor"] == "process"
    assert len(res["local"]["convergence"]) == 2                 # N = 1 and N = 2: five route ranges
    for k in ("tasks", "convergence", "drives"):
        assert json.dumps(res["local"][k]) == json.dumps(res["process"][k]), k


@functools.lru_cache(maxsize=1)
def _four_drive_pool():
    """Four short drives of the embedded town, two "scenes" of two routes (one with more subsets), built
    once on the fastest CPU backend (the backends' P-SOGs agree bit for bit; the reference would simulate
    for minutes)."""
    settings = PoolSettings(voxel_size=0.4, frames_per_subset=2, backend="warp:cpu", cache=False)
    drives = [Drive("town", seed=s, frames=4) for s in (100, 101, 102)] + [Drive("town", seed=103, frames=6)]
    return build_pooled(drives, settings)


def test_reproduce_jackknife_on_patched_grids_equals_rebuilt_pools(device_backend):
    # (the device backends: the reference scores these 64 rig scores by brute force for minutes; the backends
    # agree with it bit for bit: test_normalisation.py, test_counts_exact_across_backends)
    backend = device_backend
    # reproduce's fast path (left-out grids patched from the pool, jackknife_records) against every left-out
    # pool rebuilt and rescored (jackknife_pooled): the same points and leave-one-route-out scores, bit for bit
    from place3d_app.commands.reproduce import jackknife_placements, placement_scorer
    from place3d_kernels.uncertainty import jackknife_pooled

    pooled = _four_drive_pool()
    lidar = LidarModel.load("place3d_16ch")
    extra = np.stack([np.array([[0.0, 0.0, 2.1, 0.0, 0.0, 0.0]] * 4)])
    strata = [0, 0, 1, 1]
    import place3d_kernels.uncertainty as unc

    calls = []
    real = unc.jackknife_records
    with pytest.MonkeyPatch.context() as mp:
        # one left-out pass for both tasks over the union of their rigs: 8 seg, det's "ours", the extra
        mp.setattr(unc, "jackknife_records", lambda *a, **k: calls.append((len(a[3]), a[4])) or real(*a, **k))
        fast = jackknife_placements(pooled, lidar, "sog", backend, "rad", "vehicle", extra, strata=strata)
    assert calls == [(10, ("seg", "det"))]
    slow = jackknife_pooled(pooled, placement_scorer(lidar, "sog", backend, "rad", "vehicle", extra), strata=strata)
    assert fast.samples.shape == slow.samples.shape == (4, 18)
    np.testing.assert_array_equal(fast.point, slow.point)
    np.testing.assert_array_equal(fast.samples, slow.samples)
    assert (fast.strata, fast.df, fast.unit, fast.n_units) == (slow.strata, slow.df, slow.unit, slow.n_units)
    # the rebuilt path stays where the fast one does not apply (another detection view)
    other = jackknife_placements(pooled, lidar, "sog", backend, "rad", "vehicle+pedestrian", extra, strata=strata)
    assert not np.array_equal(other.point[9:], fast.point[9:])


@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_convergence_rows_equal_a_direct_recomputation(device_backend, occlusion):
    # reproduce's convergence table (each route range's grid from its counts, pool_scorer; the whole pool's
    # scores taken from the jackknife's point) against the plain recipe: the records of the routes in range
    # pooled from scratch, the P-SOG scored by msog_batch, tau by kendall_tau; equal to the last digit
    from place3d_app.commands.reproduce import (convergence, jackknife_placements, placement_scorer,
                                                pool_scorer)
    from place3d_kernels import paper_results as paper
    from place3d_kernels.uncertainty import kendall_tau

    pooled = _four_drive_pool()
    lidar = LidarModel.load("place3d_16ch")
    routes_of = [0, 1, 2, 3]            # one scene, four routes: rows N = 1 (1 vs 2) and N = 2 (2 vs 4)
    jk = jackknife_placements(pooled, lidar, occlusion, device_backend, "rad", "vehicle")
    rows = convergence(pooled, routes_of, known={(0, 4): jk.point},
                       score_pool=pool_scorer(lidar, occlusion, device_backend, "rad", "vehicle"))
    score = placement_scorer(lidar, occlusion, device_backend, "rad", "vehicle")

    def direct(lo, hi):
        recs = [r for r, route in zip(pooled.records, routes_of) if lo <= route < hi]
        return score(PooledPSOG(pooled.grid, recs).psog())

    want = []
    for n in (1, 2):
        a, b, c = direct(0, n), direct(0, 2 * n), direct(n, 2 * n)
        want.append({"n": n, "two_n": 2 * n,
                     "tau_seg": kendall_tau(a[:8], b[:8]), "tau_det": kendall_tau(a[8:], b[8:]),
                     "tau_seg_disjoint": kendall_tau(a[:8], c[:8]), "tau_det_disjoint": kendall_tau(a[8:], c[8:]),
                     "tau_seg_paper": kendall_tau(b[:8], paper.paper_msog("seg")),
                     "tau_det_paper": kendall_tau(b[8:], paper.paper_msog("det"))})
    assert json.dumps(rows) == json.dumps(want)          # NaN-safe, every digit
    # the scores behind the taus, bit for bit, for a part of the pool and the whole
    sp = pool_scorer(lidar, occlusion, device_backend, "rad", "vehicle")
    np.testing.assert_array_equal(sp(pooled.subset([1, 2])), direct(1, 3))
    np.testing.assert_array_equal(jk.point, direct(0, 4))


@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_pool_scorer_from_fields_made_on_the_device_is_the_hosts(monkeypatch, occlusion):
    # where the backend makes a P-SOG's fields from its count rows (fields_on_device: Warp on CUDA), the
    # convergence table's pools are scored through the pool's P-SOG; here on warp:cpu made to take that path
    import place3d_kernels as p3k
    from place3d_app.commands.reproduce import pool_scorer
    from place3d_kernels.backends.registry import get_backend

    if "warp:cpu" not in p3k.available_backends():
        pytest.skip("needs Warp")
    b = get_backend("warp:cpu")
    pooled = _four_drive_pool()
    lidar = LidarModel.load("place3d_16ch")
    host = pool_scorer(lidar, occlusion, b, "rad", "vehicle")(pooled.subset([1, 2, 3]))
    monkeypatch.setattr(type(b), "fields_on_device", property(lambda self: True))
    device = pool_scorer(lidar, occlusion, b, "rad", "vehicle")(pooled.subset([1, 2, 3]))
    assert device.shape == (16,)
    np.testing.assert_array_equal(device, host)


def test_scene_groups_pair_the_routes_of_one_town():
    from place3d_kernels.pooled import scene_groups

    drives = [Drive(s, seed=r) for r in range(4) for s in ("A", "B", "C", "D")]      # route-major, as reproduce
    for workers in (2, 3, 8):
        groups = scene_groups(drives, workers)
        assert sorted(i for g in groups for i in g) == list(range(16))
        assert [len(g) for g in groups] == [2] * 8
        assert all(len({drives[i].scene for i in g}) == 1 for g in groups)         # a task never mixes towns
    assert scene_groups(drives, 16) == [[i] for i in (0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15)]
    assert scene_groups(drives[:5], 2) == [[0, 4], [1], [2], [3]]


@pytest.mark.parametrize("ranked", [True, False])
def test_the_plain_pool_summed_on_threads_is_the_sum_on_one(monkeypatch, ranked):
    # a large pool is summed on several threads, each over a block of rows (every record's slice of it): the
    # same integer table as record after record on one thread, with rows found by rank or by binary search and
    # a record whose (voxel, class) entries repeat (summed with np.add.at) among those that do not
    import place3d_kernels.pooled as pooled_mod
    import place3d_kernels.threads as threads_mod

    rng = np.random.default_rng(3)
    grid = Grid((0.0, 0.0, 0.0), (40.0, 40.0, 4.0), 0.1)              # 1.6 M voxels
    recs = []
    for i in range(6):
        v = np.sort(rng.choice(grid.n_voxels, 20_000, replace=False)).astype(np.int64)
        v = np.repeat(v, rng.integers(1, 3, len(v)))                   # a voxel holds one or two classes
        cls = rng.integers(1, 22, len(v)).astype(np.int16)
        if i != 2:                                                    # record 2 keeps repeated (voxel, class) entries
            key, first = np.unique(v * 22 + cls, return_index=True)
            v, cls = v[first], cls[first]
        recs.append(DriveRecord(f"r{i}", 10 + i, v, cls, rng.integers(1, 10, len(v)).astype(np.int32)))
    if not ranked:
        monkeypatch.setattr(pooled_mod, "RANK_VOXELS", 0)
    monkeypatch.setattr(threads_mod, "THREADED_ENTRIES", 1 << 40)         # one thread
    vox1, c1, t1 = PooledPSOG(grid, recs).counts()
    monkeypatch.setattr(threads_mod, "THREADED_ENTRIES", 1)
    monkeypatch.setattr(threads_mod, "MAX_THREADS", 5)
    monkeypatch.setattr(threads_mod, "usable_cores", lambda: 5)           # five blocks even on a small machine
    vox5, c5, t5 = PooledPSOG(grid, recs).counts()
    assert t1 == t5 == sum(10 + i for i in range(6))
    assert np.array_equal(vox1, vox5) and c1.dtype == c5.dtype and np.array_equal(c1, c5)
    # and the table is the sum itself: every entry once (the repeated ones added up)
    assert int(c1[:, 1:].sum()) == sum(int(r.counts.sum()) for r in recs)


def test_plain_psog_returns_a_known_plain_reference_without_comparing():
    # optimize's pooled P-SOG is pooled.psog() itself (routes.pooled_psog marks it known_plain): the jackknife's
    # point takes it as it is; another P-SOG of the same content is still checked, a different one refused,
    # and adding a record forgets what was known
    pooled = _four_drive_pool()
    psog = pooled.psog()
    pooled.known_plain(psog)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(np, "array_equal", lambda *a, **k: pytest.fail("compared arrays of a known plain P-SOG"))
        assert pooled.plain_psog(psog) is psog
    twin = pooled.psog()
    assert pooled.plain_psog(twin) is twin                        # equal content: passes the check
    other = PooledPSOG(pooled.grid, pooled.records[:3]).psog()
    got = pooled.plain_psog(other)
    assert got is not other and np.array_equal(got.counts, psog.counts)
    pooled.add(pooled.records[0])
    assert pooled.plain_psog(psog) is not psog                   # the pool changed: psog is no longer it
