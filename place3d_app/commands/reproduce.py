"""``place3d reproduce``: the paper's M-SOG study of its eight placements, pooled, with intervals.

For segmentation and detection it scores the seven baselines, the task's optimised placement ("ours")
and any of the user's rigs (``--placements``) on a P-SOG pooled over the four CARLA towns (``--towns``) x
``--routes`` routes each (or the seeds ``--route-seeds`` names), gives every score a 95 % interval over
routes (a jackknife: each route left out once, stratified by town, t quantiles;
``uncertainty.jackknife_pooled``), the probability that each pairwise order holds, and Kendall's tau of the
order of the paper's eight against the paper's Table 1 M-SOG and against the paper's downstream results
(``paper_results``). ``convergence`` shows whether the order still moves with more routes: tau between the
P-SOG of N routes per town and that of 2N routes.

Where the time goes (``place3d --profile reproduce``): with the process executor (``--executor auto`` on a
machine of several cores) the workers build the drives, two routes of one town a task
(``pooled.scene_groups``), then score the convergence table's pools while this process runs the jackknife;
the whole pool's scores are the jackknife's point, not scored again. The jackknife is one pass for both tasks
over the union of their rigs (``jackknife_placements``). A drive already in the P-SOG cache is read, its scene
not built. The figure is drawn into memory on a thread once the intervals are known, and written after the
JSON. The console script starts the workers' forkserver before it imports the package
(``place3d_app.forkserver.start_early``).

Output (``--output``, default ``bench/results/reproduce-<date>/``): ``reproduce.json`` (keys:
``settings``, ``machine``, ``time_utc``, ``seconds`` (pool, jackknife, convergence: what this process
still spent on it after the jackknife, total), ``drives``, ``tasks`` -> seg/det -> placements,
msog, ci_low, ci_high, se, bias, df, rank, paper_msog, paper_rank, downstream, tau_paper,
tau_paper_loo_range, tau_downstream, tau_downstream_loo_range, order_freq, within_noise, samples (the
leave-one-route-out scores); ``convergence``) and ``reproduce.png``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import sys
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from place3d_kernels import paper_results as paper
from place3d_kernels.pooled import Drive, PooledPSOG, PoolSettings, build_pooled
from place3d_kernels.profiling import section
from place3d_kernels.uncertainty import Jackknife, jackknife_pooled, kendall_tau, plot_scores

__all__ = ["reproduce", "convergence", "convergence_ranges", "range_pool", "submit_ranges", "paper_poses",
           "placement_poses", "placement_scorer", "pool_scorer", "jackknife_placements", "det_view", "resolve_town",
           "DEFAULT_TOWNS", "DET_VARIANTS", "add_arguments", "run", "machine_info", "write_outputs", "draw_figure"]

#: The paper's maps (Sec. 4 "Data Generation": Towns 1, 3, 4 and 6 of CARLA 0.9.10).
DEFAULT_TOWNS = ("Town01", "Town03", "Town04", "Town06")
#: Detection variants of the P-SOG: the paper keeps "car" and merges every other class (Sec. 4, "Surrogate
#: Metric of SOG"); the alternative also keeps pedestrians, the detection benchmark's other instance class.
DET_VARIANTS = ("vehicle", "vehicle+pedestrian")
TASKS = ("seg", "det")


# ---------------------------------------------------------------------------------------- inputs
def _opendrive_dirs(extra=None) -> list[Path]:
    dirs = [Path(extra)] if extra else []
    if os.environ.get("PLACE3D_OPENDRIVE_DIR"):
        dirs.append(Path(os.environ["PLACE3D_OPENDRIVE_DIR"]))
    dirs += [Path("data/opendrive")]
    return dirs


def resolve_town(name: str, opendrive_dir=None) -> str:
    """A scene string for ``Drive``: 'town', 'opendrive:PATH', a .xodr path, or a map name (Town01)
    looked up in ``opendrive_dir``, ``$PLACE3D_OPENDRIVE_DIR``, ./data/opendrive, then the shipped CARLA maps."""
    if name == "town" or name.startswith("opendrive:"):
        return name
    if name.endswith(".xodr"):
        if not Path(name).exists():
            raise FileNotFoundError(f"OpenDRIVE file {name} not found")
        return f"opendrive:{Path(name).resolve()}"
    for d in _opendrive_dirs(opendrive_dir):
        p = d / f"{name}.xodr"
        if p.exists():
            return f"opendrive:{p.resolve()}"
    from place3d_kernels.data import CARLA_TOWNS, opendrive_path

    if name in CARLA_TOWNS:  # the four maps ship with the package
        return f"opendrive:{opendrive_path(name)}"
    raise FileNotFoundError(f"map {name!r}: no {name}.xodr in {[str(d) for d in _opendrive_dirs(opendrive_dir)]}; "
                            f"pass --opendrive-dir DIR or set PLACE3D_OPENDRIVE_DIR (CARLA's maps are .xodr files)")


def paper_poses(task: str, roll_units: str = "rad") -> np.ndarray:
    """(8, 4, 6) poses of the paper's eight placements for a task, in ``paper_results.PLACEMENTS`` order.

    ``roll_units="deg"`` reads the paper's roll values as degrees (as CARLA's ``carla.Rotation`` would take
    them, see docs/assumptions.md): roll x pi / 180.
    """
    from place3d_kernels.placement import Placement

    if roll_units not in ("rad", "deg"):
        raise ValueError(f"roll_units must be 'rad' or 'deg', got {roll_units!r}")
    names = [paper.OURS[task] if n == "ours" else n for n in paper.PLACEMENTS]
    poses = np.stack([Placement.load(n).poses for n in names])
    if roll_units == "deg":
        poses = poses.copy()
        poses[..., 3] *= math.pi / 180.0
    return poses


def det_view(psog, variant: str = "vehicle"):
    """The detection P-SOG: 'vehicle' = the package's (empty, vehicle, other) = ``psog.detection()``;
    'vehicle+pedestrian' = (empty, vehicle, pedestrian, other)."""
    from place3d_kernels.classes import CLASSES
    from place3d_kernels.sog import PSOG

    if variant == "vehicle":
        return psog.detection()
    if variant != "vehicle+pedestrian":
        raise ValueError(f"det variant must be one of {DET_VARIANTS}, got {variant!r}")
    p = psog.probs
    veh, ped = p[:, CLASSES.index("vehicle")], p[:, CLASSES.index("pedestrian")]
    other = np.clip(1.0 - p[:, 0] - veh - ped, 0.0, 1.0)
    return PSOG(psog.grid, psog.voxels, np.stack([p[:, 0], veh, ped, other], axis=1),
                ("empty", "vehicle", "pedestrian", "other"), psog.n_subsets)


def placement_poses(roll_units: str, extra=None) -> dict:
    """{"seg": (P, L, 6), "det": (P, L, 6)}: each task's eight paper placements, then the ``extra`` ones
    ((E, L, 6) poses, the user's rigs; P = 8 + E)."""
    seg_poses, det_poses = paper_poses("seg", roll_units), paper_poses("det", roll_units)
    if extra is not None and len(extra):
        extra = np.asarray(extra, dtype=np.float64)
        if extra.shape[1:] != seg_poses.shape[1:]:
            raise ValueError(f"--placements: rigs of {extra.shape[1]} LiDARs cannot be scored in one batch with the "
                             f"paper's {seg_poses.shape[1]}-LiDAR rigs")
        seg_poses, det_poses = np.concatenate([seg_poses, extra]), np.concatenate([det_poses, extra])
    return {"seg": seg_poses, "det": det_poses}


def placement_scorer(lidar, occlusion: str, backend, roll_units: str, det_variant: str, extra=None):
    """score(psog) -> (2 P,) seg scores of the placements of ``placement_poses(roll_units, extra)``, then
    their det scores."""
    from place3d_kernels.metrics import msog_batch

    poses = placement_poses(roll_units, extra)

    def score(psog):
        seg = msog_batch(psog, lidar, poses["seg"], occlusion=occlusion, task="seg", backend=backend)
        # a det view built here is scored as a plain P-SOG (task "seg" = its own channels as given)
        det = msog_batch(det_view(psog, det_variant), lidar, poses["det"], occlusion=occlusion, task="seg",
                         backend=backend)
        return np.concatenate([seg, det])

    return score


def pool_scorer(lidar, occlusion: str, backend, roll_units: str, det_variant: str, extra=None):
    """score(pool) -> (2 P,): what ``placement_scorer(...)(pool.psog())`` gives for a ``PooledPSOG``.

    Where the metric allows it (``left_out.fused_path`` and the package's own detection view), each task's
    weights and stop mask come from the pool's count rows in blocks (``left_out.LeftOutGrids.dense_base`` at
    the pool's own T) and only the rigs are launched on them (``metrics.msog_on_grid``): no (M, K)
    probabilities, detection view or entropies of the whole pool at once. On a backend that makes a P-SOG's
    fields from its count rows itself (``fields_on_device``: Warp on CUDA, OpenCL GPUs with doubles) the
    pool's P-SOG is scored as it is instead: its rows are sent once and made into fields there
    (``PSOG.handle``), with no host pass over them and no dense grid sent. The scores are the same to the last bit (tests/test_pooled.py)."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out import LeftOutGrids, fused_path
    from place3d_kernels.metrics import msog_on_grid

    b = get_backend(backend)
    if det_variant != "vehicle" or not fused_path(lidar, occlusion) or getattr(b, "fields_on_device", False):
        score = placement_scorer(lidar, occlusion, b, roll_units, det_variant, extra)
        return lambda pool: score(pool.psog())
    poses = placement_poses(roll_units, extra)

    def score_pool(pool):
        out = []
        for t in TASKS:
            grids = LeftOutGrids(pool, t)          # the pool's counts, summed once for both tasks
            w, stop = grids.dense_base(grids.T)
            out.append(msog_on_grid(pool.grid, w, stop if occlusion == "sog" else None, lidar, poses[t], b))
        return np.concatenate(out)

    return score_pool


def jackknife_placements(pooled: PooledPSOG, lidar, occlusion: str, backend, roll_units: str, det_variant: str,
                         extra=None, strata=None) -> Jackknife:
    """Each drive left out once: what ``jackknife_pooled(pooled, placement_scorer(...), strata)`` gives,
    (n, 2 P) seg then det scores.

    Where the metric allows it (``left_out.fused_path`` and the package's own detection view), each
    left-out grid is patched from the full pool and only the rigs are launched (``jackknife_records``),
    instead of n whole P-SOGs rebuilt and rescored; the scores are the same to the last bit
    (tests/test_pooled.py)."""
    from place3d_kernels.left_out import fused_path
    from place3d_kernels.uncertainty import jackknife_records, route_df

    if det_variant != "vehicle" or not fused_path(lidar, occlusion):
        return jackknife_pooled(pooled, placement_scorer(lidar, occlusion, backend, roll_units, det_variant, extra),
                                strata=strata)
    poses = placement_poses(roll_units, extra)
    df = route_df(len(pooled), strata)
    # one jackknife for both tasks over the union of their rigs (the paper's det rigs are its seg rigs but
    # "ours"): each left-out grid is patched once for both tasks from the same rows, and a backend that walks
    # the rays once for grids sharing a stop mask (Backend.score_placements_many) does so; a rig's score is an
    # integer sum of its own covered voxels' weights, so it does not depend on the rigs scored beside it
    column, rigs, cols = {}, [], {t: [] for t in TASKS}     # rigs told apart by their bits
    for t in TASKS:
        for p in poses[t]:
            at = column.setdefault(np.ascontiguousarray(p, dtype=np.float64).tobytes(), len(rigs))
            if at == len(rigs):
                rigs.append(p)
            cols[t].append(at)
    jk = jackknife_records(pooled, pooled.grid, lidar, {f"r{i}": p for i, p in enumerate(rigs)}, TASKS,
                           occlusion, backend, unit="drives", strata=strata, df=df)
    return Jackknife([f"s{i}" for i in range(sum(len(c) for c in cols.values()))],
                     np.concatenate([jk[t].point[cols[t]] for t in TASKS]),
                     np.column_stack([jk[t].samples[:, cols[t]] for t in TASKS]),
                     jk[TASKS[0]].level, "drives", len(pooled),
                     strata=None if strata is None else tuple(np.asarray(strata).tolist()), df=df)


def machine_info(backend_name: str | None = None) -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import scipy

    return {"node": platform.node(), "platform": platform.platform(), "cpu": cpu, "cpu_count": os.cpu_count(),
            "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "backend": backend_name}


# ---------------------------------------------------------------------------------------- study
def _task_table(task: str, boot: Jackknife) -> dict:
    """One task's table. The paper's columns and the taus use the paper's eight placements (the first
    eight); the user's rigs (``--placements``) follow them, ranked among all."""
    ref, down = np.array(paper.paper_msog(task)), np.array(paper.downstream(task))
    pt = boot.point
    ci = boot.ci
    P = len(pt)
    # tau of every leave-one-route-out pool: how far the agreement moves when one route goes (a range,
    # not a confidence interval: tau is a step function of the scores)
    taus_p = np.array([kendall_tau(s[:8], ref) for s in boot.samples])
    taus_d = np.array([kendall_tau(s[:8], down) for s in boot.samples])

    def rng(x):
        return [float(np.nanmin(x)), float(np.nanmax(x))] if np.any(np.isfinite(x)) else [None, None]

    def pad(v):
        return list(v) + [None] * (P - 8)

    rank = (-pt).argsort().argsort() + 1
    prank = (-ref).argsort().argsort() + 1
    return {"placements": list(boot.names), "ours_is": paper.OURS[task], "msog": pt.tolist(),
            "ci_low": ci[:, 0].tolist(), "ci_high": ci[:, 1].tolist(), "se": boot.se.tolist(),
            "bias": boot.bias.tolist(), "df": boot.df,
            "rank": rank.tolist(), "paper_msog_1e-6": pad(ref.tolist()), "paper_rank": pad(prank.tolist()),
            "downstream": pad(round(v, 4) for v in down.tolist()),
            "downstream_metric": "mean clean mIoU (%) of 4 models" if task == "seg" else
                                 "mean clean car mAP (%) of 4 models",
            "tau_paper": kendall_tau(pt[:8], ref), "tau_paper_loo_range": rng(taus_p),
            "tau_downstream": kendall_tau(pt[:8], down), "tau_downstream_loo_range": rng(taus_d),
            "paper_tau_msog_vs_downstream": kendall_tau(ref, down),
            "order_freq": np.round(boot.order_freq, 4).tolist(),
            "within_noise": [list(p) for p in boot.within_noise()],
            "samples": boot.samples.tolist()}        # (drives, P) leave-one-route-out scores


def _ns(R: int, ns=None) -> list[int]:
    if ns is None:
        ns, n = [], 1
        while 2 * n <= R:
            ns.append(n)
            n *= 2
    for n in ns:
        if 2 * n > R:
            raise ValueError(f"convergence N={n} needs {2 * n} routes per town, only {R} were built")
    return list(ns)


def convergence_ranges(routes_of: list[int], ns=None) -> list[tuple[int, int]]:
    """The route ranges [lo, hi) whose pools ``convergence`` scores, each once, the whole pool (0, R) last."""
    R = max(routes_of) + 1
    out: list = []
    for n in _ns(R, ns):
        out += [r for r in ((0, n), (n, 2 * n), (0, 2 * n)) if r not in out]
    return sorted(out, key=lambda r: r == (0, R))


def range_pool(pooled: PooledPSOG, routes_of: list[int], lo: int, hi: int) -> PooledPSOG:
    """The pool of the records whose route index is in [lo, hi), in record order."""
    r = np.asarray(routes_of)
    return pooled.subset(np.flatnonzero((r >= lo) & (r < hi)))


def convergence(pooled: PooledPSOG, routes_of: list[int], score=None, ns=None, known=None,
                score_pool=None) -> list[dict]:
    """Kendall tau between the orders from N and 2N routes per town, as N doubles.

    Args:
        pooled: records of all drives; ``routes_of[i]`` is the route index (seed) of record i.
        score: ``score(psog) -> (2 P,)`` (seg then det scores, as in ``reproduce``).
        ns: the N to try (default 1, 2, 4, ... while 2N <= routes).
        known: {(lo, hi): (2 P,) scores} of route ranges scored already by the same scorer (the jackknife's
            point is the whole pool's, (0, R); ``reproduce`` scores the others in its worker processes while
            the jackknife runs); the others are scored here.
        score_pool: ``score_pool(PooledPSOG) -> (2 P,)`` instead of ``score(pool.psog())`` (``pool_scorer``).

    Returns:
        rows {n, tau_seg, tau_det (N vs 2N, nested: the 2N pool contains the N pool), tau_seg_disjoint,
        tau_det_disjoint (routes [0, N) vs [N, 2N)), tau_seg_paper and tau_det_paper of the 2N pool}.
    """
    R = max(routes_of) + 1          # routes_of: the route's index (0 .. R-1) in the run's seed list
    ns = _ns(R, ns)
    if score_pool is None:
        if score is None:
            raise ValueError("convergence needs score or score_pool")
        score_pool = lambda pool: score(pool.psog())      # noqa: E731
    cache = {k: np.asarray(v) for k, v in (known or {}).items()}

    def scores(lo, hi):
        if (lo, hi) not in cache:
            cache[(lo, hi)] = np.asarray(score_pool(range_pool(pooled, routes_of, lo, hi)))
        return cache[(lo, hi)]

    rows = []
    for n in ns:
        a, b, c = scores(0, n), scores(0, 2 * n), scores(n, 2 * n)
        P = len(a) // 2
        rows.append({"n": n, "two_n": 2 * n,
                     "tau_seg": kendall_tau(a[:P], b[:P]), "tau_det": kendall_tau(a[P:], b[P:]),
                     "tau_seg_disjoint": kendall_tau(a[:P], c[:P]), "tau_det_disjoint": kendall_tau(a[P:], c[P:]),
                     "tau_seg_paper": kendall_tau(b[:8], paper.paper_msog("seg")),
                     "tau_det_paper": kendall_tau(b[P:P + 8], paper.paper_msog("det"))})
    return rows


def _import_later_modules() -> None:
    # SciPy's stats (Kendall's tau) and Matplotlib take a second or more to import on a busy machine; the
    # import lock makes the tables and the plot wait for an import still under way instead of repeating it
    try:
        import scipy.stats  # noqa: F401

        import matplotlib

        matplotlib.use("Agg")       # as intervals.plot_scores does, before pyplot
        import matplotlib.pyplot  # noqa: F401
    except Exception:  # noqa: BLE001 - a missing or broken module fails where it is used, with its message
        pass


def _range_scores(t) -> np.ndarray:
    """A worker's task: the scores of one route range's pool (``pool_scorer``)."""
    records, grid, lidar, occlusion, backend, roll_units, det_variant, extra = t
    pool = PooledPSOG(grid, records)
    return pool_scorer(lidar, occlusion, backend, roll_units, det_variant, extra)(pool)


def submit_ranges(executor, pooled: PooledPSOG, routes_of: list[int], lidar, occlusion: str, backend: str,
                  roll_units: str, det_variant: str, extra=None) -> dict:
    """{(lo, hi): Future of its scores} for every range of ``convergence_ranges`` but the whole pool (the
    jackknife's point), each scored by ``pool_scorer`` on a worker of ``executor`` (one with ``submit``: the
    process executor) while this process goes on."""
    R = max(routes_of) + 1
    # the widest ranges first: their records (a pickle of some 100 MB each for half of 32 drives) are sent
    # first, and their pools, the largest to sum and score, start first
    ranges = sorted((r for r in convergence_ranges(routes_of) if r != (0, R)), key=lambda r: r[0] - r[1])
    return {(lo, hi): executor.submit(_range_scores, (range_pool(pooled, routes_of, lo, hi).records, pooled.grid,
                                                      lidar, occlusion, backend, roll_units, det_variant, extra))
            for lo, hi in ranges}


def reproduce(towns=DEFAULT_TOWNS, routes: int = 4, frames: int = 40, voxel_size: float | None = None,
              frames_per_subset: int | None = None, occlusion: str = "sog", rig_lidar: str = "place3d_16ch",
              collection_lidar: str = "collection_64ch", roll_units: str = "rad", det_variant: str = "vehicle",
              backend=None, executor=None, opendrive_dir=None, with_convergence: bool = True, cache=None,
              progress: bool = False, route_seeds=None, placements=(), roi=None, draw_ahead: bool = False) -> dict:
    """Run the study; returns the JSON-able result (see the module docstring for its keys).

    ``route_seeds``: the seeds of the routes (default 0 .. routes-1); ``placements``: the user's rigs
    (names or TOML paths), scored beside the paper's eight; ``roi``: the ROI box (``grid.roi_bounds``:
    None for the default, 3 sizes or 6 corners in metres); ``draw_ahead``: draw the intervals' figure
    (``draw_figure``) on a thread while the convergence table is finished, into memory (the result's
    ``_figure``: a ``Future`` of the PNG's bytes, which ``write_outputs`` writes; nothing is written before)."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.placement import Placement

    t0 = time.perf_counter()
    seeds = list(range(routes)) if route_seeds is None else [int(s) for s in route_seeds]
    routes = len(seeds)
    if routes < 1 or frames < 1:
        raise ValueError(f"routes and frames must be >= 1, got routes={routes}, frames={frames}")
    if routes < 2:
        raise ValueError("an interval over routes needs at least 2 routes per town (--routes 2 or more)")
    extra = [Placement.load(p) for p in placements]
    names = list(paper.PLACEMENTS) + [pl.name or Path(str(p)).stem for pl, p in zip(extra, placements)]
    if len(set(names)) != len(names):
        raise ValueError(f"--placements: names must differ from each other and from the paper's {list(paper.PLACEMENTS)}")
    if det_variant not in DET_VARIANTS:
        raise ValueError(f"det_variant must be one of {DET_VARIANTS}, got {det_variant!r}")
    with section("setup: backend"):
        b = get_backend(backend)
    scenes = [resolve_town(t, opendrive_dir) for t in towns]
    drives, routes_of, town_of = [], [], []
    for r, seed_r in enumerate(seeds):         # route-major, so a partial pool still spans every town
        for i, s in enumerate(scenes):
            drives.append(Drive(s, seed=seed_r, frames=frames))
            routes_of.append(r)
            town_of.append(i)
    settings = PoolSettings(voxel_size, collection_lidar, frames_per_subset, b.name, cache, roi)
    from place3d_app.commands.common import check_pool_roi

    check_pool_roi(roi, voxel_size, {f"{t} placements": p for t, p in
                                     placement_poses("rad", [pl.poses for pl in extra] or None).items()})
    t1 = time.perf_counter()
    with section("pool: drives"):
        # this process waits for the drives; meanwhile it imports what the tables and the plot need
        threading.Thread(target=_import_later_modules, daemon=True, name="place3d-imports").start()
        pooled = build_pooled(drives, settings, executor=executor, progress=progress)
    t_pool = time.perf_counter() - t1
    lidar = LidarModel.load(rig_lidar)
    extra_poses = np.stack([pl.poses for pl in extra]) if extra else None
    pending = {}
    if with_convergence and getattr(executor, "kind", None) == "process":
        # the workers, their backend ready, score the convergence table's pools while this process runs the
        # jackknife (the two share nothing but the records)
        with section("convergence: submit"):
            pending = submit_ranges(executor, pooled, routes_of, lidar, occlusion, b.name, roll_units,
                                    det_variant, extra_poses)
    elif getattr(executor, "kind", None) == "process":
        executor.shutdown(wait=False)       # every drive is built: the workers exit while the jackknife runs
    t1 = time.perf_counter()
    # each route left out once, stratified by town: the four towns are the study's design, the routes its
    # sample (uncertainty.jackknife_pooled: the bootstrap's resamples repeat routes and score high)
    jk = jackknife_placements(pooled, lidar, occlusion, b, roll_units, det_variant, extra_poses, strata=town_of)
    t_boot = time.perf_counter() - t1
    P = len(names)
    boots = {task: dataclasses.replace(jk, names=names, point=jk.point[i * P:(i + 1) * P],
                                       samples=jk.samples[:, i * P:(i + 1) * P]) for i, task in enumerate(TASKS)}
    settings_d = {"towns": list(towns), "routes": routes, "route_seeds": seeds, "frames": frames,
                  **settings.to_dict(), "grid": settings.grid.to_dict(), "occlusion": occlusion,
                  "rig_lidar": rig_lidar, "roll_units": roll_units, "det_variant": det_variant,
                  "placements": [str(p) for p in placements],
                  "interval": "jackknife over routes, each left out once, stratified by town; point +- t se "
                              f"({jk.df} df)",
                  "executor": getattr(executor, "kind", "local"), "n_subsets_total": pooled.n_subsets}
    drawing = None
    if draw_ahead:
        # the figure shows the intervals alone (about 0.6 s of Matplotlib on the H200 host): drawn into memory
        # while this process mostly waits for the workers' convergence scores; written with the JSON
        from concurrent.futures import ThreadPoolExecutor

        one = ThreadPoolExecutor(1, thread_name_prefix="place3d-figure")
        drawing = one.submit(draw_figure, boots, settings_d, len(drives))
        one.shutdown(wait=False)                # its thread ends with the figure
    t1 = time.perf_counter()
    with section("convergence"):
        conv = []
        if with_convergence:
            with section("convergence: wait"):
                known = {r: f.result() for r, f in pending.items()}
            if pending:
                executor.shutdown(wait=False)
            known[(0, max(routes_of) + 1)] = jk.point      # the whole pool: the jackknife scored it
            conv = convergence(pooled, routes_of, known=known,
                               score_pool=pool_scorer(lidar, occlusion, b, roll_units, det_variant, extra_poses))
    t_conv = time.perf_counter() - t1
    with section("tables"):
        tables = {t: _task_table(t, boots[t]) for t in TASKS}
        machine = machine_info(b.name)
    return {"settings": settings_d, "machine": machine,
            "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "seconds": {"pool": round(t_pool, 2), "jackknife": round(t_boot, 2), "convergence": round(t_conv, 2),
                        "total": round(time.perf_counter() - t0, 2)},
            "drives": pooled.labels, "tasks": tables,
            "convergence": conv, "_boots": boots, "_figure": drawing}


# ---------------------------------------------------------------------------------------- output
def format_report(res: dict) -> str:
    s = res["settings"]
    lines = [f"Pooled M-SOG over {len(res['drives'])} drives ({len(s['towns'])} towns x {s['routes']} routes, "
             f"route seeds {_seeds_text(s['route_seeds'])}, {s['frames']} frames, T = {s['n_subsets_total']} subsets), "
             f"voxel {s['voxel_size']} m, k = {s['frames_per_subset']}, occlusion {s['occlusion']}, roll in "
             f"{s['roll_units']}, det = {s['det_variant']}; 95 % intervals: {s['interval']}. Higher is better."]
    for task, t in res["tasks"].items():
        lines.append("")
        lines.append(f"[{task}]  'ours' = {t['ours_is']}; downstream = {t['downstream_metric']}")
        lines.append(f"{'rank':>4} {'placement':13s} {'M-SOG':>10s} {'95 % interval':>23s}  {'paper rank':>10s} "
                     f"{'paper x1e-6':>11s} {'downstream':>10s}")
        def opt(v, fmt):
            return f"{'-':>{len(format(0.0, fmt))}s}" if v is None else format(v, fmt)

        for i in np.argsort(t["rank"]):
            lines.append(f"{t['rank'][i]:>4} {t['placements'][i]:13s} {t['msog'][i]:10.5f} "
                         f"[{t['ci_low'][i]:9.5f}, {t['ci_high'][i]:9.5f}]  {opt(t['paper_rank'][i], '>10')} "
                         f"{opt(t['paper_msog_1e-6'][i], '11.2f')} {opt(t['downstream'][i], '10.2f')}")

        def ci(c):
            return "n/a" if c[0] is None else f"[{c[0]:+.2f}, {c[1]:+.2f}]"

        lines.append(f"Kendall tau (paper's eight) vs paper M-SOG: {t['tau_paper']:+.3f} (leave-one-route-out range "
                     f"{ci(t['tau_paper_loo_range'])});  vs downstream: {t['tau_downstream']:+.3f} "
                     f"({ci(t['tau_downstream_loo_range'])})  (paper's own M-SOG vs downstream: "
                     f"{t['paper_tau_msog_vs_downstream']:+.3f})")
        noise = ", ".join(f"{a}>{b} ({f:.2f})" for a, b, f in t["within_noise"]) or "none"
        lines.append(f"within noise (P(order holds) < 0.95, from the jackknife se of the difference): {noise}")
    if res["convergence"]:
        lines.append("")
        lines.append("Convergence: Kendall tau of the order from N routes/town vs 2N (nested) and vs routes N..2N-1 "
                     "(disjoint); tau of the 2N pool vs the paper")
        lines.append(f"{'N':>3} {'2N':>3} {'seg N-2N':>9} {'det N-2N':>9} {'seg disj':>9} {'det disj':>9} "
                     f"{'seg paper':>9} {'det paper':>9}")
        for r in res["convergence"]:
            lines.append(f"{r['n']:>3} {r['two_n']:>3} {r['tau_seg']:9.3f} {r['tau_det']:9.3f} "
                         f"{r['tau_seg_disjoint']:9.3f} {r['tau_det_disjoint']:9.3f} {r['tau_seg_paper']:9.3f} "
                         f"{r['tau_det_paper']:9.3f}")
    lines.append(f"{res['seconds']['total']:.1f} s (pool {res['seconds']['pool']:.1f} s, jackknife "
                 f"{res['seconds']['jackknife']:.1f} s) on {res['machine']['cpu']}, backend {res['machine']['backend']}")
    return "\n".join(lines)


def _seeds_text(seeds) -> str:
    if len(seeds) > 2 and list(seeds) == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(str(s) for s in seeds)


def draw_figure(boots: dict, settings: dict, n_drives: int) -> bytes:
    """``reproduce.png``'s bytes: each task's scores with their intervals beside the paper's Table 1 M-SOG."""
    import io

    panels = {f"{t} ({'ours = ' + paper.OURS[t]})": boots[t] for t in TASKS}
    # the paper's values for its eight; the user's rigs (--placements) have none
    ref = {f"{t} ({'ours = ' + paper.OURS[t]})": list(paper.paper_msog(t)) + [np.nan] * (len(boots[t].names) - 8)
           for t in TASKS}
    buf = io.BytesIO()
    with section("output: figure"):
        plot_scores(panels, buf, title=f"Pooled M-SOG, {n_drives} drives ({len(settings['towns'])} towns x "
                    f"{settings['routes']} routes), {settings['voxel_size']} m voxels", reference=ref,
                    reference_label="paper Table 1 M-SOG [x 1e-6 nats/voxel]")
    return buf.getvalue()


def write_outputs(res: dict, out) -> dict:
    """reproduce.json and reproduce.png into folder ``out``, each written atomically, the JSON first (the figure
    drawn ahead, ``reproduce(draw_ahead=True)``, is waited for; its error, if it failed, is raised once the JSON
    is written); returns their paths."""
    from place3d_kernels.atomic import atomic_write, atomic_write_text

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    js = out / "reproduce.json"
    with section("output: json"):
        atomic_write_text(js, json.dumps({k: v for k, v in res.items() if not k.startswith("_")}, indent=1))
    png = out / "reproduce.png"
    drawing = res.get("_figure")
    if drawing is not None:
        with section("output: figure (wait)"):
            data = drawing.result()
    else:
        data = draw_figure(res["_boots"], res["settings"], len(res["drives"]))
    with section("output: png"):
        atomic_write(png, data)
    return {"json": str(js), "png": str(png)}


def add_arguments(p) -> None:
    from place3d_app.executors import add_executor_arguments

    p.add_argument("--towns", nargs="+", default=list(DEFAULT_TOWNS),
                   help="maps: CARLA map names (Town01 ...), .xodr paths, or 'town' (default: Town01 Town03 Town04 Town06)")
    p.add_argument("--opendrive-dir", default=None, help="folder of the .xodr maps (default: $PLACE3D_OPENDRIVE_DIR, "
                                                         "./data/opendrive, then the shipped CARLA maps)")
    p.add_argument("--routes", type=int, default=4, help="routes (seeds 0..N-1) per town (default 4)")
    p.add_argument("--route-seeds", default=None, metavar="SEEDS",
                   help="the route seeds instead, e.g. 100-107 or 1,2,5 (ranges inclusive; routes the package never "
                        "tuned on)")
    p.add_argument("--placements", nargs="+", default=[], metavar="NAME|PATH",
                   help="also score these placements (names or TOML files, 4 LiDARs), ranked beside the paper's eight")
    p.add_argument("--frames", type=int, default=40, help="frames per route (default 40, as the paper)")
    p.add_argument("--voxel-size", type=float, default=None, help="voxel size in metres (default 0.1)")
    from place3d_app.commands.common import add_roi_argument

    add_roi_argument(p)
    p.add_argument("--frames-per-subset", type=int, default=None, help="k frames per SOG (default 4)")
    p.add_argument("--occlusion", default="sog", choices=["sog", "none"], help="ray occlusion (default sog)")
    p.add_argument("--lidar", default="place3d_16ch", help="the rig's LiDAR (default place3d_16ch)")
    p.add_argument("--collection-lidar", default="collection_64ch", help="LiDAR recording the drives (default collection_64ch)")
    p.add_argument("--roll-units", default="rad", choices=["rad", "deg"],
                   help="read the paper's roll values as radians (default) or degrees (docs/assumptions.md)")
    p.add_argument("--det-variant", default="vehicle", choices=list(DET_VARIANTS), help="detection P-SOG classes")
    p.add_argument("--no-convergence", action="store_true", help="skip the N vs 2N routes table")
    p.add_argument("--backend", default=None, help="backend (default: $PLACE3D_BACKEND or auto)")
    p.add_argument("--output", default=None, help="output folder (default bench/results/reproduce-<date>/)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    add_executor_arguments(p, default="auto")      # drives built in worker processes where cores allow


def run(args) -> int:
    from place3d_app.executors import executor_from_args

    from place3d_kernels.pooled import parse_route_seeds

    seeds = None if args.route_seeds is None else parse_route_seeds(args.route_seeds)
    n_routes = args.routes if seeds is None else len(seeds)
    out = args.output or f"bench/results/reproduce-{datetime.now(timezone.utc).date().isoformat()}"
    with section("executor start"):
        ex = executor_from_args(args, tasks=n_routes * len(args.towns), backend=args.backend)
    try:
        res = reproduce(args.towns, args.routes, args.frames, args.voxel_size, args.frames_per_subset, args.occlusion,
                        args.lidar, args.collection_lidar, args.roll_units, args.det_variant, args.backend, ex,
                        args.opendrive_dir, not args.no_convergence, progress=not args.quiet, route_seeds=seeds,
                        placements=args.placements, roi=args.roi, draw_ahead=True)
    finally:
        with section("executor shutdown"):
            ex.shutdown()
    paths = write_outputs(res, out)
    with section("output: report"):
        print(format_report(res))
    print(f"wrote {paths['json']} and {paths['png']}", file=sys.stderr)
    return 0
