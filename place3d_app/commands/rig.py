"""``place3d optimize`` for real rigs: several sensor models, mounting surfaces on a body, cost.

Chosen when any of ``--n-lidars``, ``--sensors``, ``--surfaces``, ``--vehicle``, ``--dofs`` or
``--objective pareto`` is given. Every input is checked before the P-SOG is built, and nothing is written
unless the run succeeds (bad input: exit 2 and one line on stderr).

Writes to ``--output``: ``result.json`` (best rig, per sensor combination, blind spots, cost),
``rig.toml`` (a placement TOML whose ``[[lidar]]`` poses ``place3d blindspot`` and ``Placement.load``
read, plus ``[[mount]]`` tables: sensor, surface, u, v, w), ``rig.png`` (top and side views, body to
scale), ``blindspot.png``; with ``--objective pareto`` also ``pareto.json`` and ``pareto.png``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

__all__ = ["add_rig_arguments", "wants_rig_mode", "check_rig_args", "run_rig", "plot_rig_on_body", "plot_pareto"]


def add_rig_arguments(p) -> None:
    """The real-rig options of ``place3d optimize``."""
    g = p.add_argument_group("real rigs (issue 16)")
    g.add_argument("--n-lidars", type=int, default=None, help="LiDARs per rig, 1-8 (real-rig mode)")
    g.add_argument("--sensors", default=None,
                   help="comma-separated LiDAR presets or TOML files the slots choose from, e.g. vlp16,os1-64")
    g.add_argument("--surfaces", default=None,
                   help="comma-separated mounting surfaces: roof, front-bumper, rear-bumper, left-fender, "
                        "right-fender, left-a-pillar, right-a-pillar, roof-box (the paper's box); default roof")
    g.add_argument("--dofs", default=None,
                   help="optimised DOFs per LiDAR: x,y,z (= surface u,v,w), roll, pitch, yaw (default "
                        "x,y,z,pitch,yaw)")
    # --vehicle is a common option (place3d_app.cli): giving it selects this mode; its default here is car
    g.add_argument("--objective", default="msog", choices=["msog", "pareto"],
                   help="msog: best rig; pareto: the front of M-SOG against cost and sensor count")
    g.add_argument("--prices", default=None, help="price TOML (default: the shipped illustrative list prices)")
    g.add_argument("--max-blind-extent", type=float, default=None, metavar="M",
                   help="constraint: no ground blind spot reaching more than M metres from the body (at --blind-z)")
    g.add_argument("--blind-z", type=float, default=0.0, help="plane height of the blind-spot map and constraint, m "
                                                              "(default 0 = road; 0.5 = bumper height)")
    g.add_argument("--azimuth-step", type=int, default=1,
                   help="keep every K-th azimuth step of spinning sensors (faster, coarser; default 1 = all)")


def wants_rig_mode(args) -> bool:
    """True when the command line asks for the real-rig search."""
    return any(getattr(args, k, None) is not None for k in ("n_lidars", "sensors", "surfaces", "vehicle", "dofs")) \
        or getattr(args, "objective", "msog") == "pareto"


def _split(s, what):
    items = [t.strip() for t in str(s).split(",")]
    if not s or not any(items) or any(not t for t in items):
        raise ValueError(f"{what} is empty or has an empty entry ({s!r}); give comma-separated names")
    return list(dict.fromkeys(items))


def check_rig_args(args) -> dict:
    """Parse and check every real-rig input before any work; returns the parsed pieces.

    Raises:
        ValueError / FileNotFoundError: N out of 1-8, an unknown preset, surface or DOF, an empty list, a
            surface that reaches inside the body, a price table missing a sensor, a bad output folder.
    """
    from place3d_kernels.blindspot import vehicle_from_arg
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.mounting import surfaces_for
    from place3d_kernels.optimize.rig_search import DOF_NAMES
    from place3d_kernels.pricing import check_prices, load_prices

    # options of the roof-box search that this mode does not implement: refuse rather than ignore them
    unsupported = {"--fixed-height": getattr(args, "fixed_height", None) is not None,
                   "--restarts": getattr(args, "restarts", 0) != 0, "--pose-cache": getattr(args, "pose_cache", False),
                   "--checkpoint": getattr(args, "checkpoint", None) is not None,
                   "--resume": getattr(args, "resume", False),
                   "--x0": getattr(args, "x0", "best-baseline") != "best-baseline",
                   "--executor ray": getattr(args, "executor", "local") == "ray" or bool(getattr(args, "ray_address", None)),
                   "--holdout-seeds": getattr(args, "holdout_seeds", None) is not None,
                   "--holdout-scenes": getattr(args, "holdout_scenes", None) is not None}
    given = [k for k, v in unsupported.items() if v]
    if given:
        raise ValueError(f"{', '.join(given)} not supported with the real-rig options (--n-lidars, --sensors, "
                         f"--surfaces, --dofs, --vehicle, --objective pareto); drop them")
    n = args.n_lidars if args.n_lidars is not None else args.lidars
    if not 1 <= n <= 8:
        raise ValueError(f"--n-lidars must be 1-8, got {n}")
    if args.max_evals < 1:
        raise ValueError(f"--max-evals must be >= 1, got {args.max_evals}")
    if args.max_blind_extent is not None and not (np.isfinite(args.max_blind_extent) and args.max_blind_extent > 0):
        raise ValueError(f"--max-blind-extent must be a positive number of metres, got {args.max_blind_extent}")
    if not np.isfinite(args.blind_z):
        raise ValueError(f"--blind-z must be a finite height in metres, got {args.blind_z}")
    if args.azimuth_step < 1:
        raise ValueError(f"--azimuth-step must be >= 1, got {args.azimuth_step}")
    if args.output is not None and Path(args.output).exists() and not Path(args.output).is_dir():
        raise ValueError(f"--output {args.output} is an existing file; give a folder")
    names = _split(args.sensors if args.sensors is not None else args.lidar, "--sensors")
    sensors = {}
    for s in names:
        m = LidarModel.load(s)
        if args.azimuth_step > 1:
            if m.pattern is not None:
                raise ValueError(f"--azimuth-step applies to spinning sensors; {s!r} is a rosette unit")
            m = m.subsample(1, args.azimuth_step)
        sensors[s] = m
    dofs = tuple(_split(args.dofs if args.dofs is not None else "x,y,z,pitch,yaw", "--dofs"))
    bad = [d for d in dofs if d not in DOF_NAMES]
    if bad:
        raise ValueError(f"unknown DOF(s) {bad} in --dofs; choose from {list(DOF_NAMES)}")
    body = vehicle_from_arg(args.vehicle if args.vehicle is not None else "car")
    surf_names = _split(args.surfaces if args.surfaces is not None else "roof", "--surfaces")
    surfaces = surfaces_for(body, surf_names)
    if body is not None:
        for s in surfaces.values():
            inside = body.contains(s.corners())
            if np.any(inside):
                c = s.corners()[int(np.argmax(inside))]
                raise ValueError(f"surface {s.name!r} puts a sensor inside the vehicle body {body.name!r} (at "
                                 f"{np.round(c, 3).tolist()} m); choose surfaces outside it, or another vehicle")
    prices = None
    if args.objective == "pareto" or args.prices is not None:
        prices = load_prices(args.prices)
        check_prices(prices, names, args.prices)
    else:
        try:
            prices = load_prices(None)
            if any(s not in prices for s in names):
                prices = None                     # cost is reported only when every sensor is priced
        except (FileNotFoundError, ValueError):
            prices = None
    return {"n": n, "sensors": sensors, "dofs": dofs, "body": body, "surfaces": surfaces, "prices": prices}


def run_rig(args, spec, psog_for) -> int:
    """Run the real-rig search (see the module docstring)."""
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.blindspot import blind_spot_map
    from place3d_kernels.manifest import provenance
    from place3d_kernels.optimize.rig_search import RigProblem, search_rigs
    from place3d_kernels.pricing import pareto_front, rig_cost

    t0 = time.perf_counter()
    a = check_rig_args(args)
    from place3d_kernels.grid import check_inside

    for surf in a["surfaces"].values():
        check_inside(spec.grid.grid(), surf.corners(), f"mounting surface {surf.name!r}")
    seed = args.opt_seed if args.opt_seed is not None else args.seed
    b = get_backend(args.backend)
    _, psog = psog_for(b)
    from place3d_app.commands.common import warn_flat_objective

    warn_flat_objective(psog, args.normalisation)
    prob = RigProblem(psog, a["sensors"], a["surfaces"], a["n"], a["dofs"], a["body"], args.task, args.occlusion, b,
                      args.min_distance, args.max_blind_extent, args.blind_z, args.normalisation)
    pareto = args.objective == "pareto"
    sizes = list(range(1, a["n"] + 1)) if pareto else None
    res = search_rigs(prob, args.max_evals, seed=seed, popsize=args.popsize,
                      sigma0=args.sigma0 if args.sigma0 is not None else 0.3, sizes=sizes, progress=not args.quiet)
    best = res.best
    if not np.isfinite(best.msog):
        raise ValueError(f"no feasible rig found in {res.evaluations} evaluations ({best.reason}); raise "
                         f"--max-evals or choose other surfaces")
    lidars = [a["sensors"][s] for s in best.sensors]
    bs = blind_spot_map(a["body"], lidars, best.poses, args.blind_z, backend=b)
    prices = a["prices"]

    def cost(c):
        return None if prices is None else rig_cost(prices, c.sensors)

    seconds = time.perf_counter() - t0
    result = {"objective": args.objective, "task": args.task, "normalisation": args.normalisation,
              "best_msog": best.msog, "best": best.to_dict(),
              "best_cost_usd": cost(best), "per_combination": [dict(c.to_dict(), cost_usd=cost(c))
                                                               for c in res.per_combination],
              "search": {"mode": res.mode, "evaluations": res.evaluations, "launches": res.launches,
                         "max_evals": args.max_evals, "seed": seed, "dofs": list(a["dofs"]),
                         "azimuth_step": args.azimuth_step, "max_blind_extent_m": args.max_blind_extent,
                         "blind_z_m": args.blind_z},
              "vehicle": None if a["body"] is None else {"name": a["body"].name, "key": a["body"].key,
                                                         "bounds_m": np.round(a["body"].bounds, 4).tolist()},
              "surfaces": {k: s.to_dict() for k, s in a["surfaces"].items()},
              "sensors": {k: {"rays_per_frame": m.n_rays, "min_range_m": m.min_range, "max_range_m": m.max_range}
                          for k, m in a["sensors"].items()},
              "prices": None if prices is None else {k: prices[k] for k in a["sensors"]},
              "blind_spot": {k: v for k, v in bs.summary().items() if k != "nearest_from_body_m"},
              "scene": spec.scene.to_dict(), "grid": psog.grid.to_dict(), "seconds": seconds,
              "backend": b.name, "history": res.history, "provenance": provenance(backend=b.name)}
    front = None
    if pareto:
        cands = [c for c in res.per_combination]
        ms = np.array([c.msog for c in cands])
        costs = np.array([cost(c) for c in cands])
        counts = np.array([len(c.sensors) for c in cands], dtype=float)
        fc = pareto_front(ms, costs)
        fn = pareto_front(ms, counts)
        front = {"vs_cost": [dict(cands[i].to_dict(), cost_usd=float(costs[i])) for i in fc],
                 "vs_sensor_count": [dict(cands[i].to_dict(), cost_usd=float(costs[i])) for i in fn],
                 "all": [dict(c.to_dict(), cost_usd=float(k)) for c, k in zip(cands, costs)]}
        result["pareto"] = {"vs_cost": len(fc), "vs_sensor_count": len(fn)}

    print(f"best M-SOG ({args.task}, {args.normalisation} normalisation) {best.msog:.6f}: "
          + ", ".join(f"{s} on {f}" for s, f in zip(best.sensors, best.surfaces))
          + (f", US${cost(best):,.0f} (illustrative)" if prices is not None else "")
          + f"; {res.evaluations} rigs in {res.launches} launches, {seconds:.1f} s on {b.name}")
    print(f"blind area {bs.area_m2:.2f} m^2 within {bs.radius:g} m of the body at z = {bs.ground_z:g} m")
    if args.output is None:
        return 0
    import shutil
    import tempfile

    out = Path(args.output)
    with tempfile.TemporaryDirectory() as tmp:     # render everything first: a failure writes nothing
        files = _write_outputs(Path(tmp), result, front, best, bs, a, args)
        out.mkdir(parents=True, exist_ok=True)
        for f in files:
            shutil.move(str(Path(tmp) / f), str(out / f))
    print(f"wrote {', '.join(str(out / f) for f in files)}")
    return 0


def _write_outputs(out: Path, result, front, best, bs, a, args) -> list:
    from place3d_kernels.atomic import atomic_write_text

    atomic_write_text(out / "result.json", json.dumps(result, indent=2, default=float))
    _write_rig_toml(out / "rig.toml", best, a, args)
    plot_rig_on_body(best, a["body"], a["surfaces"], out / "rig.png",
                     title=f"Best rig on {a['body'].name if a['body'] is not None else 'no body'}: M-SOG "
                           f"{best.msog:.4f} ({args.task}, {args.normalisation})")
    bs.plot(out / "blindspot.png", title=f"Blind spots of the best rig at z = {bs.ground_z:g} m "
                                         f"({bs.area_m2:.1f} m$^2$ within {bs.radius:g} m)")
    files = ["result.json", "rig.toml", "rig.png", "blindspot.png"]
    if front is not None:
        atomic_write_text(out / "pareto.json", json.dumps(front, indent=2, default=float))
        plot_pareto(front, out / "pareto.png", args.task)
        files += ["pareto.json", "pareto.png"]
    return files


def _write_rig_toml(path, best, a, args) -> None:
    """The rig as a placement TOML (``Placement.save``'s layout) plus ``[[mount]]`` tables."""
    from place3d_kernels.placement import Placement

    note = (f"place3d optimize (real rig): M-SOG {best.msog:.6f} ({args.task}, {args.normalisation} normalisation) "
            f"on scene {args.scene}, vehicle {a['body'].name if a['body'] is not None else 'none'}\n"
            "[[lidar]] rows are a placement (Placement.load, place3d blindspot); [[mount]] rows say which sensor "
            "sits where\n(surface parameters u, v, w in [0, 1], see place3d_kernels/mounting.py)")
    Placement(best.poses, "optimized-rig").save(path, note=note)
    lines = []
    for s, f, uvw in zip(best.sensors, best.surfaces, best.uvw):
        lines += ["[[mount]]", f'sensor = "{s}"', f'surface = "{f}"'] + \
                 [f"{k} = {float(v)!r}" for k, v in zip("uvw", uvw)] + [""]
    with open(path, "a") as fh:
        fh.write("\n" + "\n".join(lines))


def plot_rig_on_body(rig, body, surfaces, path, title: str = ""):
    """Top and side views of a rig on its body, to scale: body boxes, mounting surfaces, sensors by model
    with their look direction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.0), dpi=120, gridspec_kw={"width_ratios": [1.0, 1.25]})
    boxes = [] if body is None else (body.boxes if body.boxes is not None else body.bounds[None])
    markers = ["o", "s", "D", "^", "v", "P", "X", "*"]
    models = list(dict.fromkeys(rig.sensors))
    colors = plt.cm.tab10(np.arange(len(models)) % 10)
    for ax, (i, j), lab in ((axes[0], (0, 1), "y (m, left)"), (axes[1], (0, 2), "z (m, up)")):
        for k, bx in enumerate(boxes):
            ax.add_patch(Rectangle((bx[0, i], bx[0, j]), bx[1, i] - bx[0, i], bx[1, j] - bx[0, j],
                                   facecolor="0.75", edgecolor="0.2", lw=1.0,
                                   label=f"vehicle body ({body.name})" if k == 0 else None))
        for n, s in enumerate(surfaces.values()):
            c = s.corners()
            ax.add_patch(Rectangle((c[:, i].min(), c[:, j].min()), max(np.ptp(c[:, i]), 0.02),
                                   max(np.ptp(c[:, j]), 0.02), fill=False, ls="--", lw=0.8, edgecolor="tab:green",
                                   label="allowed mounting region" if n == 0 else None))
        if j == 2:
            ax.axhline(0.0, color="0.4", lw=0.8)
        for m, mod in enumerate(models):
            sel = [q for q, s in enumerate(rig.sensors) if s == mod]
            p = rig.poses[sel]
            ax.plot(p[:, i], p[:, j], markers[m % len(markers)], color=colors[m], mec="black", ms=9, ls="",
                    label=f"{mod} ({len(sel)})")
            yaw, pitch = p[:, 5], p[:, 4]
            d = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)], 1) * 0.6
            ax.quiver(p[:, i], p[:, j], d[:, i], d[:, j], angles="xy", scale_units="xy", scale=1, width=0.004,
                      color=colors[m])
        for q, pose in enumerate(rig.poses):            # slot numbers, as listed in rig.toml
            ax.annotate(str(q + 1), (pose[i], pose[j]), textcoords="offset points", xytext=(-4, 7), fontsize=8,
                        fontweight="bold")
        ax.set_xlabel("x (m, forward)")
        ax.set_ylabel(lab)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    lo = np.min([b[0] for b in boxes] + [rig.poses[:, :3].min(0)], axis=0) - 0.8
    hi = np.max([b[1] for b in boxes] + [rig.poses[:, :3].max(0)], axis=0) + 0.8
    axes[0].set_xlim(lo[0], hi[0])
    axes[0].set_ylim(lo[1], hi[1])
    axes[1].set_xlim(lo[0], hi[0])
    axes[1].set_ylim(-0.1, hi[2])
    axes[0].set_title("top view (numbers: slots; arrows: look direction)")
    axes[1].set_title("side view, from the right")
    axes[1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.suptitle(title)
    fig.tight_layout()
    from place3d_kernels.atomic import atomic_savefig

    atomic_savefig(fig, path)
    plt.close(fig)
    return Path(path)


def plot_pareto(front: dict, path, task: str = "seg"):
    """M-SOG against rig cost and against sensor count: every sensor combination's best rig, and the
    non-dominated front."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.4), dpi=120)
    allr = [r for r in front["all"] if r["msog"] is not None]
    for ax, key, xk, xl in ((axes[0], "vs_cost", "cost_usd", "rig cost (US$, illustrative list prices)"),
                            (axes[1], "vs_sensor_count", None, "number of LiDARs")):
        def xs(rows):
            return [r[xk] if xk else len(r["sensors"]) for r in rows]

        ax.plot(xs(allr), [r["msog"] for r in allr], "o", color="0.6", ms=6,
                label="best rig of each sensor combination")
        fr = front[key]
        ax.plot(xs(fr), [r["msog"] for r in fr], "-o", color="tab:red", ms=8, mec="black", drawstyle="steps-post",
                label="Pareto front")
        for r, x in zip(fr, xs(fr)):
            ax.annotate("+".join(r["sensors"]), (x, r["msog"]), textcoords="offset points", xytext=(5, -12),
                        fontsize=7)
        ax.set_xlabel(xl)
        ax.set_ylabel(f"M-SOG ({task}, higher is better)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8, frameon=False)
    axes[1].xaxis.get_major_locator().set_params(integer=True)
    axes[0].set_title("M-SOG against cost")
    axes[1].set_title("M-SOG against sensor count")
    fig.tight_layout()
    from place3d_kernels.atomic import atomic_savefig

    atomic_savefig(fig, path)
    plt.close(fig)
    return Path(path)
