"""``place3d evaluate``: the paper's placements (or the ones named) scored on a scene's P-SOG, with intervals."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from place3d_kernels.profiling import section

from place3d_app.commands.common import check_output_file, check_rigs_in_roi, psog_for_spec
from place3d_app.prefetch import LATE_IMPORTS, import_in_background, start_for_spec

__all__ = ["cmd_evaluate", "PLOT_SUFFIXES"]

#: What --plot writes (matplotlib's format follows the suffix).
PLOT_SUFFIXES = (".png", ".svg", ".pdf")


def cmd_evaluate(args) -> int:
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.placement import PAPER_PLACEMENTS, Placement
    from place3d_kernels.spec import specs_from_args
    from place3d_kernels.uncertainty import MIN_SUBSETS, too_few_subsets

    t0 = time.perf_counter()
    check_output_file(args.output)
    check_output_file(args.plot, PLOT_SUFFIXES, "--plot")        # before the JSON is written, not after
    if args.plot and (args.interval == "none" or (args.interval == "bootstrap" and not args.resamples)):
        raise ValueError(f"--plot draws the scores with their intervals; --interval {args.interval}"
                         f"{' with --resamples 0' if args.interval == 'bootstrap' else ''} has none to draw")
    with section("setup: specs, backend, placements"):
        spec = specs_from_args(args)
        from place3d_app.commands.routes import build_missing, drive_specs, pooled_psog

        drives = drive_specs(args, spec)
        start_for_spec(spec, cache=not args.no_cache, drives=len(drives))  # built on another core during the probe
        b = get_backend(args.backend)
        lidar = LidarModel.load(args.lidar)
        names = args.placements or list(PAPER_PLACEMENTS)
        placements = [Placement.load(n) for n in names]
        check_rigs_in_roi(spec.grid.grid(), {n: pl.poses for n, pl in zip(names, placements)})
        body = spec.vehicle_body()
    # the intervals' and the plot's imports load while the P-SOG is read or built (after the scene's fork)
    import_in_background(*(LATE_IMPORTS["intervals"] if args.interval != "none" else ()),
                         *(LATE_IMPORTS["plot"] if (args.plot or args.output) and args.interval != "none" else ()))
    if len(drives) > 1 and args.interval == "bootstrap":
        raise ValueError("--interval bootstrap resamples the subsets of a single drive (--routes 1); over routes "
                         "its resamples repeat drives and score high, so a pooled P-SOG takes the jackknife")
    build_missing(args, drives, b)                   # drives the cache lacks, in worker processes
    pool = pooled_psog(args, spec, b, drives)
    if pool is None:
        _, psog = psog_for_spec(spec, args, b)
    else:
        psog = pool[2]
    rows = []
    with section("scoring: placements"):
        scores = _placement_scores(psog, lidar, placements, args.occlusion, b, args.normalisation, body, args.quiet)
    for name, pl, (seg, det) in zip(names, placements, scores):
        rows.append({"placement": pl.name or name, "msog_seg": seg, "msog_det": det})
    rows.sort(key=lambda r: -r["msog_seg"])
    interval_note = None
    if args.interval == "none" or (pool is None and not args.resamples):
        boots = None
    elif pool is None and too_few_subsets(psog.n_subsets):
        # leaving one of two subsets out pools one, whose entropy is 0: a zero-width interval, not a narrow one
        from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET

        k = spec.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET
        interval_note = (f"{too_few_subsets(psog.n_subsets)} (k = {k} frames each), so the table has no interval "
                         f"columns{' and no plot' if args.plot else ''}; intervals need at least {MIN_SUBSETS * k} "
                         f"frames")
        print(f"place3d: note: {interval_note}", file=sys.stderr)
        boots = None
    elif pool is None:
        boots = _evaluate_bootstrap(args, spec, b, lidar, names, placements, rows)
    else:
        boots = _route_intervals(args, pool, psog, b, lidar, names, placements, rows, body)
    seconds = time.perf_counter() - t0
    cond = f", condition {args.condition}" if args.condition else ""
    where = (f"scene {args.scene} (seed {args.seed}{cond})" if pool is None else
             f"a P-SOG pooled over {len(drives)} drives ({', '.join(dict.fromkeys(pool[1]))}; route seeds "
             f"{_seed_text(drives)}{cond})")
    print(f"M-SOG on {where}, backend {b.name}, grid {psog.grid.shape} "
          f"@ {psog.grid.voxel_size} m, occlusion {args.occlusion}, vehicle {spec.vehicle or 'none'}"
          + (f", normalisation {args.normalisation}" if args.normalisation != "paper" else "") + "; higher is better")
    det_rank = {r["placement"]: i + 1 for i, r in enumerate(sorted(rows, key=lambda r: -r["msog_det"]))}
    if boots is None:
        print(f"{'rank':>4}  {'placement':14s} {'M-SOG seg':>12s} {'M-SOG det':>12s}")
        for i, r in enumerate(rows):
            print(f"{i + 1:>4}  {r['placement']:14s} {r['msog_seg']:12.6f} {r['msog_det']:12.6f}"
                  f"   (det rank {det_rank[r['placement']]})")
    else:
        with section("intervals: table"):
            _print_intervals(rows, boots, det_rank)
    print(f"{seconds:.1f} s")
    if args.output:
        from place3d_app.commands.reproduce import machine_info
        from place3d_kernels.manifest import provenance

        out = {"rows": rows, "backend": b.name, "grid": psog.grid.to_dict(), "seconds": seconds,
               "scene": spec.scene.to_dict(), "occlusion": args.occlusion, "lidar": lidar.name,
               "condition": None if spec.condition is None else spec.condition.to_dict(),
               "psog": spec.to_dict(), "n_subsets": psog.n_subsets, "seed": args.seed,
               "normalisation": args.normalisation,
               "drives": [d.scene.label for d in drives], "scenes": list(dict.fromkeys(d.scene.name for d in drives)),
               "route_seeds": sorted({d.scene.seed for d in drives}),
               "vehicle": None if body is None else
               {"name": body.name, "key": body.key, "bounds_m": body.bounds.round(4).tolist()},
               "machine": machine_info(b.name), "provenance": provenance(backend=b.name)}
        if boots is not None:
            out["bootstrap"] = _bootstrap_summary(args, boots)
        elif interval_note:
            out["intervals_note"] = interval_note
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(args.output, json.dumps(out, indent=2))
    plot = args.plot or (str(Path(args.output).with_suffix(".png")) if args.output and boots else None)
    if plot and boots is not None:
        from place3d_kernels.uncertainty import interval_method, plot_scores

        with section("plotting"):
            what = (f"{args.scene}, seed {args.seed}{cond}" if pool is None else f"{len(drives)} drives pooled{cond}")
            plot_scores({f"M-SOG {t} ({what})": boots[t] for t in ("seg", "det")},
                        plot, title=f"M-SOG of {len(rows)} placements, {int(boots['seg'].level * 100)} % intervals: "
                                    f"{interval_method(boots['seg'])}")
        if not args.quiet:
            print(f"wrote {plot}", file=sys.stderr)
    return 0


def _placement_scores(psog, lidar, placements, occlusion, b, normalisation, body, quiet) -> list[tuple[float, float]]:
    """(seg, det) M-SOG of each placement: one ``msog_tasks`` call (both tasks) for the placements of each LiDAR
    count (a rig's score does not depend on the others scored beside it), instead of one per placement."""
    import numpy as np
    from tqdm import tqdm

    from place3d_kernels.metrics import msog_tasks

    out = [None] * len(placements)
    groups: dict = {}
    for i, pl in enumerate(placements):
        groups.setdefault(pl.poses.shape, []).append(i)
    for idx in tqdm(list(groups.values()), desc="evaluate", unit="group", disable=quiet, leave=False):
        poses = np.stack([placements[i].poses for i in idx])
        got = msog_tasks(psog, lidar, poses, occlusion, ("seg", "det"), b, normalisation, body)
        seg, det = got["seg"], got["det"]
        for k, i in enumerate(idx):
            out[i] = (float(seg[k]), float(det[k]))
    return out


def _seed_text(drives) -> str:
    seeds = sorted({d.scene.seed for d in drives})
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(str(s) for s in seeds)


def _route_intervals(args, pool, psog, backend, lidar, names, placements, rows, body) -> dict | None:
    """{task: Jackknife} over the pooled drives (each left out once, stratified by scene, t quantiles);
    None where no scene has two routes. Point estimates are the printed scores; ``ci`` and ``pairwise``
    are added to each row."""
    from place3d_kernels.uncertainty import jackknife_records, pairwise, route_df

    pooled, strata, _ = pool
    df = route_df(len(pooled), strata)
    if df < 1:
        print("no intervals: every scene has one route (an interval over routes needs two in some scene)",
              file=sys.stderr)
        return None
    order = [r["placement"] for r in rows]
    by_name = {(pl.name or n): pl for n, pl in zip(names, placements)}
    point = {t: [r[f"msog_{t}"] for r in rows] for t in ("seg", "det")}
    with section("jackknife over routes: rescoring"):
        boots = jackknife_records(pooled, pooled.grid, lidar, {n: by_name[n] for n in order}, ("seg", "det"),
                                  args.occlusion, backend, point=point, unit="drives", progress=not args.quiet,
                                  normalisation=args.normalisation, body=body, reference=psog, strata=strata, df=df)
    with section("intervals: bounds and pairwise order"):      # SciPy's t distribution is imported here
        pw = {t: pairwise(bt) for t, bt in boots.items()}
        for i, r in enumerate(rows):
            r["ci"] = {t: boots[t].ci[i].tolist() for t in boots}
            r["pairwise"] = {t: pw[t][r["placement"]] for t in boots}
    return boots


def _evaluate_bootstrap(args, spec, backend, lidar, names, placements, rows) -> dict:
    """{task: Jackknife | Bootstrap} over the subsets of the evaluated drive; point estimates are the printed
    scores (bit-identical), ``ci`` and ``pairwise`` are added to each row."""
    from place3d_kernels.subset_records import keyed_subset_records
    from place3d_kernels.uncertainty import bootstrap_records, jackknife_records, pairwise, too_few_subsets

    if args.resamples < 0:
        raise ValueError(f"--resamples must be >= 0 (0 switches the intervals off), got {args.resamples}")
    with section("bootstrap: subset records"):
        records, pool_key = keyed_subset_records(spec, backend, cache=not args.no_cache)
    if too_few_subsets(len(records)):
        raise ValueError(f"{too_few_subsets(len(records))}; use more --frames or --interval none")
    order = [r["placement"] for r in rows]
    by_name = {(pl.name or n): pl for n, pl in zip(names, placements)}
    point = {t: [r[f"msog_{t}"] for r in rows] for t in ("seg", "det")}
    chosen = {n: by_name[n] for n in order}
    with section(f"{args.interval}: rescoring"):
        if args.interval == "jackknife":
            boots = jackknife_records(records, spec.grid.grid(), lidar, chosen, ("seg", "det"), args.occlusion,
                                      backend, point=point, progress=not args.quiet,
                                      normalisation=args.normalisation, body=spec.vehicle_body(),
                                      pool_key=pool_key)
        else:
            boots = bootstrap_records(records, spec.grid.grid(), lidar, chosen, ("seg", "det"), args.occlusion,
                                      args.resamples, args.resample_seed, backend, point=point,
                                      progress=not args.quiet, normalisation=args.normalisation,
                                      body=spec.vehicle_body())
    pw = {t: pairwise(bt) for t, bt in boots.items()}
    for i, r in enumerate(rows):
        r["ci"] = {t: boots[t].ci[i].tolist() for t in boots}
        r["pairwise"] = {t: pw[t][r["placement"]] for t in boots}
    return boots


def _print_intervals(rows, boots, det_rank) -> None:
    """The ranked table with intervals; '~' marks a row whose order with the row above is within noise."""
    import numpy as np

    from place3d_kernels.uncertainty import NOISE_LEVEL

    seg, det = boots["seg"], boots["det"]
    f = seg.order_freq
    lvl = f"{int(seg.level * 100)} % interval"
    print(f"   {'rank':>4}  {'placement':14s} {'M-SOG seg':>12s} {lvl:>24s} {'M-SOG det':>12s} {lvl:>24s}")
    for i, r in enumerate(rows):
        mark = "~" if i > 0 and f[i - 1, i] < NOISE_LEVEL else " "
        cs, cd = seg.ci[i], det.ci[i]
        print(f"{mark}  {i + 1:>4}  {r['placement']:14s} {r['msog_seg']:12.6f} [{cs[0]:10.6f}, {cs[1]:10.6f}] "
              f"{r['msog_det']:12.6f} [{cd[0]:10.6f}, {cd[1]:10.6f}]   (det rank {det_rank[r['placement']]})")
    if getattr(seg, "method", "bootstrap") == "jackknife" and seg.unit == "drives":
        print(f"intervals: jackknife over the {seg.n_units} pooled routes (each left out once, stratified by scene), "
              f"point +- {seg._z():.2f} se (t, {seg.df} df): the expected score of a pool of this many routes; "
              f"'~': P(order with the row above holds) < {NOISE_LEVEL:.2f}")
    elif getattr(seg, "method", "bootstrap") == "jackknife":
        print(f"intervals: delete-one-subset jackknife over the drive's {seg.n_units} subsets, point +- "
              f"{seg._z():.2f} se (within one drive: narrower than over routes); '~': P(order with the row above "
              f"holds) < {NOISE_LEVEL:.2f}, from the jackknife se of the difference")
    else:
        print(f"intervals: percentile bootstrap, {len(seg.samples)} resamples of the drive's {seg.n_units} subsets "
              f"(within one drive: narrower than over routes); '~': order with the row above holds in < "
              f"{int(NOISE_LEVEL * 100)} % of resamples")
    outside = sum(int(not lo <= x <= hi) for x, (lo, hi) in zip(seg.point, seg.ci))
    if outside:
        # entropy is concave: a resample repeats subsets, pools fewer distinct ones and scores higher, so the
        # percentile interval can sit above the full drive's score (intervals.Bootstrap.bias)
        print(f"note: {outside} of {len(rows)} seg scores lie outside their interval (bootstrap bias, mean "
              f"{float(np.nanmean(seg.bias)):+.6f}: resamples repeat subsets and pool fewer distinct ones); read "
              f"the intervals as spread and the pairwise orders as the ranking's stability")
    for t, bt in boots.items():
        pairs = bt.within_noise()
        text = ", ".join(f"{a} > {b} ({p:.2f})" for a, b, p in pairs[:8]) or "none"
        if len(pairs) > 8:
            text += f", and {len(pairs) - 8} more pairs (all in --output's bootstrap.within_noise)"
        print(f"within noise ({t}, P(order holds) < {NOISE_LEVEL:.2f}): {text}")


def _bootstrap_summary(args, boots) -> dict:
    seg = boots["seg"]
    if seg.unit == "drives":
        method = ("jackknife over the pooled routes, each left out once, stratified by scene (rows: ci = point +- "
                  "t(df) se; pairwise[task][B] = T_df(d / se_d), d = row - B, se_d the jackknife se of the difference)")
    elif args.interval == "jackknife":
        method = ("delete-one-subset jackknife of the drive (rows: ci = point +- z se; pairwise[task][B] = "
                  "Phi(d / se_d), d = row - B, se_d the jackknife se of the difference)")
    else:
        method = ("percentile bootstrap over the subsets of the drive (rows: ci = [lo, hi], pairwise[task][B] = "
                  "P(row > B), ties count one half)")
    return {"unit": seg.unit, "n_units": seg.n_units,
            "n_resamples": int(args.resamples) if args.interval == "bootstrap" else seg.n_units,
            "seed": args.resample_seed, "level": seg.level, "method": method, "interval": args.interval,
            "df": getattr(seg, "df", None),
            "within_noise": {t: [list(p) for p in bt.within_noise()] for t, bt in boots.items()},
            "se": {t: dict(zip(bt.names, bt.se.tolist())) for t, bt in boots.items()},
            "bias": {t: dict(zip(bt.names, bt.bias.tolist())) for t, bt in boots.items()}}
