"""``place3d lidars``: the shipped LiDAR presets as a table (or JSON)."""

from __future__ import annotations

import json

from place3d_kernels.lidar import list_presets

__all__ = ["add_lidars_parser", "cmd_lidars"]


def add_lidars_parser(sub) -> None:
    """Register the ``lidars`` subcommand on an argparse subparsers object."""
    p = sub.add_parser("lidars", help="list the shipped LiDAR presets (channels, FOV, rays per frame, range, source)")
    p.add_argument("--json", action="store_true", help="print JSON rows instead of a table")
    p.set_defaults(func=cmd_lidars)


def cmd_lidars(args) -> int:
    rows = list_presets()
    if getattr(args, "json", False):
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'name':16s} {'scan':8s} {'ch':>4s} {'vertical FOV deg':>17s} {'hFOV':>6s} {'rays/frame':>10s} "
          f"{'range m':>11s}  source")
    for r in rows:
        lo, hi = r["vfov_deg"]
        print(f"{r['name']:16s} {r['scan']:8s} {r['channels']:4d} {lo:+8.2f}..{hi:+7.2f} {r['hfov_deg']:6.1f} "
              f"{r['rays_per_frame']:10,d} {r['min_range_m']:4.1f}-{r['max_range_m']:<6.0f}  {r['source']}")
    return 0
