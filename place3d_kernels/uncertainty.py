"""Resampling drivers: scores of placements on resampled or left-out pools of drives or subsets.

A pooled P-SOG is an estimate from a sample of drives; another sample of routes would give other voxel
probabilities and possibly another order of the placements. The bootstrap resamples the drives with
replacement (each resample: a multiplicity per drive, summing to D, ``resample_multiplicities``), rebuilds
the pooled P-SOG from the per-drive counts (``PooledPSOG.psog(multiplicity)``, sums of sparse counts, no
simulation) and rescores every placement with one batched ``msog_batch`` call; the jackknife leaves each
unit out once instead. A single drive is resampled the same way over its subsets (``subset_records`` gives
one record per subset of k frames).

Here: ``bootstrap_pooled`` / ``jackknife_pooled`` (any score function of a pooled P-SOG),
``bootstrap_drives`` / ``bootstrap_subsets``, ``bootstrap_records`` / ``jackknife_records`` (rigs on a
pool of records; the jackknife's left-out grids come from ``left_out.py``) and
``rig_vs_baselines_intervals`` (an optimised rig against the baselines, the baselines' scores remembered
by ``interval_memo.py``).

What the resampled scores say (the ``Bootstrap`` and ``Jackknife`` classes, intervals, pairwise orders,
"within noise") is ``place3d_kernels.intervals``; its names are re-exported here, so
``from place3d_kernels.uncertainty import Bootstrap`` keeps working.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Callable

import numpy as np

# re-exported: callers import the interval classes and their statistics from here too
from place3d_kernels.intervals import (MIN_SUBSETS, NOISE_LEVEL, Bootstrap, Jackknife, interval_method,
                                       kendall_tau, pairwise, plot_scores, route_df, too_few_subsets,
                                       within_noise)
from place3d_kernels.pooled import PooledPSOG
from place3d_kernels.profiling import section

__all__ = ["Bootstrap", "resample_multiplicities", "bootstrap_pooled", "bootstrap_drives",
           "bootstrap_subsets", "within_noise", "plot_scores", "NOISE_LEVEL", "kendall_tau",
           "bootstrap_records", "pairwise", "rig_vs_baselines_intervals", "Jackknife", "jackknife_records",
           "jackknife_pooled", "route_df", "MIN_SUBSETS", "too_few_subsets", "interval_method"]


def resample_multiplicities(n: int, n_resamples: int, seed: int = 0, strata=None) -> np.ndarray:
    """(R, n) int64: how often each of n units is drawn in each resample (n draws with replacement).

    Args:
        strata: optional (n,) labels; units are then resampled within each stratum (as many draws as the
            stratum has units), so e.g. every resample keeps each town's share of routes: the towns are
            fixed by the study's design, the routes are the random sample.
    """
    if n < 1 or n_resamples < 1:
        raise ValueError(f"need n >= 1 units and n_resamples >= 1, got n={n}, n_resamples={n_resamples}")
    rng = np.random.default_rng(seed)
    if strata is None:
        return rng.multinomial(n, np.full(n, 1.0 / n), size=int(n_resamples)).astype(np.int64)
    strata = np.asarray(strata)
    if strata.shape != (n,):
        raise ValueError(f"strata must have one label per unit ({n}), got shape {strata.shape}")
    out = np.zeros((int(n_resamples), n), dtype=np.int64)
    for s in np.unique(strata):
        idx = np.flatnonzero(strata == s)
        out[:, idx] = rng.multinomial(len(idx), np.full(len(idx), 1.0 / len(idx)), size=int(n_resamples))
    return out


def bootstrap_pooled(pooled: PooledPSOG, score: Callable, n_resamples: int = 200, seed: int = 0,
                     progress: bool = False, strata=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Apply ``score(psog) -> (S,) array`` to the full pool and to R drive resamples.

    Args:
        strata: optional per-drive labels (e.g. the town) to resample within (``resample_multiplicities``).

    Returns:
        point (S,), samples (R, S), multiplicities (R, D).
    """
    mult = resample_multiplicities(len(pooled), n_resamples, seed, strata)
    point = np.asarray(score(pooled.psog()), dtype=np.float64)
    it = mult
    if progress:
        from tqdm import tqdm

        it = tqdm(mult, desc="bootstrap", unit="resample", leave=False)
    samples = np.stack([np.asarray(score(pooled.psog(m)), dtype=np.float64) for m in it])
    return point, samples, mult


def _placement_scorer(lidar, poses: np.ndarray, task: str, occlusion: str, backend) -> Callable:
    from place3d_kernels.metrics import msog_batch

    def score(psog):
        return msog_batch(psog, lidar, poses, occlusion=occlusion, task=task, backend=backend)

    return score


def _poses(placements) -> tuple[list, np.ndarray]:
    if isinstance(placements, dict):
        names = list(placements)
        rows = [getattr(p, "poses", p) for p in placements.values()]
    else:
        rows = [getattr(p, "poses", p) for p in placements]
        names = [getattr(p, "name", f"placement {i}") for i, p in enumerate(placements)]
    return names, np.stack([np.asarray(r, dtype=np.float64) for r in rows])


def bootstrap_drives(pooled: PooledPSOG, lidar, placements, task: str = "seg", occlusion: str = "sog",
                     n_resamples: int = 200, seed: int = 0, backend=None, level: float = 0.95,
                     progress: bool = False, strata=None) -> Bootstrap:
    """Bootstrap over drives of the M-SOG of each placement (one batched call per resample).

    Args:
        pooled: the pooled P-SOG's per-drive records.
        lidar: the rig's ``LidarModel`` (or name).
        placements: {name: Placement or (L, 6) poses} or a list of ``Placement``.
        task, occlusion, backend: as ``msog_batch``.
        n_resamples, seed: R and the resampling seed (results depend on nothing else).
        level: interval coverage.
        strata: optional per-drive labels to resample within (e.g. the town of each drive).
    """
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel

    L = LidarModel.load(lidar) if isinstance(lidar, str) else lidar
    names, poses = _poses(placements)
    scorer = _placement_scorer(L, poses, task, occlusion, get_backend(backend))
    point, samples, _ = bootstrap_pooled(pooled, scorer, n_resamples, seed, progress, strata)
    return Bootstrap(names, point, samples, level, "drives", len(pooled))


def bootstrap_subsets(drive, lidar, placements, settings=None, task: str = "seg", occlusion: str = "sog",
                      n_resamples: int = 200, seed: int = 0, level: float = 0.95) -> Bootstrap:
    """Bootstrap over the subsets (SOGs of k frames) of a single drive.

    The point estimate equals the drive's ordinary P-SOG score. Subsets of one drive overlap in space
    and follow each other in time, so they are not independent draws: this interval is narrower than
    one over routes and says how stable the estimate is within the drive, not across drives.
    """
    from place3d_kernels.pooled import PoolSettings, subset_records

    settings = settings or PoolSettings()
    pooled = PooledPSOG(settings.grid, subset_records(drive, settings))
    b = bootstrap_drives(pooled, lidar, placements, task, occlusion, n_resamples, seed, settings.backend, level)
    b.unit = "subsets"
    return b


def bootstrap_records(records, grid, lidar, placements, tasks=("seg", "det"), occlusion: str = "sog",
                      n_resamples: int = 200, seed: int = 0, backend=None, level: float = 0.95,
                      point: dict | None = None, unit: str = "subsets", progress: bool = False,
                      normalisation: str = "paper", body=None, reference=None) -> dict:
    """{task: Bootstrap} of ``placements`` over resamples of ``records`` (one ``msog_batch`` call over all
    placements per resample and task; the resampled P-SOG is built once per resample for both tasks).

    Args:
        point: optional {task: (P,) scores} used as the point estimates (e.g. the scores already printed,
            so they stay bit-identical); default: the scores on the pool of all records.
        progress: a progress bar over the distinct resamples (stderr).
        body: the ego ``VehicleBody`` the rigs are scored on (as ``msog_batch``; None: no body).
        reference: the scene's P-SOG, used for the point estimates when it is exactly the records' pool
            (``PooledPSOG.plain_psog``), so its weights and device grids are not built again.
    """
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch

    L = LidarModel.load(lidar) if isinstance(lidar, str) else lidar
    b = get_backend(backend)
    names, poses = _poses(placements)
    pooled = PooledPSOG(grid, records)
    mult = resample_multiplicities(len(pooled), n_resamples, seed)
    # a resample's score depends only on its multiplicities: score each distinct one once (with few
    # subsets many resamples repeat, e.g. 2 subsets give only 3 distinct pools)
    uniq, inv = np.unique(mult, axis=0, return_inverse=True)
    scores = {t: np.empty((len(uniq), len(names))) for t in tasks}
    it = uniq
    if progress:
        from tqdm import tqdm

        it = tqdm(uniq, desc="bootstrap", unit="resample", leave=False)
    for r, m in enumerate(it):
        ps = pooled.psog(m)
        for t in tasks:
            scores[t][r] = msog_batch(ps, L, poses, occlusion, t, b, normalisation=normalisation, body=body)
    samples = {t: scores[t][np.asarray(inv).reshape(-1)] for t in tasks}
    out = {}
    for t in tasks:
        pt = point[t] if point is not None else msog_batch(pooled.plain_psog(reference), L, poses, occlusion, t, b,
                                                           normalisation=normalisation, body=body)
        out[t] = Bootstrap(names, np.asarray(pt, dtype=np.float64), samples[t], level, unit, len(pooled))
    return out


#: Threads that build leave-one-out P-SOGs ahead of their scoring (NumPy work that mostly releases the
#: GIL); each one in flight holds a P-SOG (about 100 MB on the default grid).
LEFT_OUT_THREADS = 3


def _left_out_psogs(pooled: PooledPSOG, tasks):
    """The n leave-one-out P-SOGs in order, built up to LEFT_OUT_THREADS ahead on threads, each with its
    weights and stop mask per task computed (the host work of a jackknife step; its scoring stays on the
    caller's thread, which owns the backend)."""
    n = len(pooled)
    pooled.counts(np.ones(n, dtype=np.int64))       # the shared memos, before the threads read them

    def build(i):
        m = np.ones(n, dtype=np.int64)
        m[i] = 0
        ps = pooled.psog(m)
        for t in tasks:
            q = ps.for_task(t)
            q.weights, q.stop_mask                   # noqa: B018 - computed (and cached) here
        return ps

    workers = max(1, min(LEFT_OUT_THREADS, (os.cpu_count() or 1) - 1))
    if workers == 1:
        yield from (build(i) for i in range(n))
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(workers, thread_name_prefix="place3d-jackknife") as ex:
        ahead = [ex.submit(build, i) for i in range(min(workers, n))]
        for i in range(n):
            ps = ahead[i].result()
            if i + workers < n:
                ahead.append(ex.submit(build, i + workers))
            ahead[i] = None                          # the caller holds it; drop ours
            yield ps


def jackknife_records(records, grid, lidar, placements, tasks=("seg", "det"), occlusion: str = "sog",
                      backend=None, level: float = 0.95, point: dict | None = None, unit: str = "subsets",
                      progress: bool = False, normalisation: str = "paper", body=None, reference=None,
                      pool_key=None, strata=None, df=None) -> dict:
    """{task: Jackknife} of ``placements`` leaving each record (subset or drive) out in turn: n rescorings,
    one ``msog_batch`` call over all placements per left-out unit and task (``body``: the ego
    ``VehicleBody`` the rigs are scored on, as ``msog_batch``; ``reference``: as ``bootstrap_records``).
    ``records``: the ``DriveRecord``s, or their ``PooledPSOG`` on ``grid`` (its summed counts reused).

    ``pool_key``: the records' content identity (``subset_records.keyed_subset_records``), or None. With
    one, the prepared left-out grids and the reference's identity check are kept in the process
    (``left_out.HANDLES``), so the next jackknife on the same records patches and uploads nothing.

    ``strata`` and ``df``: as ``Jackknife``'s (the routes' intervals pass the scene of each drive and
    ``route_df``)."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch, msog_tasks

    L = LidarModel.load(lidar) if isinstance(lidar, str) else lidar
    b = get_backend(backend)
    names, poses = _poses(placements)
    # a PooledPSOG passed as it is keeps its summed counts (a pooled command has them from its P-SOG)
    pooled = records if isinstance(records, PooledPSOG) and records.grid == grid else PooledPSOG(
        grid, getattr(records, "records", records))
    n = len(pooled)
    if n < 2:
        raise ValueError(f"the jackknife needs at least 2 units, got {n}")
    # the point first: msog_batch checks the poses before any left-out grid is scored
    point_scores = dict(point) if point is not None else {}
    from place3d_kernels.left_out import HANDLES

    with section("jackknife: point"):
        with section("pooled P-SOG"):
            full = None if point is not None else HANDLES.plain_psog(pooled, reference, pool_key)
        if point is None:
            with section("point scores"):
                point_scores = msog_tasks(full, L, poses, occlusion, tasks, b, normalisation, body)
        del full
    scores = {t: np.empty((n, len(names))) for t in tasks}
    it = range(n)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="jackknife", unit="left-out", leave=False)
    from place3d_kernels.left_out import fused_path, prepared_grids

    if fused_path(L, occlusion, normalisation, body):
        # msog_batch's fused path: each left-out grid patched from the full pool (left_out.py, several times
        # faster) and prepared once; with a pool_key the prepared grids are kept for the next jackknife on these
        # records (or were prepared during the search: prepare_in_background)
        from place3d_kernels.left_out import LeftOutRows
        from place3d_kernels.metrics import msog_on_handles

        # an iterator per task: kept handles, or (not kept) each grid prepared just before its scoring, in one
        # working grid per task where the backend writes grids in place; the tasks share each record's rows
        if not HANDLES.fits(pooled.grid, n):
            pool_key = None                 # too large to keep: one working grid per task, patched in place
        reuse = not HANDLES.will_keep(pool_key)
        with section("jackknife: left-out grid"):
            rows = LeftOutRows.shared(pooled)
        handles = {t: iter(HANDLES.get(pool_key, pooled.grid, t, occlusion, b,
                                       lambda t=t: prepared_grids(pooled, t, occlusion, b, normalisation, reuse, rows),
                                       normalisation=normalisation))
                   for t in tasks}
        for i in it:
            got = [next(handles[t]) for t in tasks]
            with section("jackknife: scoring"):
                # one call for every task: the tasks' grids share the stop mask, so the rays may be walked once
                pairs = [h if isinstance(h, tuple) else (h, None) for h in got]
                for t, s in zip(tasks, msog_on_handles(pooled.grid, pairs, L, poses, b)):
                    scores[t][i] = s
    else:
        left_out = _left_out_psogs(pooled, tasks)
        for i in it:
            with section("jackknife: left-out P-SOG (wait)"):
                ps = next(left_out)
            with section("jackknife: scoring"):
                for t in tasks:
                    scores[t][i] = msog_batch(ps, L, poses, occlusion, t, b, normalisation=normalisation, body=body)
            del ps
        left_out.close()                             # its thread pool, now idle, shuts down
    st = None if strata is None else tuple(strata)
    return {t: Jackknife(names, np.asarray(point_scores[t], dtype=np.float64), scores[t], level, unit, n,
                         strata=st, df=df) for t in tasks}


def jackknife_pooled(pooled: PooledPSOG, score: Callable, strata=None, level: float = 0.95,
                     names=None) -> Jackknife:
    """The routes' interval of ``score(psog) -> (S,)`` on a pooled P-SOG: each drive left out once.

    Why not the bootstrap over drives (``bootstrap_pooled``): a resample drawn with replacement pools
    about 63 % distinct drives, and entropy is concave, so resampled M-SOGs run high and a percentile
    interval can exclude its own point (it did in the 8-route reproduce run). A leave-one-out pool repeats
    no drive; the jackknife variance is conservative on average for any symmetric statistic (Efron and
    Stein, Ann. Statist. 9, 1981), and with t quantiles of n - strata degrees of freedom the interval holds
    its nominal coverage of the expected score of a pool of this many routes
    (tests/test_route_intervals.py, on synthetic pools with a known spread).
    """
    n = len(pooled)
    if n < 2:
        raise ValueError(f"an interval over routes needs at least 2 drives, got {n}")
    point = np.asarray(score(pooled.psog()), dtype=np.float64)
    samples = np.empty((n, point.size))
    for i in range(n):
        m = np.ones(n, dtype=np.int64)
        m[i] = 0
        samples[i] = np.asarray(score(pooled.psog(m)), dtype=np.float64)
    st = None if strata is None else tuple(np.asarray(strata).tolist())
    return Jackknife(list(names) if names is not None else [f"s{i}" for i in range(point.size)], point, samples,
                     level, "drives", n, strata=st, df=route_df(n, strata))


def rig_vs_baselines_intervals(source, lidar, best_poses, baseline_placements, task: str = "seg",
                               occlusion: str = "sog", backend=None, n_resamples: int = 200, seed: int = 0,
                               level: float = 0.95, best_name: str = "best",
                               settings=None, method: str = "bootstrap", normalisation: str = "paper",
                               reference=None, strata=None) -> dict:
    """Interval of an optimised rig and of each baseline, and how often the rig beats each baseline.

    Args:
        source: a ``PSOGSpec`` (resampled over its subsets, records cached as ``spec_subset_records``),
            a ``pooled.Drive`` (over its subsets, with ``settings``) or a ``PooledPSOG`` (over its drives).
        best_poses: (L, 6) poses of the optimised rig.
        baseline_placements: {name: Placement or (L', 6) poses} or a list of ``Placement``.
        task, occlusion, backend, normalisation: as ``msog_batch``; n_resamples, seed, level: the bootstrap's.
        reference: the scene's P-SOG (see ``bootstrap_records``).
        method: ``"bootstrap"`` (resamples with replacement) or ``"jackknife"`` (each unit left out once;
            ``n_resamples`` and ``seed`` unused).

    Returns:
        {"task", "level", "unit", "n_units", "n_resamples",
         "best": {"name", "score", "ci": [lo, hi]},
         "baselines": [{"name", "score", "ci": [lo, hi], "p_best_better": P(best > baseline),
                        "within_noise": bool (P < NOISE_LEVEL)}, ...]}
    """
    from place3d_kernels.interval_memo import IntervalMemo, rig_key
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.pooled import Drive, PoolSettings, subset_records
    from place3d_kernels.subset_records import keyed_subset_records, subset_records_path

    names, poses = _poses(baseline_placements)
    best = np.asarray(best_poses, dtype=np.float64)
    if best.ndim != 2 or best.shape[1] != 6:
        raise ValueError(f"best_poses must be (L, 6) poses, got shape {best.shape}")
    placements = {best_name: best, **{n: p for n, p in zip(names, poses)}}
    records_path = pool_key = None
    if isinstance(source, PooledPSOG):
        pooled, unit = source, "drives"
    elif isinstance(source, Drive):
        settings = settings or PoolSettings()
        pooled, unit = PooledPSOG(settings.grid, subset_records(source, settings)), "subsets"
    else:
        records, pool_key = keyed_subset_records(source, backend)
        pooled, unit = PooledPSOG(source.grid.grid(), records), "subsets"
        records_path = subset_records_path(source)[0]
    if method not in ("bootstrap", "jackknife"):
        raise ValueError(f"method must be 'bootstrap' or 'jackknife', got {method!r}")
    L = LidarModel.load(lidar) if isinstance(lidar, str) else lidar

    def scores(rigs):
        if method == "jackknife":
            routes = unit == "drives"       # over routes: stratified by scene, t quantiles (jackknife_pooled)
            return jackknife_records(pooled, pooled.grid, L, rigs, (task,), occlusion, backend, level,
                                     unit=unit, normalisation=normalisation, reference=reference,
                                     pool_key=pool_key, strata=strata if routes else None,
                                     df=route_df(len(pooled), strata) if routes else None)[task]
        return bootstrap_records(pooled.records, pooled.grid, L, rigs, (task,), occlusion, n_resamples, seed,
                                 backend, level, unit=unit, normalisation=normalisation, reference=reference)[task]

    # The baselines' resampled scores depend on the scene's records, not on the search: remembered on disk
    # (interval_memo), so a warm run rescores only the optimised rig.
    memo = IntervalMemo(records_path) if records_path is not None else None
    setting = dict(task=task, occlusion=occlusion, normalisation=normalisation, body=None, method=method,
                   resamples=int(n_resamples) if method == "bootstrap" else None,
                   seed=int(seed) if method == "bootstrap" else None)
    keys = [rig_key(L, p, **setting) for p in poses] if memo is not None else []
    known = [memo.get(k) for k in keys]
    if memo is not None and all(k is not None for k in known):
        own = scores({best_name: best})
        boot = dataclasses.replace(own, names=[best_name, *names],
                                   point=np.concatenate([own.point, [k[0] for k in known]]),
                                   samples=np.column_stack([own.samples, *[k[1] for k in known]]))
    else:
        boot = scores(placements)
        if memo is not None:
            for i, k in enumerate(keys):
                memo.put(k, boot.point[i + 1], boot.samples[:, i + 1])
            memo.save()
    if method == "jackknife":
        n_resamples = boot.n_units
    ci, f = boot.ci, boot.order_freq
    rows = [{"name": n, "score": float(boot.point[i]), "ci": ci[i].tolist(),
             "p_best_better": round(float(f[0, i]), 4), "within_noise": bool(f[0, i] < NOISE_LEVEL)}
            for i, n in enumerate(boot.names) if i > 0]
    return {"task": task, "method": method, "level": level, "unit": unit, "n_units": boot.n_units,
            "n_resamples": int(n_resamples),
            "best": {"name": best_name, "score": float(boot.point[0]), "ci": ci[0].tolist()}, "baselines": rows}
