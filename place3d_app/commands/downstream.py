"""``place3d downstream``: train segmentation models on each rig's simulated data and compare their mIoU
with M-SOG (``place3d_kernels.downstream.study``; docs/downstream.md).

The CLI wires ``add_parser(subparsers)`` and ``run(args)``; until then::

    place3d downstream --rigs center,pyramid --towns town --frames 8 ...

Nothing here imports PyTorch: ``run`` does, through the study, and says how to install it when missing.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["add_parser", "add_arguments", "run", "dataset_executor", "format_table", "PAPER_RIGS"]

#: the eight placements of the paper's Table 1 ("ours" = the segmentation-optimised one)
PAPER_RIGS = ("center", "line", "pyramid", "square", "trapezoid", "line-roll", "pyramid-roll", "ours-seg")


def _ints(s: str) -> tuple:
    """'0,1,2' or '0-3' (inclusive) or a mix -> tuple of non-negative ints."""
    out = []
    for part in (x.strip() for x in s.split(",")):
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return tuple(out)


def _names(s: str) -> tuple:
    return tuple(x.strip() for x in s.split(",") if x.strip())


def add_arguments(p) -> None:
    p.add_argument("--rigs", type=_names, default=PAPER_RIGS,
                   help="comma-separated placements: shipped names or placement TOML paths (default: the paper's eight)")
    p.add_argument("--lidar", default="place3d_16ch", help="the rigs' LiDAR model (default: place3d_16ch)")
    p.add_argument("--towns", type=_names, default=("Town01", "Town03", "Town04"),
                   help="training towns: 'town' (embedded), CARLA maps (Town01, ...) or .xodr paths")
    p.add_argument("--heldout-towns", type=_names, default=("Town06",),
                   help="towns only tested on (comma-separated; '' for none)")
    p.add_argument("--train-routes", type=_ints, default=(0, 1, 2, 3), help="route seeds to train on: '0,1,2' or '0-3'")
    p.add_argument("--test-routes", type=_ints, default=(100, 101), help="route seeds to test on (disjoint from training)")
    p.add_argument("--frames", type=int, default=40, help="frames per route (0.5 s apart)")
    p.add_argument("--models", type=_names, default=("bev",), help="bev, range or both ('bev,range')")
    p.add_argument("--steps", type=int, default=400, help="optimiser steps per model (the same for every rig)")
    p.add_argument("--seeds", type=_ints, default=(0, 1, 2), help="training seeds (>= 3 for an interval)")
    p.add_argument("--batch-size", type=int, default=4, help="frames per step")
    p.add_argument("--lr", type=float, default=3e-3, help="peak learning rate (AdamW)")
    p.add_argument("--bev-cells", type=int, default=None, help="BEV grid cells per side (default 256)")
    p.add_argument("--width", type=int, default=None, help="U-Net first-stage channels (default 32)")
    p.add_argument("--depth", type=int, default=None, help="U-Net stages (default 4)")
    p.add_argument("--range-shape", default=None, help="range image ROWSxCOLS (default 64x512)")
    p.add_argument("--resamples", type=int, default=1000, help="bootstrap resamples for the intervals")
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: cuda when available)")
    p.add_argument("--threads", type=int, default=None, help="PyTorch CPU threads (default: PyTorch's)")
    p.add_argument("--backend", default=None, help="ray-cast backend for the simulation and M-SOG "
                   "(default: $PLACE3D_BACKEND or auto; the reference backend is far too slow for this)")
    p.add_argument("--workers", type=int, default=0,
                   help="processes that build scenes and simulate drives at once (0: in this process; with "
                        "--executor local or process)")
    # the executor options of simulate/optimize/study (place3d_app.executors), for the dataset tasks
    p.add_argument("--executor", default="local", choices=["auto", "local", "process", "ray"],
                   help="where the dataset tasks (one per drive) run: local (this process, or --workers "
                        "processes), process (one worker process per usable core, at most $PLACE3D_WORKERS, or "
                        "--workers), ray (a Ray cluster; needs pip install 'place3d-kernels[dist]'), auto "
                        "(process where there are several drives and more than one usable core, else local; "
                        "default local)")
    p.add_argument("--ray-address", default=None,
                   help="Ray cluster to join: auto | HOST:PORT | ray://HOST:10001 (default: start a local one)")
    p.add_argument("--num-cpus", type=int, default=None, help="CPUs of a local Ray cluster (default: all)")
    p.add_argument("--gpus-per-task", type=float, default=0,
                   help="GPUs each Ray task requests (default 0; Ray hides the GPUs from a task that asks for "
                        "none, so give a share, e.g. 0.125, with a GPU backend)")
    p.add_argument("--output", required=True, help="study folder (datasets/, cells/, results.json, plot)")
    p.add_argument("--data", default=None, help="dataset folder to share between studies (default: OUTPUT/datasets)")
    p.add_argument("--overwrite", action="store_true", help="rebuild datasets and cells instead of resuming")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def add_parser(subparsers):
    p = subparsers.add_parser("downstream", help="train segmentation models per rig; mIoU against M-SOG, Kendall tau")
    add_arguments(p)
    p.set_defaults(func=run)
    return p


def config_from_args(args):
    from place3d_kernels.downstream.dataset import Splits
    from place3d_kernels.downstream.study import StudyConfig

    model = {k: v for k, v in (("bev_cells", args.bev_cells), ("width", args.width), ("depth", args.depth))
             if v is not None}
    if args.range_shape:
        r, c = args.range_shape.lower().split("x")
        model["range_shape"] = (int(r), int(c))
    splits = Splits(tuple(args.towns), tuple(args.train_routes), tuple(args.test_routes), int(args.frames),
                    tuple(args.heldout_towns))
    if len(args.seeds) < 1 or args.steps < 1:
        raise ValueError("give at least one seed and one step")
    return StudyConfig(tuple(args.rigs), splits, args.lidar, tuple(args.models), tuple(args.seeds), int(args.steps),
                       model, {"batch_size": int(args.batch_size), "lr": float(args.lr)}, resamples=int(args.resamples))


def dataset_executor(args, n_drives: int):
    """(workers, executor) for ``run_study``: ``--workers N`` alone keeps the local worker processes
    (``build_datasets``'s own pool); ``--executor process|ray|auto`` gives a ``place3d_app.executors``
    executor, as ``simulate``, ``optimize`` and ``study`` choose theirs. ``ValueError`` for a bad mix."""
    kind = getattr(args, "executor", "local") or "local"
    workers = int(getattr(args, "workers", 0) or 0)
    address = getattr(args, "ray_address", None)
    if workers < 0:
        raise ValueError(f"--workers must be >= 0, got {workers}")
    if (kind == "ray" or address) and workers:
        raise ValueError("--workers counts local processes; with --executor ray size a local cluster with "
                         "--num-cpus instead")
    if kind == "local" and not address:
        return workers, None
    if kind in ("process", "auto") and workers:
        from place3d_app.executors import ProcessExecutor

        return 0, ProcessExecutor(min(workers, max(n_drives, 1)), backend=str(args.backend or "auto"), prestart=True)
    from place3d_app.executors import executor_from_args

    return 0, executor_from_args(args, tasks=n_drives, backend=args.backend)


def run(args) -> int:
    try:
        import torch
    except ImportError:
        print("place3d downstream needs PyTorch: pip install 'place3d-kernels[downstream]' (or torch>=2.1)",
              file=sys.stderr)
        return 2
    from place3d_kernels.downstream.study import run_study

    try:
        cfg = config_from_args(args)
        workers, executor = dataset_executor(args, len(cfg.splits.all_drives()))
    except ValueError as e:
        print(f"place3d downstream: {e}", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(int(args.threads))
    try:
        res = run_study(cfg, args.output, args.backend, args.device, progress=not args.quiet,
                        overwrite=args.overwrite, data=args.data, workers=workers, executor=executor)
    finally:
        if executor is not None:
            executor.shutdown()
    print(format_table(res))
    t = res["timing"]
    print(f"{res['cells_run']} cells trained, {res['cells_skipped']} resumed; datasets {t['dataset_seconds']:.1f} s, "
          f"(wall {t['datasets_wall_seconds']:.1f} s), P-SOG {t['psog_seconds']:.1f} s, cells {t['cells_seconds']:.1f} s, total {t['total_seconds']:.1f} s on "
          f"{res['machine'].get('gpu', res['machine']['device'])}; wrote {args.output}/results.json and {res['plot']}")
    return 0


def format_table(res: dict) -> str:
    lines = []
    for model, splits in res["table"].items():
        for split, t in splits.items():
            norms = list(t["tau"])
            lines.append(f"{model} / {split} ({t['drives']} drives, {len(t['classes'])} classes):")
            lines.append(f"  {'rig':16s} {'mIoU %':>7s} {'95 % interval':>15s}  " + " ".join(f"{'M-SOG ' + n:>16s}" for n in norms))
            for r in sorted(t["rows"], key=lambda r: -r["miou"]):
                lines.append(f"  {r['rig']:16s} {100 * r['miou']:7.2f} [{100 * r['lo']:5.2f}, {100 * r['hi']:5.2f}]  "
                             + " ".join(f"{r['msog'][n]:16.6f}" for n in norms))
            for n, tau in t["tau"].items():
                lines.append(f"  Kendall tau (M-SOG {n} vs mIoU): {tau['tau']:+.3f} [{tau['lo']:+.3f}, {tau['hi']:+.3f}], "
                             f"P(tau > 0) = {tau['p_positive']:.2f}")
            for cls, o in t.get("objects", {}).items():
                th = o["thresholds"]
                lines.append(f"  {cls} recall (detection proxy: found with >= {th['detect_min_points']} points and "
                             f">= {100 * th['detect_min_share']:.0f} % of them predicted {cls}; {o['objects']} objects):")
                for r in sorted(o["rows"], key=lambda r: -r["recall"] if r["recall"] == r["recall"] else 1):
                    lines.append(f"    {r['rig']:16s} {100 * r['recall']:6.2f} [{100 * r['lo']:5.2f}, "
                                 f"{100 * r['hi']:5.2f}]  seen {100 * r['seen']:5.1f} %")
                for n, tau in o["tau"].items():
                    lines.append(f"    Kendall tau (M-SOG {n} vs {cls} recall): {tau['tau']:+.3f} [{tau['lo']:+.3f}, "
                                 f"{tau['hi']:+.3f}], P(tau > 0) = {tau['p_positive']:.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="place3d downstream", description=__doc__.split("\n\n")[0])
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
