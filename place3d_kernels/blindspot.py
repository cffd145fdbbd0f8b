"""Blind-spot map: the ground around the ego vehicle that no LiDAR ray of a rig reaches.

The rig's rays are clipped by the body (``rig_metrics.body_t_end``) and intersected with the plane
z = ``ground_z`` (0: the road; e.g. 0.5 m: bumper height). A ray *sees* the plane where it reaches it
before the body stops it. Around the car, azimuth sectors (angles about the ego origin; by default the
smallest whole number of degrees dividing 360 that is at least the LiDAR's azimuth step, ``azimuth_step_deg``,
so that every sector can get a ray: 1 degree for steps up to 1 degree, 2 for the 1.44 degrees of
place3d_16ch) take the nearest point seen in them: every point of the plane nearer than that, in the sector,
outside the body's footprint and within ``radius`` of the footprint, is blind (the near-field shadow of
the body and of the lowest beams). Gaps between channels farther out are sampling, not blind spots, and
are not counted. A sector with no hit at all is blind out to ``radius``.

The map is rasterised on square cells (0.1 m by default) for the area in m^2 and the plot; a raster that
would need more than ``MAX_RASTER_BYTES`` of memory is refused before anything is allocated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.rig_metrics import body_t_end, check_outside_body, direction_table, rig_rays
from place3d_kernels.vehicle import VehicleBody

__all__ = ["BlindSpotMap", "blind_spot_map", "ground_hits", "max_blind_extent", "footprint_distance",
           "azimuth_step_deg", "default_sector_deg", "MAX_RASTER_BYTES", "vehicle_from_arg", "cmd_blindspot",
           "add_blindspot_parser"]

#: Rasters needing more memory than this (bytes, estimated by ``_raster_bytes``) are refused with the
#: memory they would need and the cell size that fits; a 0.0001 m cell around a car needs terabytes.
MAX_RASTER_BYTES = 4 * 2**30


def _circular_step(azimuths_deg: np.ndarray) -> float | None:
    """The widest gap between neighbouring azimuths around the circle, leaving out the single widest one
    (outside a limited field of view it is no sampling gap; on a full circle of even steps it equals the
    others). None for fewer than two distinct azimuths."""
    a = np.unique(np.round(np.asarray(azimuths_deg, dtype=np.float64) % 360.0, 9))
    if len(a) < 2:
        return None
    gaps = np.sort(np.diff(np.r_[a, a[0] + 360.0]))
    return float(gaps[-2])


def azimuth_step_deg(lidar) -> float | None:
    """Azimuth spacing of a LiDAR in degrees: of its azimuth steps for a spinning unit (before per-channel
    offsets), of its rays' azimuths for a rosette unit or an (R, 3) direction table (rays within 1e-9 of
    vertical have no azimuth and are left out); the largest over a list of them. None when there is no
    second azimuth."""
    if isinstance(lidar, (list, tuple)):
        steps = [s for s in (azimuth_step_deg(m) for m in lidar) if s is not None]
        return max(steps) if steps else None
    if getattr(lidar, "pattern", 1) is None:
        return _circular_step(np.degrees(lidar.base_azimuths))
    table, _ = direction_table(lidar)
    flat = np.hypot(table[:, 0], table[:, 1]) > 1e-9
    return _circular_step(np.degrees(np.arctan2(table[flat, 1], table[flat, 0])))


def default_sector_deg(lidar) -> float:
    """The smallest whole number of degrees that divides 360 and is at least ``azimuth_step_deg(lidar)``
    (1 when the step is 1 degree or less, or unknown)."""
    step = azimuth_step_deg(lidar)
    if step is None:
        return 1.0
    return float(next(d for d in range(1, 361) if 360 % d == 0 and d >= step - 1e-9))


def _raster_bytes(n_cells: int, n_rects: int) -> int:
    # peak memory of blind_spot_map per cell: about 6 float64 values (centres, distances, angles) plus 6
    # per footprint rectangle (footprint_distance's (cells, rectangles, 2) temporaries); tracemalloc
    # peaks of 82, 128 and 224 bytes per cell for 1, 2 and 4 rectangles (dev VM) lie just below
    return int(n_cells) * 8 * (6 + 6 * max(int(n_rects), 1))


def footprint_distance(points_xy, footprint) -> np.ndarray:
    """(N,) distance in the ground plane from each point to the union of the (K, 2, 2) rectangles
    (0 inside)."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 1, 2)
    fp = np.asarray(footprint, dtype=np.float64).reshape(1, -1, 2, 2)
    gap = np.maximum(np.maximum(fp[:, :, 0] - p, p - fp[:, :, 1]), 0.0)      # (N, K, 2)
    return np.sqrt((gap ** 2).sum(axis=2)).min(axis=1)


def ground_hits(body: VehicleBody | None, lidar, poses, ground_z: float = 0.0, backend=None,
                max_range: float | None = None) -> np.ndarray:
    """(M, 2) ground-plane points (x, y) where rays of the rig reach z = ``ground_z`` unblocked.

    Args:
        body: the ego vehicle (None: nothing blocks).
        lidar: ``LidarModel`` or (R, 3) direction table (then ``max_range`` is required), or a list of
            them, one per pose (a rig of several sensor models).
        poses: (L, 6) ego-frame poses.
        ground_z: height of the plane, metres.

    Raises:
        ValueError: a LiDAR lies inside the body, or no range is known.
    """
    if not np.isfinite(ground_z):
        raise ValueError(f"ground_z (--ground-z) must be a finite height in metres, got {ground_z!r}")
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    if isinstance(lidar, (list, tuple)):
        # one model per LiDAR (a heterogeneous rig): the union of each LiDAR's ground hits
        if len(lidar) != len(poses):
            raise ValueError(f"give one LiDAR model per pose: {len(lidar)} models for {len(poses)} poses")
        msg = check_outside_body(body, poses[:, :3])
        if msg:
            raise ValueError(msg)
        parts = [ground_hits(body, m, p[None], ground_z, backend, max_range) for m, p in zip(lidar, poses)]
        return np.concatenate(parts) if parts else np.empty((0, 2))
    table, rng = direction_table(lidar)
    rng = max_range if max_range is not None else rng
    if rng is None or not rng > 0:
        raise ValueError(f"max_range must be a positive number of metres, got {rng!r}")
    msg = check_outside_body(body, poses[:, :3])
    if msg:
        raise ValueError(msg)
    o, d = rig_rays(table, poses)
    down = (d[:, 2] < 0) & (o[:, 2] > ground_z)
    o, d = o[down], d[down]
    tg = (ground_z - o[:, 2]) / d[:, 2]
    reach = tg <= rng
    o, d, tg = o[reach], d[reach], tg[reach]
    te = body_t_end(body, o, d, rng, backend=get_backend(backend))
    seen = tg <= te
    return (o[seen] + tg[seen, None] * d[seen])[:, :2]


@dataclass
class BlindSpotMap:
    """Result of ``blind_spot_map`` (ego frame, metres).

    Attributes:
        x_edges, y_edges: cell edges of the raster.
        blind: (ny, nx) bool, blind cells (outside the footprint, within ``radius`` of it).
        hits: (ny, nx) int64 ground hits per cell.
        region: (ny, nx) bool, cells outside the footprint within ``radius`` of it.
        sector_deg: sector width; sector s spans [s, s + 1) * sector_deg degrees (0 = +x, 90 = +y).
        nearest_radius: (S,) distance from the ego origin of the nearest seen point per sector (inf: none).
        nearest_from_body: (S,) its distance from the body footprint (inf: none).
        area_m2: blind area.
        footprint: (K, 2, 2) body rectangles; sensors: (L, 3) LiDAR positions.
    """

    x_edges: np.ndarray
    y_edges: np.ndarray
    blind: np.ndarray
    hits: np.ndarray
    region: np.ndarray
    sector_deg: float
    nearest_radius: np.ndarray
    nearest_from_body: np.ndarray
    area_m2: float
    footprint: np.ndarray
    sensors: np.ndarray
    radius: float
    ground_z: float
    cell: float
    body_name: str = ""
    meta: dict = field(default_factory=dict)

    def max_extent(self) -> float:
        """Largest distance from the body to the nearest seen ground point over all sectors (inf when a
        sector sees nothing): the size of the worst blind spot, for use as a constraint."""
        return float(np.max(self.nearest_from_body))

    def summary(self) -> dict:
        """Numbers for JSON reports."""
        nb = self.nearest_from_body
        return {"area_m2": round(self.area_m2, 4), "max_extent_m": None if not np.isfinite(nb.max()) else
                round(float(nb.max()), 4), "mean_extent_m": None if not np.all(np.isfinite(nb)) else
                round(float(nb.mean()), 4), "sectors_without_hit": int(np.sum(~np.isfinite(nb))),
                "sector_deg": self.sector_deg, "radius_m": self.radius, "ground_z_m": self.ground_z,
                "cell_m": self.cell, "body": self.body_name,
                "nearest_from_body_m": [None if not np.isfinite(v) else round(float(v), 4) for v in nb]}

    def plot(self, path, title: str | None = None):
        """Top view PNG: hit density (colour bar), blind region, body footprint to scale, sensors."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.patches import Patch, Rectangle

        fig, ax = plt.subplots(figsize=(8.5, 7), dpi=120)
        ext = (self.x_edges[0], self.x_edges[-1], self.y_edges[0], self.y_edges[-1])
        under = np.zeros(self.blind.shape + (4,))
        under[self.region & ~self.blind] = (0.55, 0.8, 0.55, 0.35)          # seen ground
        ax.imshow(under, origin="lower", extent=ext, interpolation="nearest")
        dens = np.where(self.region & (self.hits > 0), self.hits / self.cell ** 2, np.nan)
        if np.any(np.isfinite(dens)):       # LogNorm cannot scale an all-empty map (no ray reaches the ground)
            im = ax.imshow(dens, origin="lower", extent=ext, cmap="viridis", interpolation="nearest",
                           norm=matplotlib.colors.LogNorm())
            fig.colorbar(im, ax=ax, shrink=0.8, label="ground hits per m$^2$ (log scale)")
        overlay = np.zeros(self.blind.shape + (4,))
        overlay[self.blind] = (0.85, 0.1, 0.1, 0.55)
        overlay[~self.region] = (0.6, 0.6, 0.6, 0.15)
        ax.imshow(overlay, origin="lower", extent=ext, interpolation="nearest")
        for (x0, y0), (x1, y1) in self.footprint:
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor="0.25", edgecolor="black", lw=1.0))
        ax.plot(self.sensors[:, 0], self.sensors[:, 1], "^", color="orange", mec="black", ms=9)
        handles = [Patch(color=(0.85, 0.1, 0.1, 0.55), label=f"blind: {self.area_m2:.1f} m$^2$"),
                   Patch(color=(0.55, 0.8, 0.55, 0.6), label="seen (beyond the nearest ground hit)"),
                   Patch(color="0.25", label=f"vehicle body {self.body_name}".strip()),
                   Patch(color=(0.6, 0.6, 0.6, 0.3), label=f"beyond {self.radius:g} m of the body"),
                   plt.Line2D([], [], marker="^", ls="", color="orange", mec="black", label="LiDAR")]
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.0, -0.09), ncol=3, fontsize=8,
                  frameon=False)
        ax.set_xlabel("x (m, forward)")
        ax.set_ylabel("y (m, left)")
        ax.set_aspect("equal")
        ext_txt = "inf" if not np.isfinite(self.max_extent()) else f"{self.max_extent():.2f} m"
        ax.set_title(title or f"Blind spots at z = {self.ground_z:g} m (max extent from body {ext_txt})")
        fig.tight_layout()
        from place3d_kernels.atomic import atomic_savefig

        atomic_savefig(fig, path)
        plt.close(fig)
        return path


def blind_spot_map(body: VehicleBody | None, lidar, poses, ground_z: float = 0.0, radius: float = 10.0,
                   cell: float = 0.1, sector_deg: float | None = None, backend=None,
                   max_range: float | None = None) -> BlindSpotMap:
    """Blind ground region of a rig on a body (see the module docstring).

    Args:
        body: the ego vehicle (None: a point vehicle, no footprint, nothing blocks).
        lidar: ``LidarModel`` or (R, 3) direction table (with ``max_range``), or a list of them, one per pose.
        poses: (L, 6) ego-frame poses.
        ground_z: plane height (0 road, 0.5 bumper height); finite.
        radius: distance from the footprint out to which blind cells count, metres.
        cell: raster cell size, metres.
        sector_deg: sector width in degrees, dividing 360 and at least the LiDAR's azimuth step (a
            narrower sector can fall between two rays and see nothing); None: ``default_sector_deg``.

    Raises:
        ValueError: bad sizes, a non-finite ``ground_z``, a sector narrower than the azimuth step, a raster
            needing more than ``MAX_RASTER_BYTES``, or a LiDAR inside the body.
    """
    sizes = [("radius", radius), ("cell", cell)] + ([("sector_deg", sector_deg)] if sector_deg is not None else [])
    for what, v in sizes:
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"blind_spot_map {what} must be positive, got {v!r}")
    if not np.isfinite(ground_z):
        raise ValueError(f"ground_z (--ground-z) must be a finite height in metres, got {ground_z!r}")
    step = azimuth_step_deg(lidar)
    if sector_deg is None:
        sector_deg = default_sector_deg(lidar)
    elif step is not None and sector_deg < step - 1e-9:
        raise ValueError(f"sector_deg (--sector-deg) {sector_deg:g} is narrower than the LiDAR's azimuth step of {step:.4g} degrees: "
                         f"such sectors can fall between two rays and report no ground hit; use at least "
                         f"{default_sector_deg(lidar):g} (the default)")
    if not 360.0 / sector_deg == int(round(360.0 / sector_deg)):
        raise ValueError(f"sector_deg must divide 360, got {sector_deg!r}")
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    fp = body.footprint() if body is not None else np.zeros((1, 2, 2))
    span = fp[:, 1].max(axis=0) - fp[:, 0].min(axis=0) + 2 * radius
    with np.errstate(over="ignore"):          # a 5e-324 m cell: inf cells, refused below
        cells = float(np.ceil(span[0] / cell)) * float(np.ceil(span[1] / cell))
    per_cell = _raster_bytes(1, len(fp))
    if cells * per_cell > MAX_RASTER_BYTES:
        area = float(span[0]) * float(span[1])
        fits = math.sqrt(area * per_cell / MAX_RASTER_BYTES)      # cells scale as 1 / cell^2
        if math.isfinite(fits):
            unit = 10.0 ** (math.floor(math.log10(fits)) - 1)
            fix = f"use a cell of at least {math.ceil(fits / unit) * unit:.2g} m or a smaller radius"
        else:
            fix = "use a smaller radius"
        raise ValueError(f"a {cell:g} m raster (--cell) of the {span[0]:.4g} m x {span[1]:.4g} m region ({cells:.3g} "
                         f"cells) would need about {cells * per_cell / 2**30:,.1f} GiB of memory, above the "
                         f"{MAX_RASTER_BYTES / 2**30:g} GiB limit; {fix}")
    hits = ground_hits(body, lidar, poses, ground_z, backend, max_range)
    n_sec = int(round(360.0 / sector_deg))

    def sector(xy):
        ang = np.degrees(np.arctan2(xy[:, 1], xy[:, 0])) % 360.0
        return np.minimum((ang / sector_deg).astype(np.int64), n_sec - 1)

    r_hit = np.hypot(hits[:, 0], hits[:, 1])
    nearest_r = np.full(n_sec, np.inf)
    nearest_b = np.full(n_sec, np.inf)
    if len(hits):
        s = sector(hits)
        np.minimum.at(nearest_r, s, r_hit)
        np.minimum.at(nearest_b, s, footprint_distance(hits, fp))
    lo = fp[:, 0].min(axis=0) - radius
    hi = fp[:, 1].max(axis=0) + radius
    nx, ny = (int(np.ceil((hi[i] - lo[i]) / cell)) for i in range(2))
    xe = lo[0] + cell * np.arange(nx + 1)
    ye = lo[1] + cell * np.arange(ny + 1)
    xc, yc = np.meshgrid(0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1]))
    centres = np.stack([xc.ravel(), yc.ravel()], axis=1)
    dist = footprint_distance(centres, fp)
    region = (dist > 0) & (dist <= radius)
    blind = region & (np.hypot(centres[:, 0], centres[:, 1]) < nearest_r[sector(centres)])
    counts = np.zeros(nx * ny, dtype=np.int64)
    if len(hits):
        ix = np.floor((hits[:, 0] - lo[0]) / cell).astype(np.int64)
        iy = np.floor((hits[:, 1] - lo[1]) / cell).astype(np.int64)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        np.add.at(counts, iy[ok] * nx + ix[ok], 1)
    return BlindSpotMap(xe, ye, blind.reshape(ny, nx), counts.reshape(ny, nx), region.reshape(ny, nx),
                        float(sector_deg), nearest_r, nearest_b, float(blind.sum()) * cell * cell, fp,
                        poses[:, :3].copy(), float(radius), float(ground_z), float(cell),
                        body.name if body is not None else "")


def max_blind_extent(body: VehicleBody | None, lidar, poses, ground_z: float = 0.0, **kw) -> float:
    """Constraint value for optimisers: the largest distance from the body to the nearest seen point at
    height ``ground_z`` over all azimuth sectors (inf where a sector sees nothing, or the rig is
    infeasible). "No blind spot larger than X m at bumper height" is ``max_blind_extent(..., 0.5) <= X``."""
    try:
        return blind_spot_map(body, lidar, poses, ground_z, **kw).max_extent()
    except ValueError as e:
        if "inside" in str(e):
            return float("inf")
        raise


# ----------------------------------------------------------------------------- command line
def vehicle_from_arg(spec: str | None) -> VehicleBody | None:
    """``none`` -> no body; a preset name (car, suv, van, truck); else a mesh file path."""
    if spec is None or str(spec).strip().lower() == "none":
        return None
    from pathlib import Path

    from place3d_kernels.vehicle import PRESETS

    if str(spec).strip().lower() in PRESETS:
        return VehicleBody.preset(spec)
    if Path(spec).suffix:
        return VehicleBody.load(spec)
    raise ValueError(f"unknown vehicle {spec!r}: use one of {sorted(PRESETS)}, 'none', or a mesh file path")


def add_blindspot_parser(sub) -> None:
    """Register ``place3d blindspot`` on an argparse subparsers object (the CLI wires it in)."""
    p = sub.add_parser("blindspot", help="blind-spot map of a rig on a vehicle body (JSON numbers + top-view PNG)")
    p.add_argument("placement", nargs="?", default="center", help="placement name or TOML path (default center)")
    p.add_argument("--lidar", default="place3d_16ch", help="LiDAR model name or TOML (default place3d_16ch)")
    p.add_argument("--vehicle", default="car",
                   help="body: car, suv, van, truck, none, or a mesh file (OBJ, GLB, ...) in the ego frame "
                        "(glTF is Y-up by its specification and is turned Z-up)")
    p.add_argument("--ground-z", type=float, default=0.0, help="plane height in metres (0 road; 0.5 bumper)")
    p.add_argument("--radius", type=float, default=10.0, help="metres around the body (default 10)")
    p.add_argument("--cell", type=float, default=0.1, help="raster cell in metres (default 0.1)")
    p.add_argument("--sector-deg", type=float, default=None,
                   help="azimuth sector in degrees, at least the LiDAR's azimuth step (default: the smallest whole "
                        "degree dividing 360 at or above that step)")
    p.add_argument("--backend", default=None, help="backend name (default: the current one)")
    p.add_argument("--output", required=True, help="output folder (blindspot.json, blindspot.png)")
    p.set_defaults(func=cmd_blindspot)


def cmd_blindspot(args) -> int:
    """``place3d blindspot``: compute everything first, then write the JSON and PNG (bad input writes
    nothing)."""
    import json
    from pathlib import Path

    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.placement import Placement

    lidar = LidarModel.load(args.lidar)
    placement = Placement.load(args.placement)
    body = vehicle_from_arg(args.vehicle)
    m = blind_spot_map(body, lidar, placement.poses, args.ground_z, args.radius, args.cell, args.sector_deg,
                       backend=args.backend)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"placement": placement.name or str(args.placement), "lidar": lidar.name or str(args.lidar),
               "vehicle": None if body is None else {"name": body.name, "key": body.key,
                                                     "bounds_m": np.round(body.bounds, 4).tolist()},
               "sensors_m": np.round(m.sensors, 4).tolist(), **m.summary()}
    from place3d_kernels.atomic import atomic_write_text

    atomic_write_text(out / "blindspot.json", json.dumps(summary, indent=2))
    m.plot(out / "blindspot.png", title=f"{summary['placement']} on {body.name if body else 'no body'}: "
                                        f"blind spots at z = {args.ground_z:g} m")
    ext = summary["max_extent_m"]
    print(f"blind area {m.area_m2:.2f} m^2 within {args.radius:g} m of the body at z = {args.ground_z:g} m; "
          f"max extent {'inf' if ext is None else f'{ext:.2f} m'}; wrote {out / 'blindspot.json'} and "
          f"{out / 'blindspot.png'}")
    return 0
