"""``place3d optimize``: CMA-ES over batched M-SOG on a scene, with outputs for people and programs."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from place3d_kernels.profiling import section

__all__ = ["add_arguments", "run", "start_plots", "DEFAULT_NORMALISATION"]

#: The M-SOG denominator ``place3d optimize`` searches with unless ``--normalisation`` says otherwise: the one
#: whose winners held best on held-out routes and towns (docs/metric-normalisation.md, "Which objective's
#: winners transfer"). ``evaluate`` and ``reproduce`` keep the paper's definition ("paper").
DEFAULT_NORMALISATION = "uncertain"


def add_arguments(p) -> None:
    p.add_argument("--task", default="seg", choices=["seg", "det"], help="M-SOG variant (default seg)")
    p.add_argument("--lidar", default="place3d_16ch", help="LiDAR model of the rig (default place3d_16ch)")
    p.add_argument("--lidars", type=int, default=4, help="number of LiDARs, 1-8 (default 4)")
    p.add_argument("--fixed-height", type=float, default=None, metavar="Z",
                   help="keep every LiDAR at height Z (the paper's 2-D plane study)")
    p.add_argument("--min-distance", type=float, default=0.2, help="minimum distance between LiDARs, m (default 0.2)")
    p.add_argument("--max-evals", type=int, default=2000, help="evaluation budget (default 2000)")
    p.add_argument("--popsize", type=int, default=None, help="CMA-ES population (default: pycma's)")
    p.add_argument("--sigma0", type=float, default=None,
                   help="initial step, fraction of each bound width (default 0.15 from a baseline, 0.3 from the "
                        "box centre)")
    p.add_argument("--x0", default="best-baseline",
                   help="where the search starts: 'best-baseline' (default with 4 LiDARs: the best of the paper's "
                        "placements on this scene), 'centre' (the box centre), or a placement name / TOML file")
    p.add_argument("--restarts", type=int, default=0,
                   help="further independent runs (seeds + 1, + 2, ...), each with the full --max-evals budget; "
                        "the best run wins (default 0)")
    p.add_argument("--delta", type=float, default=0.1, help="grid density of candidates (default 0.1, the paper's)")
    p.add_argument("--opt-seed", type=int, default=None, help="optimiser seed (default: --seed)")
    p.add_argument("--occlusion", default="sog", choices=["sog", "none"], help="ray occlusion mode")
    p.add_argument("--pose-cache", action="store_true",
                   help="cache covered voxels per LiDAR pose (pays off when rigs repeat most poses; otherwise "
                        "the fused batched kernel is faster)")
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint file written after a generation, at most once a second (default: "
                        "OUTPUT/checkpoint.ckpt with --output)")
    p.add_argument("--resume", action="store_true",
                   help="continue from --checkpoint (the run's settings must match; they are checked first)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results and checkpoint of another run in --output (refused otherwise)")
    p.add_argument("--output", default=None, help="folder for result.json, placement TOML, history.csv and plots")
    # issue 13 item 4, issue 34 item 4: an optimiser whose winners transfer (docs/metric-normalisation.md)
    p.add_argument("--normalisation", default=DEFAULT_NORMALISATION, choices=["paper", "evidence", "uncertain"],
                   help=f"M-SOG denominator the search maximises: 'uncertain' (covered voxels with H > 0; default "
                        f"{DEFAULT_NORMALISATION!r}: its winners transferred best to held-out routes and towns), "
                        f"'evidence' (covered voxels ever occupied in the P-SOG) or 'paper' (N_L, every covered "
                        f"voxel: the paper's definition, evaluate's default)")
    p.add_argument("--holdout-seeds", default=None, metavar="SEEDS",
                   help="route seeds of the held-out P-SOGs, pooled per scene, e.g. 100-103 (default: as many routes "
                        "as the search pooled, from seed 100); the winner's rank among the baselines there is the "
                        "run's verdict")
    p.add_argument("--holdout-scenes", default=None, metavar="SCENE1,SCENE2",
                   help="scenes of the held-out P-SOGs (map names such as Town03, or opendrive:PATH; default: the "
                        "searched scenes)")
    p.add_argument("--no-holdout", action="store_true",
                   help="skip the held-out re-scoring (the search's answer then has no transfer verdict)")
    p.add_argument("--interval", default="jackknife", choices=["jackknife", "bootstrap", "none"],
                   help="95 %% intervals of the best rig and the baselines over the drive's subsets, and P(best > "
                        "baseline): 'jackknife' (default), 'bootstrap' (--resamples draws) or 'none'")
    p.add_argument("--resamples", type=int, default=200, help="bootstrap resamples (with --interval bootstrap)")
    from place3d_app.commands.rig import add_rig_arguments

    add_rig_arguments(p)


def run_setup(args, spec) -> dict:
    """Everything a resumed run must share with the run that wrote the checkpoint (the checkpoint's
    manifest, ``<checkpoint>.manifest.json``); ``--max-evals`` may grow, so it is left out."""
    psog = spec.to_dict()
    psog.pop("backend", None)           # the backends agree bit for bit
    psog.pop("cache", None)
    if psog["grid"].get("voxel_size") is None:
        # the default's size, not None: a checkpoint made when the default was 0.2 m must not resume at 0.1 m
        psog["grid"] = {**psog["grid"], "voxel_size": spec.grid.grid().voxel_size}
    return {"task": args.task, "psog": psog, "lidar": args.lidar, "lidars": args.lidars,
            "fixed_height": args.fixed_height, "min_distance": args.min_distance, "popsize": args.popsize,
            "sigma0": args.sigma0, "x0": args.x0, "restarts": args.restarts, "delta": args.delta,
            "seed": args.opt_seed, "occlusion": args.occlusion,
            # pooled runs only, so the manifests of single-drive runs still match
            **({"drives": [d.scene.to_dict() for d in args.drives]} if len(getattr(args, "drives", None) or ()) > 1
               else {}),
            # only when not the paper's, so the manifests of earlier runs still match
            **({"normalisation": args.normalisation} if getattr(args, "normalisation", "paper") != "paper" else {})}


def check_args(args, spec) -> None:
    """Every check that needs no P-SOG, before it is built: counts, paths, the start, the checkpoint."""
    from place3d_kernels.manifest import verify_manifest
    from place3d_kernels.optimize import SearchSpace
    from place3d_kernels.optimize.checkpoint import DEFAULT_NAME
    from place3d_kernels.outputs import claim_optimize_folder
    from place3d_kernels.placement import Placement

    if args.max_evals < 1:
        raise ValueError(f"--max-evals must be >= 1, got {args.max_evals}")
    if not 1 <= args.lidars <= 8:
        raise ValueError(f"--lidars must be 1-8, got {args.lidars}")
    check_search_options(args)
    check_box_in_roi(args, spec.grid.grid())
    if args.output is not None and Path(args.output).exists() and not Path(args.output).is_dir():
        raise ValueError(f"--output {args.output} is an existing file; give a folder")
    if args.checkpoint is None and args.output is not None and args.restarts == 0:
        args.checkpoint = str(Path(args.output) / DEFAULT_NAME)
    if args.checkpoint is not None and Path(args.checkpoint).is_dir():
        raise ValueError(f"--checkpoint {args.checkpoint} is a folder; give a file path")
    if args.resume and args.checkpoint is None:
        raise ValueError(f"--resume needs --checkpoint FILE (or --output DIR, whose {DEFAULT_NAME} is used)")
    if args.x0 not in ("best-baseline", "centre"):
        space = SearchSpace(n_lidars=args.lidars)
        x = space.from_placement(Placement.load(args.x0))
        if not np.all(space.contains(x, tol=1e-9)):
            raise ValueError(f"--x0 {args.x0} lies outside the search box {space}; choose a placement inside it")
    # parses --holdout-seeds / --holdout-scenes, raising on bad values; the drives are built with the search's
    args.holdout = holdout_specs(args, spec)
    from place3d_app.executors import check_actor_arguments

    check_actor_arguments(args)          # --gpu-actors / --cpu-actors need --executor ray
    if len(getattr(args, "drives", None) or ()) > 1 and args.interval == "bootstrap":
        raise ValueError("--interval bootstrap resamples the subsets of a single drive (--routes 1); over routes its "
                         "resamples repeat drives and score high, so a pooled P-SOG takes the jackknife")
    if len(getattr(args, "drives", None) or ()) > 1 and (getattr(args, "executor", "local") == "ray"
                                                         or getattr(args, "ray_address", None)):
        raise ValueError("the Ray executor scores on one drive's P-SOG; run a pooled P-SOG locally, or use "
                         "--routes 1 with --executor ray")
    if not getattr(args, "overwrite", False):
        refuse_other_normalisation(args)
    claim_optimize_folder(args.output, args.checkpoint, run_setup(args, spec), getattr(args, "overwrite", False),
                          args.resume)           # another run's results or an old pickle checkpoint: refused
    if args.resume and args.checkpoint is not None and Path(args.checkpoint).exists():
        man = Path(str(args.checkpoint) + ".manifest.json")
        if not verify_manifest(man, run_setup(args, spec), "checkpoint",
                               "resume with the same settings, or start a fresh run (without --resume)"):
            raise ValueError(f"{args.checkpoint} has no manifest ({man.name}), so its settings cannot be checked; "
                             f"start a fresh run (without --resume)")


def check_box_in_roi(args, grid) -> None:
    """``ValueError`` naming --roi when a corner of the search box (the paper's, at --fixed-height if given)
    or a LiDAR of the paper's placements (the baselines) lies outside the ROI ``grid``."""
    import itertools

    from place3d_app.commands.common import check_rigs_in_roi
    from place3d_kernels.grid import check_inside
    from place3d_kernels.optimize import DEFAULT_BOUNDS
    from place3d_kernels.placement import PAPER_PLACEMENTS, Placement

    zs = DEFAULT_BOUNDS["z"] if args.fixed_height is None else (args.fixed_height,)
    check_inside(grid, list(itertools.product(DEFAULT_BOUNDS["x"], DEFAULT_BOUNDS["y"], zs)),
                 "a corner of the search box")
    check_rigs_in_roi(grid, {n: Placement.load(n).poses for n in PAPER_PLACEMENTS})


def refuse_other_normalisation(args) -> None:
    """Refuse results or a checkpoint (``--output``, ``--checkpoint``) of a run that searched with another
    normalisation, naming the option: before ``uncertain`` became the default, a run without
    ``--normalisation`` searched with ``paper``, and its checkpoint must not be continued as ``uncertain``.
    (``run_setup`` records the normalisation only when it is not the paper's, so such files hold none.)"""
    from place3d_kernels.outputs import stored_setup

    found = []
    if args.output is not None:
        found.append((Path(args.output) / "result.json", stored_setup(Path(args.output) / "result.json", "setup")))
    if args.checkpoint is not None:
        man = Path(str(args.checkpoint) + ".manifest.json")
        found.append((man, stored_setup(man, "spec")))
    for where, setup in found:
        if not isinstance(setup, dict) or not setup:     # none, or unreadable (claim_optimize_folder names that)
            continue
        theirs = setup.get("normalisation", "paper")
        if theirs != args.normalisation:
            was = (" (optimize's default; it was 'paper' before)"
                   if args.normalisation == DEFAULT_NORMALISATION and theirs == "paper" else "")
            fix = (f"add --normalisation {theirs} to resume it, or drop --resume and pass --overwrite to start afresh"
                   if args.resume else f"add --normalisation {theirs} to continue that run, --overwrite to discard "
                                       f"it, or choose a fresh folder")
            raise ValueError(f"{where} is from a run that searched with --normalisation {theirs}; this one searches "
                             f"with {args.normalisation}{was}: {fix}")


def check_search_options(args) -> None:
    """The search's options, named as the command line names them, before any work.

    The library checks the same values after the P-SOG is built and names its own parameters
    (``popsize``, ``sigma0``, ``seed``, ``MinDistance(...)``); here they are refused first, as options."""
    import math

    from place3d_kernels.optimize import MinDistance, SearchSpace

    if args.popsize is not None and args.popsize < 2:
        raise ValueError(f"--popsize must be >= 2 (CMA-ES needs two candidates a generation), got {args.popsize}")
    if args.sigma0 is not None and not (math.isfinite(args.sigma0) and args.sigma0 > 0):
        raise ValueError(f"--sigma0 must be > 0 (a fraction of each bound width, e.g. 0.15), got {args.sigma0}")
    if not (math.isfinite(args.delta) and args.delta > 0):
        raise ValueError(f"--delta must be a positive grid step in metres and radians, got {args.delta}")
    seed = args.opt_seed if args.opt_seed is not None else args.seed
    if not 0 <= seed < 2 ** 32:
        raise ValueError(f"--opt-seed (default: --seed) must be from 0 to 2**32 - 1, got {seed}")
    if args.restarts < 0:
        raise ValueError(f"--restarts must be >= 0, got {args.restarts}")
    if args.restarts and (args.checkpoint is not None or args.resume):
        raise ValueError(f"--restarts {args.restarts} runs several searches, which are not checkpointed: drop "
                         f"--checkpoint / --resume, or --restarts")
    if args.fixed_height is not None and not math.isfinite(args.fixed_height):
        raise ValueError(f"--fixed-height must be a finite height in metres, got {args.fixed_height}")
    if args.lidars > 1:
        if not (math.isfinite(args.min_distance) and args.min_distance > 0):
            raise ValueError(f"--min-distance must be a positive distance in metres, got {args.min_distance}")
        why = MinDistance(args.min_distance).impossibility(SearchSpace(n_lidars=args.lidars), args.delta)
        if why:
            raise ValueError(f"--min-distance {args.min_distance:g} cannot hold {why}; lower it or use fewer "
                             f"--lidars")


def _probe(name):
    from place3d_kernels.backends.registry import get_backend

    with section("backend probe (thread)"):
        return get_backend(name)


def _scipy_imports(certificate_here: bool, t_quantiles: bool) -> None:
    """Import, ahead of their use, the SciPy modules the command takes after its search: where the certificate
    is computed in this process (``certificate_here``) SciPy's ``pdist``; with ``t_quantiles`` (intervals over
    pooled routes) ``scipy.special``, whose t quantiles the interval takes (``intervals.Jackknife``)."""
    import importlib

    if certificate_here:
        importlib.import_module("scipy.spatial.distance")       # optimize.certificate's pdist
    if t_quantiles:
        importlib.import_module("scipy.special")


def run(args, spec, psog_for) -> int:
    """Run ``place3d optimize``.

    Args:
        args: the parsed command line.
        spec: the run's ``PSOGSpec`` (built once by the CLI; the Ray executor ships it to the workers).
        psog_for: ``psog_for(backend) -> (scene, PSOG)`` builds the P-SOG locally with the CLI's progress
            and cache options (``backend`` may be a ``Future`` of one, waited for only on a cache miss).
    """
    from place3d_kernels.optimize.plots import PlotWorker
    from place3d_app.commands.rig import run_rig, wants_rig_mode

    if wants_rig_mode(args):              # sensors, surfaces, a body, cost: place3d_app/commands/rig.py
        return run_rig(args, spec, psog_for)
    t0 = time.perf_counter()
    if args.opt_seed is None:
        args.opt_seed = args.seed          # --seed S seeds the scene and the optimiser alike
    check_args(args, spec)
    plotter = PlotWorker() if args.output else None      # started now: it imports matplotlib meanwhile
    failed = True
    try:
        code = _run(args, spec, psog_for, plotter, t0)
        failed = False
        return code
    finally:
        if plotter is not None:
            plotter.close(cancel=failed)


def _run(args, spec, psog_for, plotter, t0) -> int:
    """``run`` after the checks: the P-SOG, the search, the reports and the outputs."""
    from place3d_kernels.atomic import atomic_write_text
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.manifest import provenance, write_manifest
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.optimize import FixedHeight, MinDistance, MSOGObjective, SearchSpace, optimize
    from place3d_kernels.lazy_imports import import_cma
    from place3d_kernels.placement import PAPER_PLACEMENTS, Placement

    # The backend probe (importing Warp and starting CUDA: a large part of a cold command) runs on a thread
    # while this one builds the scene and reads the cached P-SOG, which need no backend; a cache miss waits
    # for it (scene_psog takes the Future). The same thread then imports pycma, which a cold command otherwise
    # imported once the P-SOG was built; on a cache miss it overlaps the simulation. Where the figures have
    # processes, the certificate is computed in their helper process (optimize's certificate_executor): its
    # SciPy import held the interpreter lock beside an in-process simulation (bench/README.md, "What the
    # studies found", cold command: imports, tail and exit). Elsewhere this thread imports the certificate's
    # SciPy module too. Intervals over pooled routes take t quantiles from scipy.special (0.3-0.5 s to import
    # on the H200 host, once the search had ended): this thread imports it while the drives are built in the
    # worker processes. The search waits for pycma alone: a warm command waited 0.01-0.07 s more for SciPy's
    # modules (bench/results/ab-2026-11-30-s35/README.md).
    bg = ThreadPoolExecutor(max_workers=1, thread_name_prefix="place3d-optimize")
    probe = bg.submit(_probe, args.backend)
    helper = plotter.helper if plotter is not None else None
    cma_imported = bg.submit(import_cma)
    bg.submit(_scipy_imports, helper is None,
              args.interval == "jackknife" and len(getattr(args, "drives", None) or ()) > 1)
    try:
        lidar = LidarModel.load(args.lidar)
        with section("scene + P-SOG"):
            _, psog = psog_for(probe)
        with section("import cma"):
            # SciPy's modules go on importing on the thread meanwhile (a later import of one waits for it there:
            # Python's import lock)
            cma_imported.result()
        with section("backend probe (wait)"):
            b = probe.result()
    finally:
        bg.shutdown(wait=False)
    from place3d_app.commands.common import warn_flat_objective

    warn_flat_objective(psog, args.normalisation)
    # The jackknife after the search scores the rigs on the drive's left-out grids, which depend on the
    # records and the task, not on the search: they are prepared on a thread while it runs
    # (place3d_app.prefetch.prepare_in_background)
    if args.interval == "jackknife" and args.lidars == 4 and getattr(args, "pool", None) is None:
        # the baselines' intervals over one drive's subsets: 4-LiDAR rigs (a pool's are over its routes)
        from place3d_app.prefetch import prefetch_wanted, prepare_in_background

        if prefetch_wanted():
            prepare_in_background(spec, psog, lidar, args.task, args.occlusion, b, normalisation=args.normalisation)
    space = SearchSpace(n_lidars=args.lidars)
    cons = [MinDistance(args.min_distance)] if args.lidars > 1 else []
    if args.fixed_height is not None:
        cons.append(FixedHeight(args.fixed_height))

    executor = None
    if getattr(args, "executor", "local") == "ray" or getattr(args, "ray_address", None):
        from place3d_app.executors import DistributedObjective, executor_from_args

        executor = executor_from_args(args)
        objective = DistributedObjective(dataclasses.replace(spec, backend=b.name), lidar, space, executor,
                                         task=args.task, occlusion=args.occlusion, backend=b.name, chunk=args.chunk,
                                         normalisation=args.normalisation)
    elif args.pose_cache:
        objective = MSOGObjective(psog, lidar, space, task=args.task, occlusion=args.occlusion, backend=b,
                                  normalisation=args.normalisation)
    else:
        def objective(X):
            return msog_batch(psog, lidar, space.to_poses(X), occlusion=args.occlusion, task=args.task, backend=b,
                              normalisation=args.normalisation)

    baselines = {}
    if args.lidars == 4:
        # the paper's placements in one batch (each rig's score is the same alone or batched): eleven calls of one
        # rig took 2.34 [2.24-2.59] s of the warm default command against 1.19 [0.95-1.54] s for one call on the
        # 2-core dev VM (opencl:pocl, 3 runs each, alternated, with the session's other changes; results ab-2026-11-29-s27)
        with section("baseline scores"):
            got = msog_batch(psog, lidar, np.stack([Placement.load(n).poses for n in PAPER_PLACEMENTS]),
                             args.occlusion, args.task, b, normalisation=args.normalisation)
            baselines = {name: float(v) for name, v in zip(PAPER_PLACEMENTS, got)}
    # The held-out P-SOGs and coverage.png's left panel are made on threads during the search, started once the
    # baselines are scored: started before them, they slowed the baselines' call (which makes the pooled P-SOG's
    # grids), 0.13 -> 0.10 s cold and 0.19 -> 0.09 s warm; the default optimize 3.41 -> 3.24 s cold, 2.39 -> 2.29 s
    # warm (H200, 6 runs each; bench/results/ab-2026-12-01-s42/)
    held_out = held_out_ahead(args, spec, b)     # the held-out P-SOGs (their grids off a GPU), during the search
    left_out_rows = left_out_rows_ahead(args, lidar, b)   # the jackknife's index tables of the pooled drives
    panel_view = []                 # keep_panel's entropy_view, which coverage.png's view then reuses
    if plotter is not None and plotter.processes:
        # the panel's entropies (float, every stored voxel: 0.3-0.4 s of NumPy on the H200 host) on a thread,
        # joined before the figures start
        def keep_panel():
            try:
                panel_view.append(entropy_view(psog))
                plotter.keep_panel(*panel_view[0])
            except Exception:  # noqa: BLE001 - the figure then draws the panel itself, and meets the error there
                pass

        panel = threading.Thread(target=keep_panel, daemon=True, name="place3d-panel")
        panel.start()
    else:
        panel = None
    # A warm start from the best paper placement with a smaller step: on the default town the "center"
    # rig is a strong local optimum for detection, which 2,000-evaluation runs from the box centre
    # (sigma0 0.3) beat in none of seeds 0-3 and runs from center (sigma0 0.15) in each of them
    # (tests/test_optimize_scene.py, docs/guide.md, "Optimisation")
    x0 = None
    if args.x0 == "best-baseline":
        if baselines:
            x0 = Placement.load(max(baselines, key=baselines.get))
    elif args.x0 != "centre":
        x0 = Placement.load(args.x0)
    sigma0 = args.sigma0 if args.sigma0 is not None else (0.15 if x0 is not None else 0.3)
    if args.checkpoint is not None:
        write_manifest(Path(str(args.checkpoint) + ".manifest.json"), run_setup(args, spec))
    out = Path(args.output) if args.output else None
    plots = None

    def search_ended(history, placement):
        # the figures need only the search's history and best rig: they are drawn while the certificate,
        # the diagnostics and the intervals are computed (the rig is named as the command names it below)
        nonlocal plots
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            placement.name = f"optimized-{args.task}"
            if panel is not None:
                with section("plotting: panel (wait)"):
                    panel.join()
            plots = start_plots(plotter, history, placement, space, psog, lidar, b, args.occlusion, out,
                                panel_view[0] if panel_view else None)

    try:
        with warnings.catch_warnings():
            # the report below says so itself, naming the options to change (no second line on stderr)
            warnings.filterwarnings("ignore", message="the search never left its start", category=RuntimeWarning)
            res = optimize(objective, space, cons, sigma0=sigma0, popsize=args.popsize, max_evals=args.max_evals,
                           delta=args.delta, seed=args.opt_seed, checkpoint=args.checkpoint, resume=args.resume,
                           progress=not args.quiet, restarts=args.restarts, x0=x0, on_search_end=search_ended,
                           certificate_executor=helper)
    finally:
        if executor is not None:
            executor.shutdown()
    seconds = time.perf_counter() - t0
    best = res.best_placement
    best.name = f"optimized-{args.task}"
    print(f"best M-SOG ({args.task}, {args.normalisation} normalisation) {res.best_score:.6f} after "
          f"{res.evaluations} evaluations in {seconds:.1f} s on {b.name}"
          + (f"; LiDAR poses traversed {objective.pose_misses}, reused {objective.pose_hits}"
             if args.pose_cache and executor is None else ""))
    if not res.left_start:
        print(f"warning: the search never left its start ({res.evaluations} evaluations found nothing better "
              f"than {x0.name if x0 is not None else 'the box centre'}); raise --max-evals or --sigma0, or start "
              f"elsewhere (--x0)")
    for name, s in sorted(baselines.items(), key=lambda kv: -kv[1]):
        mark = "  <" if s > res.best_score else ""
        print(f"  {name:14s} {s:.6f}{mark}")
    print("best placement (x, y, z, roll):")
    for p in best.poses:
        print("  " + ", ".join(f"{v:+.2f}" for v in p[:4]))
    report_trust(args, spec, res, psog, lidar, b, baselines, held_out, left_out_rows)
    cert = res.certificate
    if args.output:
        best.save(out / f"optimized-{args.task}.toml",
                  note=f"place3d optimize --task {args.task} --normalisation {args.normalisation}: M-SOG "
                       f"{res.best_score:.6f} on scene {args.scene} seed {args.seed}, backend {b.name}")
        result = {"task": args.task, "normalisation": args.normalisation, "best_score": res.best_score,
                  "best_placement": best.poses.tolist(),
                  "baseline_scores": baselines,
                  # over feasible samples, G = -M-SOG: the penalty term would otherwise dominate k_G and C_M
                  "certificate": {k: (cert.get("feasible") or cert).get(k)
                                  for k in ("k_G", "C_M", "bound", "bound_corollary")},
                  "certificate_samples": "feasible" if cert.get("feasible") else "all",
                  "evaluations": res.evaluations, "seconds": seconds, "backend": b.name, "seed": args.opt_seed,
                  "x0": x0.name if x0 is not None else "box centre", "sigma0": sigma0,
                  "scene": spec.scene.to_dict(), "grid": psog.grid.to_dict(), "n_subsets": psog.n_subsets,
                  "drives": [d.scene.label for d in getattr(args, "drives", None) or [spec]],
                  "sensor": {"name": lidar.name, "n_lidars": args.lidars, "occlusion": args.occlusion},
                  "condition": None if spec.condition is None else spec.condition.to_dict(),
                  "setup": run_setup(args, spec), "left_start": res.left_start,
                  "feasible": res.feasible,
                  "pose_cache": ({"traversed": objective.pose_misses, "reused": objective.pose_hits}
                                 if args.pose_cache and executor is None else None),
                  "transfer": res.transfer, "diagnostics": res.diagnostics, "holdout": res.holdout,
                  "intervals": res.intervals,
                  "details": res.to_dict(), "provenance": provenance(backend=b.name)}
        with section("writing result.json"):
            atomic_write_text(out / "result.json", json.dumps(result, indent=2, default=float))
        fh = io.StringIO(newline="")
        if res.history:
            w = csv.DictWriter(fh, fieldnames=list(res.history[0].keys()))
            w.writeheader()
            w.writerows(res.history)
        atomic_write_text(out / "history.csv", fh.getvalue())
        with section("plotting (wait)"):
            plots.result()             # re-raises a plotting error here
        print(f"wrote {out}/result.json, history.csv, optimized-{args.task}.toml, convergence.png, rig.png, coverage.png")
    return 0


#: First route seed of the default held-out P-SOGs: routes no default search pools (those start at --seed).
HOLDOUT_SEED = 100


def holdout_specs(args, spec) -> list:
    """``(scene name, seeds, [PSOGSpec per seed])``: one held-out P-SOG per scene of --holdout-scenes (default:
    the searched scenes), pooled over the route seeds of --holdout-seeds (default: as many as the search
    pooled, from ``HOLDOUT_SEED``). None with --no-holdout, and by default for scenes with one fixed route
    (mesh, semantickitti), which have no other routes to hold out.

    A held-out drive the search pooled (same scene and seed) is refused: it validates nothing.
    """
    from place3d_kernels.pooled import parse_route_seeds

    seeds_arg, scenes_arg = getattr(args, "holdout_seeds", None), getattr(args, "holdout_scenes", None)
    if getattr(args, "no_holdout", False):
        if seeds_arg or scenes_arg:
            raise ValueError("--no-holdout with --holdout-seeds / --holdout-scenes: give one or the other")
        return []
    trained_specs = getattr(args, "drives", None) or [spec]
    if not seeds_arg and not scenes_arg and spec.scene.kind not in ("town", "opendrive"):
        return []
    if seeds_arg:
        try:
            seeds = parse_route_seeds(seeds_arg)
        except ValueError as e:
            raise ValueError(f"--holdout-seeds: {e}") from None
    else:
        n = len({d.scene.seed for d in trained_specs})
        seeds = list(range(HOLDOUT_SEED, HOLDOUT_SEED + n))
    searched = list(dict.fromkeys(d.scene.name for d in trained_specs))
    scenes = [v.strip() for v in scenes_arg.split(",") if v.strip()] if scenes_arg else searched
    from place3d_app.commands.reproduce import resolve_town

    # a bare map name (Town03) is looked up like `place3d reproduce` does (shipped CARLA maps included)
    scenes = [n if ":" in n or n == "town" else resolve_town(n) for n in scenes]
    trained = {(d.scene.name, d.scene.seed) for d in trained_specs}
    out = []
    for name in scenes:
        specs = []
        for seed in seeds:
            if (name, seed) in trained:
                raise ValueError(f"held-out P-SOG {name} seed {seed} is one the search pooled; hold out other "
                                 f"seeds or scenes")
            scene = dataclasses.replace(spec.scene, name=name, seed=seed)
            if name != spec.scene.name:
                scene = dataclasses.replace(scene, labels=None, route=None)
            scene.validate()
            specs.append(dataclasses.replace(spec, scene=scene))
        out.append((name, seeds, specs))
    return out


def report_intervals(args, spec, res, lidar, b, base_poses, psog=None) -> dict | None:
    """Intervals of the best rig and each baseline over the drive's subsets, printed (issue 13, item 3)."""
    if args.interval == "none" or not base_poses:
        return None
    from place3d_kernels.uncertainty import rig_vs_baselines_intervals, route_df, too_few_subsets

    pool = getattr(args, "pool", None)         # a pooled P-SOG: intervals over its routes (jackknife only)
    if pool is not None and route_df(len(pool[0]), pool[1]) < 1:
        print("no intervals: every scene has one route (an interval over routes needs two in some scene)")
        return None
    if pool is None and psog is not None and too_few_subsets(psog.n_subsets):
        # leaving one of two subsets out pools one, whose entropy is 0: a zero-width interval, not a narrow one
        print(f"no intervals: {too_few_subsets(psog.n_subsets)} (use more --frames)")
        return None
    with section(f"intervals ({args.interval})"):
        iv = rig_vs_baselines_intervals(spec if pool is None else pool[0], lidar, res.best_placement.poses, base_poses,
                                        args.task, args.occlusion, b, args.resamples, args.opt_seed,
                                        method=args.interval, best_name="optimised", normalisation=args.normalisation,
                                        reference=psog, strata=None if pool is None else pool[1])
    lo, hi = iv["best"]["ci"]
    print(f"95 % intervals ({iv['method']} over the {iv['n_units']} {iv['unit']}): optimised "
          f"{iv['best']['score']:.6f} [{lo:.6f}, {hi:.6f}]")
    noisy = [r for r in iv["baselines"] if r["within_noise"]]
    for r in sorted(iv["baselines"], key=lambda r: -r["score"])[:4]:
        print(f"  {r['name']:14s} {r['score']:.6f} [{r['ci'][0]:.6f}, {r['ci'][1]:.6f}]  "
              f"P(optimised > it) = {r['p_best_better']:.2f}{'  (within noise)' if r['within_noise'] else ''}")
    if noisy:
        print(f"the optimised rig is within noise of {len(noisy)} baseline(s): "
              + ", ".join(r["name"] for r in noisy))
    return iv


def held_out_psogs(args, spec, specs, b, grids: bool = False):
    """Yield ``(scene name, seeds, P-SOG)`` for each held-out spec of ``specs`` (``holdout_specs``), each checked
    for entropy; with ``grids``, the grids its scoring will ask for (the task's weights, stop mask and
    indicators on ``b``, kept by the P-SOG) are prepared too."""
    from place3d_app.commands.routes import built_records
    from place3d_kernels.metrics import count_handles
    from place3d_kernels.pipeline import check_entropy
    from place3d_kernels.pooled import pool_specs

    for name, seeds, drives in specs:
        with section("held-out P-SOGs"):
            if len(drives) == 1:
                p = drives[0].build(backend=b, cache=not args.no_cache, progress=not args.quiet)
            else:
                known = built_records(args, drives)      # held-out drives the workers may still be building
                p = pool_specs(drives, backend=b, cache=not args.no_cache, known=known).kept_psog()
        check_entropy(p, spec.frames_per_subset)
        if grids and args.occlusion in ("sog", "none"):
            with section("held-out grids"):       # the grids the held-out scores (coverage_counts) ask for
                count_handles(p.for_task(args.task), args.occlusion, b)
        yield name, seeds, p


def held_out_ahead(args, spec, b):
    """A ``Future`` of the held-out P-SOGs (``held_out_psogs``), made on a daemon thread while the search runs,
    or None (they are made after it, as before): where there are held-out P-SOGs, each pooled from drives the
    workers built (a single drive would be built with a progress bar), and the host has cores to spare
    (``prefetch.prefetch_wanted``: 4 or more, or ``PLACE3D_JACKKNIFE_PREFETCH=1``). Their grids are made on the
    thread too unless ``b`` makes them on its device (``grids_beside_search``).

    They depend on the held-out drives alone, not on the search, and took about 1 s of a cold default
    ``optimize`` after it on the H200 (pooling, weights, and the uploads of three grids). An error on the
    thread is raised where the command asks for them, after the search."""
    from concurrent.futures import Future

    from place3d_app.prefetch import prefetch_wanted

    specs = getattr(args, "holdout", None)
    if not specs or any(len(drives) < 2 for _, _, drives in specs) or not prefetch_wanted():
        return None
    done: Future = Future()

    def work():
        try:
            done.set_result(list(held_out_psogs(args, spec, specs, b, grids=grids_beside_search(b))))
        except BaseException as e:  # noqa: BLE001 - raised by result() in the command
            done.set_exception(e)

    threading.Thread(target=work, name="place3d-held-out", daemon=True).start()
    return done


def left_out_rows_ahead(args, lidar, b):
    """A started thread making the jackknife's index tables of the pooled drives (``LeftOutRows.batch``: where
    each record's entries fall in the pool, host NumPy over every entry) while the search runs, or None (made
    in the jackknife, as before): where the intervals are a jackknife over pooled routes that will read them
    (``left_out.index_tables_used``: its fused path, the rows made on backend ``b``) and the host has cores
    to spare (``prefetch.prefetch_wanted``). They depend on the pooled records alone; after the search they took
    most of the jackknife's "left-out grid" rows (0.07-0.085 s of a cold default optimize on the H200 host).
    The tables are kept with the pool (``LeftOutRows.shared``), where the jackknife finds them; an error on the
    thread is left to the jackknife, which makes them again and meets it there."""
    from place3d_app.prefetch import prefetch_wanted

    from place3d_kernels.left_out import LeftOutRows, index_tables_used

    pool = getattr(args, "pool", None)
    if (pool is None or args.interval != "jackknife" or len(pool[0]) < 2 or not prefetch_wanted()
            or not index_tables_used(lidar, args.occlusion, args.normalisation, b)):
        return None

    rows = LeftOutRows.shared(pool[0])          # made here: the jackknife's shared() finds this one

    def work():
        try:
            rows.batch()
        except Exception:  # noqa: BLE001 - the jackknife calls batch() again and reports the error
            pass

    t = threading.Thread(target=work, daemon=True, name="place3d-left-out-rows")
    t.start()
    return t


def grids_beside_search(b) -> bool:
    """Whether ``held_out_ahead``'s thread also makes the held-out P-SOGs' grids: not where backend ``b`` makes
    a grid on its device (``fields_on_device``: Warp on CUDA, OpenCL GPUs with doubles), whose one in-order
    queue the search's scores wait on. There the grids' kernels and copies, made beside the search, held some
    of its generations 20-120 ms each: a cold default ``optimize`` on the H200 host scored its generations in
    0.49-0.62 s with them beside it and 0.35-0.41 s with them made after it, in the held-out check (about 0.08
    s there; 5 runs each, traced), and ended at 3.49 against 3.62 s and 3.89 against 4.05 s (two leases, 6 runs
    each; bench/results/ab-2026-12-01-s42/README.md). A CPU device makes them on this process's threads, as
    before."""
    return not getattr(b, "fields_on_device", False)


def report_trust(args, spec, res, psog, lidar, b, baselines, held_out=None, left_out_rows=None) -> None:
    """Fill ``res.diagnostics``, ``res.holdout`` and ``res.transfer`` (the held-out verdict, unless
    --no-holdout) and print them (issue 34, item 4). ``held_out``: ``held_out_ahead``'s Future, or None;
    ``left_out_rows``: ``left_out_rows_ahead``'s thread, joined before the intervals, or None."""
    from place3d_kernels.optimize.diagnostics import diagnose, format_diagnostics, format_holdout, holdout
    from place3d_kernels.placement import Placement

    base_poses = {name: Placement.load(name).poses for name in baselines}
    with section("diagnostics"):
        res.diagnostics = diagnose(psog, lidar, res.search_space, res.best_placement.poses, base_poses,
                                   delta=args.delta, occlusion=args.occlusion, task=args.task, backend=b)
    res.diagnostics["normalisation"] = args.normalisation
    for line in format_diagnostics(res.diagnostics):
        print(line)
    if left_out_rows is not None:
        with section("jackknife: index tables (wait)"):
            left_out_rows.join()
    res.intervals = report_intervals(args, spec, res, lidar, b, base_poses, psog)
    specs = args.holdout if getattr(args, "holdout", None) is not None else holdout_specs(args, spec)
    if not specs:
        return
    from place3d_kernels.optimize.diagnostics import transfer

    with section("held-out check"):           # its P-SOGs (a nested section) and the rigs' scores on them
        if held_out is not None:
            with section("held-out P-SOGs (wait)"):
                scenes = iter(held_out.result())
        else:
            scenes = held_out_psogs(args, spec, specs, b)
        res.holdout = holdout(scenes, lidar, res.best_placement.poses, base_poses, occlusion=args.occlusion,
                              task=args.task, backend=b, normalisation=args.normalisation)
    res.transfer = transfer(res.holdout)
    for line in format_holdout(res.holdout, res.transfer):
        print(line)


def start_plots(plotter, history, best, space, psog, lidar, backend, occlusion, out: Path, panel=None):
    """Hand convergence.png, rig.png and coverage.png to ``plotter`` (a ``PlotWorker``); returns the Future.

    The rig's covered voxels (a backend call) and the coverage view's two top-view arrays are computed
    here, on the calling thread; matplotlib then runs beside the diagnostics and the jackknife. ``panel``:
    ``entropy_view(psog)`` where it was made already (the panel kept during the search).
    """
    from place3d_kernels.metrics import coverage_mask

    def view():
        # called by the worker once the other two figures are on their way
        with section("plotting: covered voxels"):
            covered = coverage_mask(psog, lidar, best.poses, occlusion=occlusion, backend=backend)
            return coverage_view(psog, covered, panel) + (best.name or "the rig",)

    return plotter.submit(history, best, space, view, out)


def entropy_view(psog) -> tuple:
    """(column entropy, extent): coverage.png's left panel's data for ``psog``."""
    g = psog.grid
    return psog.entropy.sum(axis=2), (g.lower[1], g.upper[1], g.lower[0], g.upper[0])


def coverage_view(psog, covered, view=None) -> tuple:
    """(column entropy, covered columns, covered voxels, extent): ``draw_coverage``'s data for a rig's
    ``coverage_mask`` on ``psog`` (the mask itself: rebuilding it from ``covered_voxels``' indices took
    about 50 ms of a default optimize on the dev VM); ``view``: ``entropy_view(psog)`` if made already."""
    g = psog.grid
    mask = np.asarray(covered, dtype=bool).reshape(g.shape)
    column, extent = entropy_view(psog) if view is None else view
    return column, mask.any(axis=2), int(np.count_nonzero(mask)), extent
