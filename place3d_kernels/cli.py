"""The ``place3d`` command: backends | evaluate | simulate | optimize | study | reproduce | bench."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

from place3d_kernels.profiling import profile, section


__all__ = ["main"]


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", default=None,
                   help="reference | warp[:cpu|:cuda:N] | opencl[:platform] | auto (default: $PLACE3D_BACKEND or auto)")
    p.add_argument("--scene", default="town",
                   help="scene: 'town' (the embedded procedural town), 'opendrive:PATH' (e.g. a CARLA .xodr map), "
                        "'mesh:PATH' (a mesh file trimesh reads or a Mitsuba XML; see --labels, --route) or "
                        "'semantickitti:DIR' (labelled frames + poses.txt: the P-SOG is built from them)")
    p.add_argument("--labels", default=None,
                   help="mesh scenes: TOML label map (part name -> class) or one class for the whole file")
    p.add_argument("--route", default=None,
                   help="mesh scenes: ego poses, one per line: 'x y z roll pitch yaw' or 'x y yaw' (m, rad)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--frames", type=int, default=40, help="frames along the ego route (default 40, as the paper)")
    p.add_argument("--voxel-size", type=float, default=None, help="ROI voxel size in metres (default 0.2)")
    p.add_argument("--no-cache", action="store_true", help="rebuild the P-SOG even if a cached one exists")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--condition", default=None,
                   help="adverse condition on the simulated frames: fog, wet_ground, snow, motion_blur, crosstalk, "
                        "incomplete_echo (paper settings unless --severity/--param)")
    p.add_argument("--severity", default=None, choices=["light", "moderate", "heavy"], help="condition severity")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="condition parameter, e.g. --param alpha=0.03 (repeatable)")
    p.add_argument("--vehicle", default=None, metavar="car|suv|van|truck|none|PATH",
                   help="ego vehicle body blocking the rays of the collection LiDAR (P-SOG) and of the scored "
                        "rigs: a preset or a mesh file in the ego frame. Default none, the paper's setting (no "
                        "body), so the paper's numbers reproduce; optimize: giving it selects real-rig mode, "
                        "whose default is car")


def _check_output_file(path, suffixes=(".json",), what="--output") -> None:
    """An output file path the writer can produce: the right extension, not an existing folder."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{what} {p} is a folder; give a file path ending in {' or '.join(suffixes)}")
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{what} {p}: only {' or '.join(suffixes)} is written; use e.g. {p.with_suffix(suffixes[0])}")


def _check_output_dir(path, what="--output") -> None:
    if path is not None and Path(path).exists() and not Path(path).is_dir():
        raise ValueError(f"{what} {path} is an existing file; give a folder")


def _psog(spec, args, backend, with_scene: bool = True):
    """(scene, P-SOG) of ``spec`` built with ``backend`` (the local path), honouring --no-cache / --quiet.

    Raises ``ValueError`` for a P-SOG without entropy (every voxel a single class: fewer than two subsets),
    on which every rig would score 0.
    """
    from place3d_kernels.pipeline import check_entropy
    from place3d_kernels.subset_records import records_aggregator

    t = time.perf_counter()
    # on a cache miss the P-SOG is pooled from per-subset records kept on disk, so the intervals find
    # them instead of simulating the same frames again
    aggregate = None if args.no_cache else records_aggregator(spec)
    with section("P-SOG (cache or build)"):
        # the new P-SOG's file is written on a thread while the command goes on (main waits for it at the end),
        # unless Ray workers will read it from the cache meanwhile
        local = getattr(args, "executor", "local") == "local" and not getattr(args, "ray_address", None)
        psog = spec.build(backend=backend, cache=not args.no_cache, progress=not args.quiet, aggregate=aggregate,
                          save_in_background=local)
    check_entropy(psog, spec.frames_per_subset)
    if not args.quiet:
        print(f"P-SOG ready in {time.perf_counter() - t:.1f} s: {psog}", file=sys.stderr)
    if not with_scene or spec.scene.kind == "semantickitti":
        return None, psog       # a cached P-SOG was found without building the scene (scene.keymemo)
    with section("scene build"):
        return spec.scene.build(), psog


# ---------------------------------------------------------------------------------------- commands
def cmd_backends(args) -> int:
    from place3d_kernels.backends.registry import backend_report

    for name, ok, note in backend_report():
        print(f"{'available' if ok else 'missing':10s} {name:16s} {note}")
    return 0


def cmd_evaluate(args) -> int:
    from tqdm import tqdm

    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import PAPER_PLACEMENTS, Placement
    from place3d_kernels.spec import specs_from_args

    t0 = time.perf_counter()
    _check_output_file(args.output)
    spec = specs_from_args(args)
    spec.prefetch_scene(cache=not args.no_cache)     # the scene is built on another core during the probe
    b = get_backend(args.backend)
    lidar = LidarModel.load(args.lidar)
    names = args.placements or list(PAPER_PLACEMENTS)
    placements = [Placement.load(n) for n in names]
    body = spec.vehicle_body()
    _, psog = _psog(spec, args, b)
    rows = []
    for name, pl in tqdm(list(zip(names, placements)), desc="evaluate", unit="placement", disable=args.quiet,
                         leave=False):
        seg = float(msog_batch(psog, lidar, pl.poses[None], args.occlusion, "seg", b, normalisation=args.normalisation,
                               body=body)[0])
        det = float(msog_batch(psog, lidar, pl.poses[None], args.occlusion, "det", b, normalisation=args.normalisation,
                               body=body)[0])
        rows.append({"placement": pl.name or name, "msog_seg": seg, "msog_det": det})
    rows.sort(key=lambda r: -r["msog_seg"])
    boots = (_evaluate_bootstrap(args, spec, b, lidar, names, placements, rows)
             if args.resamples and args.interval != "none" else None)
    seconds = time.perf_counter() - t0
    cond = f", condition {args.condition}" if args.condition else ""
    print(f"M-SOG on scene {args.scene} (seed {args.seed}{cond}), backend {b.name}, grid {psog.grid.shape} "
          f"@ {psog.grid.voxel_size} m, occlusion {args.occlusion}, vehicle {spec.vehicle or 'none'}"
          + (f", normalisation {args.normalisation}" if args.normalisation != "paper" else "") + "; higher is better")
    det_rank = {r["placement"]: i + 1 for i, r in enumerate(sorted(rows, key=lambda r: -r["msog_det"]))}
    if boots is None:
        print(f"{'rank':>4}  {'placement':14s} {'M-SOG seg':>12s} {'M-SOG det':>12s}")
        for i, r in enumerate(rows):
            print(f"{i + 1:>4}  {r['placement']:14s} {r['msog_seg']:12.6f} {r['msog_det']:12.6f}"
                  f"   (det rank {det_rank[r['placement']]})")
    else:
        _print_intervals(rows, boots, det_rank)
    print(f"{seconds:.1f} s")
    if args.output:
        from place3d_kernels.manifest import provenance

        out = {"rows": rows, "backend": b.name, "grid": psog.grid.to_dict(), "seconds": seconds,
               "scene": spec.scene.to_dict(), "occlusion": args.occlusion, "lidar": lidar.name,
               "condition": None if spec.condition is None else spec.condition.to_dict(),
               "psog": spec.to_dict(), "n_subsets": psog.n_subsets, "seed": args.seed,
               "normalisation": args.normalisation, "vehicle": None if body is None else
               {"name": body.name, "key": body.key, "bounds_m": body.bounds.round(4).tolist()},
               "provenance": provenance(backend=b.name)}
        if boots is not None:
            out["bootstrap"] = _bootstrap_summary(args, boots)
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(args.output, json.dumps(out, indent=2))
    plot = args.plot or (str(Path(args.output).with_suffix(".png")) if args.output and boots else None)
    if plot and boots is not None:
        from place3d_kernels.uncertainty import plot_scores

        with section("plotting"):
            plot_scores({f"M-SOG {t} ({args.scene}, seed {args.seed}{cond})": boots[t] for t in ("seg", "det")},
                        plot, title=f"M-SOG of {len(rows)} placements, {int(boots['seg'].level * 100)} % bootstrap "
                                    f"intervals over the drive's subsets")
        if not args.quiet:
            print(f"wrote {plot}", file=sys.stderr)
    return 0


def _evaluate_bootstrap(args, spec, backend, lidar, names, placements, rows) -> dict:
    """{task: Jackknife | Bootstrap} over the subsets of the evaluated drive; point estimates are the printed
    scores (bit-identical), ``ci`` and ``pairwise`` are added to each row."""
    from place3d_kernels.subset_records import keyed_subset_records
    from place3d_kernels.uncertainty import bootstrap_records, jackknife_records, pairwise

    if args.resamples < 0:
        raise ValueError(f"--resamples must be >= 0 (0 switches the intervals off), got {args.resamples}")
    with section("bootstrap: subset records"):
        records, pool_key = keyed_subset_records(spec, backend, cache=not args.no_cache)
    if len(records) < 2:
        raise ValueError(f"intervals need at least 2 subsets, the drive has {len(records)}; use more "
                         f"--frames or --interval none")
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
    if getattr(seg, "method", "bootstrap") == "jackknife":
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
        # percentile interval can sit above the full drive's score (uncertainty.Bootstrap.bias)
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
    if args.interval == "jackknife":
        method = ("delete-one-subset jackknife of the drive (rows: ci = point +- z se; pairwise[task][B] = "
                  "Phi(d / se_d), d = row - B, se_d the jackknife se of the difference)")
    else:
        method = ("percentile bootstrap over the subsets of the drive (rows: ci = [lo, hi], pairwise[task][B] = "
                  "P(row > B), ties count one half)")
    return {"unit": seg.unit, "n_units": seg.n_units,
            "n_resamples": int(args.resamples) if args.interval == "bootstrap" else seg.n_units,
            "seed": args.resample_seed, "level": seg.level, "method": method, "interval": args.interval,
            "within_noise": {t: [list(p) for p in bt.within_noise()] for t, bt in boots.items()},
            "se": {t: dict(zip(bt.names, bt.se.tolist())) for t, bt in boots.items()},
            "bias": {t: dict(zip(bt.names, bt.bias.tolist())) for t, bt in boots.items()}}


def cmd_simulate(args) -> int:
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.io import prepare_sequence_folder, sequence_spec, write_sequence_metadata
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.simulate import DEFAULT_MOUNT
    from place3d_kernels.spec import specs_from_args

    spec = specs_from_args(args)
    meta = sequence_spec(spec.scene.to_dict(), LidarModel.load(args.lidar),
                         None if spec.condition is None else spec.condition.to_dict(), DEFAULT_MOUNT)
    body = spec.vehicle_body()
    if body is not None:
        # a sequence made with another body is another sequence (prepare_sequence_folder compares specs)
        meta["vehicle"] = {"name": body.name, "key": body.key}
    distributed = getattr(args, "executor", "local") == "ray" or getattr(args, "ray_address", None)
    if distributed and body is not None:
        raise ValueError(f"--vehicle {spec.vehicle} is not supported with --executor ray yet; simulate locally "
                         f"(drop --executor/--ray-address) or drop --vehicle")
    prepare_sequence_folder(args.output, meta, overwrite=args.overwrite)
    if distributed:
        from place3d_kernels.distributed import executor_from_args, simulate_to_folder

        ex = executor_from_args(args)
        try:
            r = simulate_to_folder(spec.scene, args.lidar, args.output, ex, chunk=args.chunk or 8,
                                   backend=args.backend, condition=spec.condition, overwrite=args.overwrite)
        finally:
            ex.shutdown()
        print(f"wrote {r['written']} frames ({r['skipped']} already there) to {r['out']} in {r['seconds']:.1f} s "
              f"on {ex.kind}")
        return 0
    from place3d_kernels.io import write_semantickitti_sequence
    from place3d_kernels.simulate import simulate

    b = get_backend(args.backend)
    frames = simulate(spec.scene.build(), args.lidar, backend=b, progress=not args.quiet, body=body)
    if spec.condition is not None:
        cond = spec.condition.condition(b)
        frames = [cond(f, i) for i, f in enumerate(frames)]
    out = write_semantickitti_sequence(frames, args.output)
    write_sequence_metadata(out, meta)
    print(f"wrote {len(frames)} frames to {out}")
    return 0


def cmd_bench(args) -> int:
    from place3d_kernels.kernel_bench import format_table, run_kernel_bench

    _check_output_file(args.output)
    res = run_kernel_bench(backends=args.backends, quick=args.quick, progress=not args.quiet)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(format_table(res))
    if args.output:
        from place3d_kernels.manifest import provenance

        res["provenance"] = provenance()
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(args.output, json.dumps(res, indent=2))
        print(f"wrote {args.output}")
    return 0


def cmd_study(args) -> int:
    from place3d_kernels.study import run as run_study

    return run_study(args)


def cmd_optimize(args) -> int:
    from place3d_kernels.optimize.cli import run as run_optimize
    from place3d_kernels.spec import specs_from_args

    from place3d_kernels.rig_cli import wants_rig_mode

    if wants_rig_mode(args) and args.vehicle is None:
        # real-rig mode scores on a car by default; the P-SOG is collected from the same body
        args.vehicle = "car"
    spec = specs_from_args(args)
    spec.prefetch_scene(cache=not args.no_cache)     # the scene is built on another core during the probe
    return run_optimize(args, spec, psog_for=lambda backend: _psog(spec, args, backend, with_scene=False))


def cmd_serve(args) -> int:
    from place3d_kernels.serve import serve

    return serve(args, command=main, warm=build_parser)


# ---------------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    from place3d_kernels import __version__

    ap = argparse.ArgumentParser(prog="place3d", description="Multi-LiDAR placement kernels (Place3D metric and optimiser)",
                                 epilog="place3d --server[=SOCKET] COMMAND ... (or PLACE3D_SERVER=1) runs the command in "
                                        "a warm 'place3d serve' process if one is running, here otherwise")
    ap.add_argument("--version", action="version", version=f"place3d-kernels {__version__}")
    ap.add_argument("--profile", action="store_true",
                    help="print where the command's time went (sections: backend probe, scene, P-SOG, scoring, "
                         "CMA-ES, plotting, writing) on stderr at the end")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("backends", help="list available backends and why others are missing")
    p.set_defaults(func=cmd_backends)

    from place3d_kernels.lidar_cli import add_lidars_parser

    add_lidars_parser(sub)

    from place3d_kernels.blindspot import add_blindspot_parser

    add_blindspot_parser(sub)

    p = sub.add_parser("evaluate", help="score the paper's placements by M-SOG on a scene")
    _add_common(p)
    p.add_argument("placements", nargs="*", help="placement names or TOML paths (default: all eleven)")
    p.add_argument("--lidar", default="place3d_16ch", help="LiDAR model name or TOML (default place3d_16ch)")
    p.add_argument("--occlusion", default="sog", choices=["sog", "none"], help="ray occlusion mode (default sog)")
    p.add_argument("--output", help="write the table as JSON to this path")
    p.add_argument("--normalisation", default="paper", choices=["paper", "evidence", "uncertain"],
                   help="M-SOG denominator (docs/metric-normalisation.md): 'paper' (default), 'evidence', 'uncertain'")
    p.add_argument("--interval", default="jackknife", choices=["jackknife", "bootstrap", "none"],
                   help="95 %% intervals and pairwise orders over the drive's subsets: 'jackknife' (default; one "
                        "rescoring per subset, unbiased for the full drive), 'bootstrap' (--resamples draws; its "
                        "resamples repeat subsets and score high, see docs/commands.md), or 'none'")
    p.add_argument("--resamples", type=int, default=200,
                   help="bootstrap resamples (with --interval bootstrap; default 200; 0 switches intervals off)")
    p.add_argument("--resample-seed", type=int, default=0, help="seed of the bootstrap resampling (default 0)")
    p.add_argument("--plot", default=None,
                   help="PNG of the scores with their intervals (default with --output: next to it, same stem)")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("simulate", help="simulate semantic LiDAR frames (SemanticKITTI layout)")
    _add_common(p)
    p.add_argument("--lidar", default="collection_64ch", help="LiDAR model (default collection_64ch)")
    p.add_argument("--output", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a sequence in --output made with other settings (deletes velodyne/, labels/, "
                        "poses.txt first)")
    from place3d_kernels.distributed import add_executor_arguments

    add_executor_arguments(p)
    p.set_defaults(func=cmd_simulate)

    from place3d_kernels.study import add_arguments as add_study

    p = sub.add_parser("study", help="M-SOG over a grid of placements x conditions x scenes (one table)")
    add_study(p)
    p.set_defaults(func=cmd_study)

    from place3d_kernels import reproduce

    p = sub.add_parser("reproduce", help="the paper's eight placements on a pooled P-SOG, with intervals and Kendall tau")
    reproduce.add_arguments(p)
    p.set_defaults(func=reproduce.run)

    p = sub.add_parser("bench", help="kernel microbenchmarks per backend (a table; JSON with --json / --output)")
    p.add_argument("--backends", nargs="*", default=None, help="backends to time (default: all available)")
    p.add_argument("--quick", action="store_true", help="skip the 1M-triangle city (ray-mesh on the town only)")
    p.add_argument("--output", help="also write the results as JSON to this path")
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_bench)

    try:
        from place3d_kernels.optimize.cli import add_arguments as add_opt
    except ImportError:
        add_opt = None
    if add_opt is not None:
        p = sub.add_parser("optimize", help="optimise a placement with CMA-ES")
        _add_common(p)
        add_opt(p)
        add_executor_arguments(p)
        p.set_defaults(func=cmd_optimize)

    from place3d_kernels.serve import add_arguments as add_serve

    p = sub.add_parser("serve", help="a resident process that runs commands sent with --server, imports and "
                                     "backend already loaded")
    add_serve(p)
    p.set_defaults(func=cmd_serve)
    return ap


def asks_for_server(argv) -> bool:
    """Whether ``--server`` (``--server=PATH``) comes before the subcommand, as ``place3d_client`` reads it."""
    for a in argv:
        if a == "--server" or a.startswith("--server="):
            return True
        if not a.startswith("-"):
            return False
    return False


def _wait_for_saves() -> None:
    # a P-SOG the command built is written on a thread (scene_psog(save_in_background=True)); the command
    # ends when it is on disk, so a caller that runs commands in-process (tests, place3d serve) finds it
    pipeline = sys.modules.get("place3d_kernels.pipeline")
    if pipeline is not None:
        with section("P-SOG save (wait)"):
            pipeline.wait_for_saves()


def main(argv=None) -> int:
    from place3d_kernels.atomic import WriteError
    from place3d_kernels.manifest import set_command_line

    if asks_for_server(sys.argv[1:] if argv is None else argv):
        # --server reached this parser (python -m place3d_kernels.cli, or a console script installed before
        # the entry point moved to place3d_client): the launcher forwards, or strips the flag and runs here
        from place3d_kernels.serve import client_wire

        try:
            client_wire()
        except ValueError as e:        # place3d_client not installed beside the package
            print(f"place3d: error: {e}", file=sys.stderr)
            return 2
        from place3d_client import main as launch

        return launch(argv)
    args = build_parser().parse_args(argv)
    set_command_line(None if argv is None else ["place3d", *argv])
    try:
        with (profile() if args.profile else contextlib.nullcontext()):
            try:
                return int(args.func(args) or 0)
            finally:
                _wait_for_saves()
    except (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, WriteError) as e:
        print(f"place3d: error: {e}", file=sys.stderr)     # one line; a full disk too (atomic.WriteError)
        return 2
    except KeyboardInterrupt:
        hint = ""
        if getattr(args, "command", None) == "optimize" and getattr(args, "checkpoint", None):
            hint = f"; resume with the same command and --resume (checkpoint {args.checkpoint})"
        print(f"place3d: interrupted{hint}", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    from place3d_client import leave     # the console script's exit (place3d_client.leave)

    leave(main())
