"""The ``place3d`` command: backends | evaluate | simulate | optimize | study | reproduce | bench."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys

from place3d_app.commands.common import add_common, check_output_file, psog_for_spec
from place3d_app.commands.evaluate import cmd_evaluate
from place3d_app.commands.simulate import cmd_simulate
from place3d_app.prefetch import start_for_spec
from place3d_kernels.profiling import profile, section


__all__ = ["main"]


def cmd_backends(args) -> int:
    from place3d_kernels.backends.registry import backend_report

    for name, ok, note in backend_report():
        print(f"{'available' if ok else 'missing':10s} {name:16s} {note}")
    return 0


def cmd_bench(args) -> int:
    from place3d_app.kernel_bench import format_table, run_kernel_bench

    check_output_file(args.output)
    res = run_kernel_bench(backends=args.backends, quick=args.quick, progress=not args.quiet)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(format_table(res))
    if args.output:
        from place3d_kernels.manifest import provenance

        res["provenance"] = provenance()
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(args.output, json.dumps(res, indent=2))
        print(f"wrote {args.output}")
    return 0


def cmd_study(args) -> int:
    from place3d_app.commands.study import run as run_study

    return run_study(args)


def cmd_optimize(args) -> int:
    from place3d_app.commands.optimize import run as run_optimize
    from place3d_kernels.spec import specs_from_args

    from place3d_app.commands.rig import wants_rig_mode

    if wants_rig_mode(args) and args.vehicle is None:
        # real-rig mode scores on a car by default; the P-SOG is collected from the same body
        args.vehicle = "car"
    from place3d_app.commands.routes import drive_specs, psog_for_routes

    spec = specs_from_args(args)
    args.drives = drive_specs(args, spec)             # scenes x route seeds, checked before any work
    start_for_spec(spec, cache=not args.no_cache, drives=len(args.drives))   # built on another core during the probe
    return run_optimize(args, spec, psog_for=lambda backend: psog_for_routes(spec, args, backend))


def cmd_serve(args) -> int:
    from place3d_app.serve import serve

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

    from place3d_app.commands.lidars import add_lidars_parser

    add_lidars_parser(sub)

    from place3d_kernels.blindspot import add_blindspot_parser

    add_blindspot_parser(sub)

    from place3d_app.commands.routes import add_route_arguments

    p = sub.add_parser("evaluate", help="score the paper's placements by M-SOG on a P-SOG pooled over routes")
    add_common(p, several_scenes=True)
    add_route_arguments(p)
    p.add_argument("placements", nargs="*", help="placement names or TOML paths (default: all eleven)")
    p.add_argument("--lidar", default="place3d_16ch", help="LiDAR model name or TOML (default place3d_16ch)")
    p.add_argument("--occlusion", default="sog", choices=["sog", "none"], help="ray occlusion mode (default sog)")
    p.add_argument("--output", help="write the table as JSON to this path")
    p.add_argument("--normalisation", default="paper", choices=["paper", "evidence", "uncertain"],
                   help="M-SOG denominator (docs/metric-normalisation.md): 'paper' (default), 'evidence', 'uncertain'")
    p.add_argument("--interval", default="jackknife", choices=["jackknife", "bootstrap", "none"],
                   help="95 %% intervals and pairwise orders: 'jackknife' (default; over the routes of a pooled "
                        "P-SOG, each left out once, or over the subsets of a single drive), 'bootstrap' (single "
                        "drive only: --resamples draws of its subsets, which repeat subsets and score high, see "
                        "docs/commands.md), or 'none'")
    p.add_argument("--resamples", type=int, default=200,
                   help="bootstrap resamples (with --interval bootstrap; default 200; 0 switches intervals off)")
    p.add_argument("--resample-seed", type=int, default=0, help="seed of the bootstrap resampling (default 0)")
    p.add_argument("--plot", default=None,
                   help="PNG of the scores with their intervals (default with --output: next to it, same stem)")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("simulate", help="simulate semantic LiDAR frames (SemanticKITTI layout)")
    add_common(p)
    p.add_argument("--lidar", default="collection_64ch", help="LiDAR model (default collection_64ch)")
    p.add_argument("--output", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a sequence in --output made with other settings (deletes velodyne/, labels/, "
                        "poses.txt first)")
    from place3d_app.executors import add_executor_arguments

    add_executor_arguments(p)
    p.set_defaults(func=cmd_simulate)

    from place3d_app.commands.study import add_arguments as add_study

    p = sub.add_parser("study", help="M-SOG over a grid of placements x conditions x scenes (one table)")
    add_study(p)
    p.set_defaults(func=cmd_study)

    from place3d_app.commands import reproduce

    p = sub.add_parser("reproduce", help="the paper's eight placements on a pooled P-SOG, with intervals and Kendall tau")
    reproduce.add_arguments(p)
    p.set_defaults(func=reproduce.run)

    from place3d_app.commands import downstream

    downstream.add_parser(sub)

    p = sub.add_parser("bench", help="kernel microbenchmarks per backend (a table; JSON with --json / --output)")
    p.add_argument("--backends", nargs="*", default=None, help="backends to time (default: all available)")
    p.add_argument("--quick", action="store_true", help="skip the 1M-triangle city (ray-mesh on the town only)")
    p.add_argument("--output", help="also write the results as JSON to this path")
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_bench)

    try:
        from place3d_app.commands.optimize import add_arguments as add_opt
    except ImportError:
        add_opt = None
    if add_opt is not None:
        p = sub.add_parser("optimize", help="optimise a placement with CMA-ES")
        add_common(p, several_scenes=True)
        add_route_arguments(p)
        add_opt(p)
        add_executor_arguments(p)
        p.set_defaults(func=cmd_optimize)

    from place3d_app.serve import add_arguments as add_serve

    p = sub.add_parser("serve", help="a resident process that runs commands sent with --server, imports and "
                                     "backend already loaded")
    add_serve(p)
    p.set_defaults(func=cmd_serve)
    return ap


def asks_for_server(argv) -> bool:
    """Whether ``--server`` (``--server=PATH``) comes before the subcommand, as ``place3d_app`` reads it."""
    for a in argv:
        if a == "--server" or a.startswith("--server="):
            return True
        if not a.startswith("-"):
            return False
    return False


def _wait_for_saves() -> None:
    # a P-SOG the command built is written on a thread (scenepsog_for_spec(save_in_background=True)); the command
    # ends when it is on disk, so a caller that runs commands in-process (tests, place3d serve) finds it
    pipeline = sys.modules.get("place3d_kernels.pipeline")
    if pipeline is not None:
        with section("P-SOG save (wait)"):
            pipeline.wait_for_saves()


def main(argv=None) -> int:
    from place3d_kernels.atomic import WriteError
    from place3d_kernels.manifest import set_command_line

    if asks_for_server(sys.argv[1:] if argv is None else argv):
        # the launcher (place3d_app.main, the console script) reads --server and runs this parser without
        # it; here, reached directly (python -m place3d_app.cli), there is no one to forward to
        print("place3d: error: --server is read by the launcher: run 'place3d --server ...' or "
              "'python -m place3d_app --server ...'", file=sys.stderr)
        return 2
    args = build_parser().parse_args(argv)
    set_command_line(None if argv is None else ["place3d", *argv])
    from place3d_app.messages import cli_output

    quick = sys.modules.get("place3d_app.quick_return")
    if args.profile and quick is not None and quick.waiting_parent() is not None:
        from place3d_kernels.profiling import count_start_up_of

        count_start_up_of(quick.waiting_parent())     # the start-up line counts from the console script's start
    try:
        # warnings and the library's log lines print as one line each (only those that matter under --quiet)
        with cli_output(quiet=bool(getattr(args, "quiet", False))), \
                (profile() if args.profile else contextlib.nullcontext()):
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
    sys.exit(main())
