"""Intervals over routes (issue 34): their coverage on synthetic pools with a known spread, and that an
interval contains its own estimate.

The synthetic pool: D drives of T subsets over N voxels; in drive d voxel v is class 1 in a
Binomial(T, p_vd) number of subsets, with p_vd ~ Beta around a per-voxel base (the spread between routes).
The statistic is the paper's M-SOG of a rig that covers every voxel: minus the mean entropy of the pooled
probabilities. Its target is the expected score of a pool of D such drives, computed here by Monte Carlo
from 20,000 pools; 200 further pools each give one interval, and the share that covers the target must lie
within three binomial standard deviations of the nominal 0.95.
"""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.grid import Grid
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.uncertainty import Bootstrap, Jackknife, bootstrap_pooled, jackknife_pooled, route_df

N, T, POOLS = 60, 10, 200
GRID = Grid((0, 0, 0), (N, 1, 1), 1.0)
TOLERANCE = 3 * np.sqrt(0.95 * 0.05 / POOLS)


def _draw(rng, D, shift=None):
    base = np.linspace(0.05, 0.6, N)
    conc = 8.0                                       # Beta concentration: the spread between routes
    p = rng.beta(base * conc, (1 - base) * conc, size=(D, N))
    if shift is not None:                            # strata (towns) that differ in their mean
        p = np.clip(p + shift[:, None], 0.0, 1.0)
    return rng.binomial(T, p)


def _entropy(q):
    with np.errstate(divide="ignore", invalid="ignore"):
        return -(np.where(q > 0, q * np.log(q), 0.0) + np.where(q < 1, (1 - q) * np.log(1 - q), 0.0))


def _stat(counts):
    return -_entropy(counts.sum(0) / (T * counts.shape[0])).mean()


def _records(counts):
    out = []
    for d, c in enumerate(counts):
        v = np.flatnonzero(c)
        out.append(DriveRecord(f"d{d}", T, v.astype(np.int64), np.ones(len(v), np.int16), c[v].astype(np.int32)))
    return out


def _score(psog):
    return np.array([-_entropy(psog.probs[:, 1]).sum() / N])


def _coverage(D, strata=None, shift=None, method="jackknife"):
    rng = np.random.default_rng(1)
    target = np.mean([_stat(_draw(rng, D, shift)) for _ in range(20_000)])
    hits = contains = 0
    for r in range(POOLS):
        c = _draw(rng, D, shift)
        pool = PooledPSOG(GRID, _records(c))
        if method == "jackknife":
            iv = jackknife_pooled(pool, _score, strata=strata)
            assert iv.point[0] == pytest.approx(_stat(c), abs=1e-12)     # the pooled score is the statistic
        else:
            pt, smp, _ = bootstrap_pooled(pool, _score, 200, seed=r, strata=strata)
            iv = Bootstrap(["rig"], pt, smp)
        lo, hi = iv.ci[0]
        hits += lo <= target <= hi
        contains += lo <= iv.point[0] <= hi
    return hits / POOLS, contains / POOLS


@pytest.mark.parametrize("D", [4, 8])
def test_jackknife_over_routes_holds_its_nominal_coverage(D):
    cov, contains = _coverage(D)
    assert abs(cov - 0.95) <= TOLERANCE, cov
    assert contains == 1.0


def test_stratified_jackknife_over_towns_holds_its_nominal_coverage():
    # two towns of four routes each, whose voxels differ in their mean occupancy: the towns are the design
    strata = np.repeat([0, 1], 4)
    cov, contains = _coverage(8, strata, np.where(strata == 0, -0.03, 0.03))
    assert abs(cov - 0.95) <= TOLERANCE, cov
    assert contains == 1.0


def test_the_bootstrap_over_routes_fails_the_same_check():
    # the method this replaces: resamples repeat routes, pool fewer distinct ones and score high, so its
    # percentile interval misses the target far more often than 5 % (and sometimes misses its own point)
    cov, contains = _coverage(8, method="bootstrap")
    assert cov < 0.95 - TOLERANCE, cov
    assert contains < 1.0


def test_an_interval_contains_its_own_estimate_and_uses_t_quantiles():
    rng = np.random.default_rng(3)
    pool = PooledPSOG(GRID, _records(_draw(rng, 5)))
    iv = jackknife_pooled(pool, lambda ps: np.concatenate([_score(ps), 2 * _score(ps)]), names=["a", "b"])
    lo, hi = iv.ci.T
    assert np.all(lo < iv.point) and np.all(iv.point < hi)
    assert iv.df == route_df(5) == 4 and iv.unit == "drives" and iv.n_units == 5
    from scipy.stats import t

    assert (hi - iv.point) / iv.se == pytest.approx(t.ppf(0.975, 4), rel=1e-9)


def test_stratified_jackknife_variance_is_the_sum_over_strata():
    # per stratum of a mean: (n_h - 1) / n_h * sum of squared leave-one-out deviations = s_h^2 / n_h
    rng = np.random.default_rng(4)
    x = rng.normal(size=7)
    strata = (0, 0, 0, 1, 1, 1, 1)
    loo = np.empty(7)
    for h in (0, 1):
        idx = [i for i in range(7) if strata[i] == h]
        for i in idx:
            loo[i] = np.mean([x[j] for j in idx if j != i])
    jk = Jackknife(["m"], np.array([0.0]), loo[:, None], strata=strata, df=route_df(7, strata))
    want = sum(np.var(x[[i for i in range(7) if strata[i] == h]], ddof=1) / strata.count(h) for h in (0, 1))
    assert jk.se[0] ** 2 == pytest.approx(want, rel=1e-12)
    assert jk.df == 5
    single = Jackknife(["m"], np.array([0.0]), loo[:1, None], strata=(0,), df=route_df(1, (0,)))
    assert single.se[0] == 0.0 and np.all(np.isnan(single.ci))          # one route per town: no interval
