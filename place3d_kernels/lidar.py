"""LiDAR beam patterns and ray generation.

A ``LidarModel`` is either a spinning unit (channels at fixed elevations, swept through azimuth steps,
each channel optionally shifted by its own azimuth offset) or a non-repetitive rosette unit
(``place3d_kernels.scan_patterns.RosettePattern``). ``directions()`` gives the sensor-frame rays of any
of them; ``is_grid`` says whether the rays are the separable elevations x azimuths grid that the
backend kernels take today (issue 16 generalises the kernel contract to a direction table).

Sensor frame: x forward, y left, z up; azimuth counter-clockwise from +x seen from above, elevation up
from the x-y plane.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels._toml import config_dir, read_toml, require, resolve_config
from place3d_kernels.backends.base import rotation_matrices, sensor_directions
from place3d_kernels.scan_patterns import RosettePattern

__all__ = ["LidarModel", "lidar_rays", "rays_from_directions", "CARLA_LIDAR_DEFAULTS", "list_presets"]

# CARLA's sensor.lidar.ray_cast blueprint defaults (FLidarDescription in LidarDescription.h,
# https://carla.org/Doxygen/html/de/d92/LidarDescription_8h_source.html; Range there is 1000 cm).
CARLA_LIDAR_DEFAULTS = {"channels": 32, "range": 10.0, "points_per_second": 56000, "rotation_frequency": 10.0,
                        "upper_fov": 10.0, "lower_fov": -30.0, "horizontal_fov": 360.0}
# Blueprint attributes that do not change ray geometry (noise, drop-off, timing): accepted and ignored.
_CARLA_IGNORED = {"atmosphere_attenuation_rate", "dropoff_general_rate", "dropoff_intensity_limit",
                  "dropoff_zero_intensity", "noise_stddev", "noise_seed", "sensor_tick", "role_name"}

_ISSUE = "issue 16 (Real rigs) moves the kernels to a direction table"


def _round_half_up(x: float) -> int:
    # CARLA rounds points per laser with FMath::RoundHalfFromZero; counts here are positive.
    return int(np.floor(x + 0.5))


class LidarModel:
    """A LiDAR's beam pattern: spinning (elevations x azimuths, per-channel azimuth offsets) or rosette.

    Construct spinning units as ``LidarModel(elevations, azimuths, max_range, name)`` (as before), with
    ``LidarModel.uniform``, ``LidarModel.load`` (TOML preset), ``LidarModel.from_carla``; rosette units
    with ``LidarModel.rosette`` or a TOML with ``scan = "rosette"``.

    Attributes:
        max_range: metres.
        min_range: metres; returns nearer than this are dropped by the sensor (default 0).
        name: label.
        azimuth_offsets: (C,) radians added to each channel's azimuth (zeros for a plain grid), or None
            for a rosette unit.
        pattern: the ``RosettePattern`` of a rosette unit, else None.
        horizontal_fov_deg: horizontal FOV of a spinning unit in degrees (None when not known).
        frame_rate_hz: frames (revolutions) per second, used by CARLA export; default 10.
        source: where the numbers come from (data sheet, calibration file).
    """

    def __init__(self, elevations=None, azimuths=None, max_range: float = 100.0, name: str = "", *,
                 azimuth_offsets=None, min_range: float = 0.0, pattern: RosettePattern | None = None,
                 horizontal_fov_deg: float | None = None, frame_rate_hz: float = 10.0, source: str = ""):
        if not (np.isfinite(max_range) and max_range > 0):
            raise ValueError(f"LidarModel max_range must be positive, got {max_range!r}")
        if not (np.isfinite(min_range) and 0 <= min_range < max_range):
            raise ValueError(f"LidarModel min_range must be in [0, max_range={max_range}), got {min_range!r}")
        if not (np.isfinite(frame_rate_hz) and frame_rate_hz > 0):
            raise ValueError(f"LidarModel frame_rate_hz must be positive, got {frame_rate_hz!r}")
        d = self.__dict__
        d.update(max_range=float(max_range), min_range=float(min_range), name=str(name), pattern=pattern,
                 frame_rate_hz=float(frame_rate_hz), source=str(source),
                 horizontal_fov_deg=None if horizontal_fov_deg is None else float(horizontal_fov_deg))
        if pattern is not None:
            if elevations is not None or azimuths is not None or azimuth_offsets is not None:
                raise ValueError("a rosette LidarModel takes its rays from the pattern: give no elevations, "
                                 "azimuths or azimuth_offsets")
            d.update(_elevations=None, _azimuths=None, azimuth_offsets=None)
            return
        e = np.asarray(elevations, dtype=np.float64).reshape(-1)
        a = np.asarray(azimuths, dtype=np.float64).reshape(-1)
        if len(e) == 0 or len(a) == 0:
            raise ValueError("LidarModel needs at least one channel and one azimuth step")
        if not (np.all(np.isfinite(e)) and np.all(np.abs(e) <= np.pi / 2)):
            raise ValueError(f"LidarModel elevations must be finite and within +-90 deg, got {np.degrees(e)}")
        if not np.all(np.isfinite(a)):
            raise ValueError("LidarModel azimuths must be finite")
        off = np.zeros_like(e) if azimuth_offsets is None else np.asarray(azimuth_offsets, np.float64).reshape(-1)
        if len(off) != len(e):
            raise ValueError(f"LidarModel azimuth_offsets has {len(off)} entries but there are {len(e)} channels; "
                             "give one offset per channel")
        if not np.all(np.isfinite(off)):
            raise ValueError("LidarModel azimuth_offsets must be finite")
        d.update(_elevations=e, _azimuths=a, azimuth_offsets=off)

    def __setattr__(self, key, value):
        raise AttributeError(f"LidarModel is immutable; build a new one instead of setting {key!r}")

    def __repr__(self) -> str:
        kind = "rosette" if self.pattern is not None else ("grid" if self.is_grid else "offset grid")
        return (f"LidarModel(name={self.name!r}, {kind}, rays={self.n_rays}, max_range={self.max_range}, "
                f"min_range={self.min_range})")

    # ------------------------------------------------------------------ geometry
    @property
    def is_grid(self) -> bool:
        """True when the rays are the separable elevations x azimuths grid the kernels take today."""
        return self.pattern is None and not np.any(self.azimuth_offsets)

    @property
    def channel_elevations(self) -> np.ndarray:
        """(C,) radians, one per channel of a spinning unit."""
        if self.pattern is not None:
            raise NotImplementedError(f"LidarModel {self.name!r} is a rosette unit: it has no channels; "
                                      "use directions()")
        return self._elevations

    @property
    def base_azimuths(self) -> np.ndarray:
        """(A,) radians, the azimuth steps of a spinning unit before per-channel offsets."""
        if self.pattern is not None:
            raise NotImplementedError(f"LidarModel {self.name!r} is a rosette unit: it has no azimuth steps; "
                                      "use directions()")
        return self._azimuths

    @property
    def elevations(self) -> np.ndarray:
        """(C,) radians; the kernels' grid input (raises for a rosette unit)."""
        return self.channel_elevations

    @property
    def azimuths(self) -> np.ndarray:
        """(A,) radians; the kernels' grid input. Raises for a non-grid model so no kernel silently drops
        the per-channel offsets or the rosette; ``without_azimuth_offsets()`` gives the grid approximation."""
        if not self.is_grid:
            raise NotImplementedError(
                f"LidarModel {self.name!r} is not a separable elevation x azimuth grid (per-channel azimuth "
                f"offsets or a rosette scan); today's kernels take only grids ({_ISSUE}). Use directions() / "
                "lidar_rays() for its rays, or lidar.without_azimuth_offsets() for the grid approximation.")
        return self._azimuths

    @property
    def n_channels(self) -> int:
        return 1 if self.pattern is not None else len(self._elevations)

    @property
    def n_rays(self) -> int:
        if self.pattern is not None:
            return self.pattern.n_rays
        return len(self._elevations) * len(self._azimuths)

    def directions(self, frame: int = 0) -> np.ndarray:
        """(R, 3) float64 unit sensor-frame directions.

        Spinning units: ordered (channel, azimuth), equal to ``sensor_directions(elevations, azimuths)``
        bit for bit when the offsets are zero. Rosette units: firing order of frame ``frame``.
        """
        if self.pattern is not None:
            return self.pattern.directions(frame)
        if not np.any(self.azimuth_offsets):
            return sensor_directions(self._elevations, self._azimuths)
        e = self._elevations[:, None]
        a = self._azimuths[None, :] + self.azimuth_offsets[:, None]
        d = np.stack(np.broadcast_arrays(np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)), -1)
        return d.reshape(-1, 3)

    def without_azimuth_offsets(self) -> "LidarModel":
        """The same spinning unit with every channel's azimuth offset set to zero (a kernel grid)."""
        return self._replace(azimuth_offsets=None, name=f"{self.name}/grid")

    def subsample(self, channel_step: int = 1, azimuth_step: int = 1) -> "LidarModel":
        """Every ``channel_step``-th channel and ``azimuth_step``-th azimuth step of a spinning unit."""
        if self.pattern is not None:
            raise NotImplementedError(f"LidarModel {self.name!r} is a rosette unit; subsample it by building "
                                      "a RosettePattern with fewer points_per_second")
        return self._replace(elevations=self._elevations[::channel_step], azimuths=self._azimuths[::azimuth_step],
                             azimuth_offsets=self.azimuth_offsets[::channel_step],
                             name=f"{self.name}/c{channel_step}a{azimuth_step}")

    def _replace(self, **kw) -> "LidarModel":
        args = dict(elevations=self._elevations, azimuths=self._azimuths, max_range=self.max_range,
                    name=self.name, azimuth_offsets=self.azimuth_offsets, min_range=self.min_range,
                    pattern=self.pattern, horizontal_fov_deg=self.horizontal_fov_deg,
                    frame_rate_hz=self.frame_rate_hz, source=self.source)
        args.update(kw)
        return LidarModel(**args)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def uniform(cls, channels: int, fov_deg=(-24.8, 2.0), azimuth_steps: int = 250,
                horizontal_fov_deg: float = 360.0, max_range: float = 100.0, name: str = "", **kw) -> "LidarModel":
        """Channels spread uniformly over the vertical FOV; azimuth steps evenly over the horizontal FOV.

        Extra keywords (``min_range``, ``azimuth_offsets``, ``frame_rate_hz``, ``source``) pass through.
        """
        if channels < 1 or azimuth_steps < 1:
            raise ValueError(f"channels and azimuth_steps must be >= 1, got {channels}, {azimuth_steps}")
        lo, hi = fov_deg
        if not lo <= hi:
            raise ValueError(f"vertical FOV lower bound must not exceed the upper, got {fov_deg}")
        e = np.radians(np.linspace(lo, hi, channels)) if channels > 1 else np.radians([0.5 * (lo + hi)])
        return cls(e, _azimuth_steps(azimuth_steps, horizontal_fov_deg), max_range, name,
                   horizontal_fov_deg=horizontal_fov_deg, **kw)

    @classmethod
    def rosette(cls, pattern: RosettePattern, max_range: float, name: str = "", **kw) -> "LidarModel":
        """A non-repetitive rosette unit; ``frame_rate_hz`` defaults to 1 / pattern.frame_time_s."""
        kw.setdefault("frame_rate_hz", 1.0 / pattern.frame_time_s)
        return cls(None, None, max_range, name, pattern=pattern, **kw)

    @classmethod
    def load(cls, path_or_name) -> "LidarModel":
        """Read a LiDAR TOML (path or shipped name such as ``"place3d_16ch"`` or ``"vlp16"``).

        Keys: ``max_range_m``; ``min_range_m`` (default 0); for spinning units ``channels``,
        ``elevations_deg`` (explicit list) or ``vertical_fov_deg`` ([lower, upper], uniform),
        ``azimuth_offsets_deg`` (optional, one per channel), ``horizontal_fov_deg`` (default 360),
        ``azimuth_steps`` or ``points_per_second`` + ``rotation_frequency_hz``; for rosette units
        ``scan = "rosette"`` and a ``[rosette]`` table (fov_deg, points_per_second, frame_time_s, prism_hz).
        """
        path = resolve_config(path_or_name, "lidars")
        d = read_toml(path)
        name = str(d.get("name", path.stem))
        common = dict(min_range=float(d.get("min_range_m", 0.0)), source=str(d.get("source", "")))
        max_range = float(require(d, "max_range_m", path))
        scan = d.get("scan", "spinning")
        if scan == "rosette":
            r = d.get("rosette")
            if not isinstance(r, dict):
                raise ValueError(f"{path}: scan = 'rosette' needs a [rosette] table")
            pat = RosettePattern(float(require(r, "fov_deg", path)), float(require(r, "points_per_second", path)),
                                 float(require(r, "frame_time_s", path)), tuple(require(r, "prism_hz", path, list)))
            return cls.rosette(pat, max_range, name, **common)
        if scan != "spinning":
            raise ValueError(f"{path}: scan must be 'spinning' or 'rosette', got {scan!r}")
        hfov = float(d.get("horizontal_fov_deg", 360.0))
        freq = float(d.get("rotation_frequency_hz", 10.0))
        if "azimuth_steps" in d:
            steps = int(require(d, "azimuth_steps", path, int))
        elif "points_per_second" in d:
            pps = float(require(d, "points_per_second", path))
            n_ch = len(d["elevations_deg"]) if "elevations_deg" in d else int(require(d, "channels", path, int))
            steps = _round_half_up(pps / (n_ch * freq))
        else:
            raise ValueError(f"{path}: give azimuth_steps, or points_per_second and rotation_frequency_hz")
        offsets = d.get("azimuth_offsets_deg")
        if offsets is not None:
            offsets = np.radians(np.asarray(offsets, dtype=float))
        common.update(frame_rate_hz=freq, azimuth_offsets=offsets)
        if "elevations_deg" in d:
            e = d["elevations_deg"]
            if not isinstance(e, list) or not e:
                raise ValueError(f"{path}: elevations_deg must be a non-empty list of degrees")
            if "channels" in d and int(d["channels"]) != len(e):
                raise ValueError(f"{path}: channels = {d['channels']} but elevations_deg lists {len(e)} "
                                 "angles; make them agree")
            if offsets is not None and len(offsets) != len(e):
                raise ValueError(f"{path}: azimuth_offsets_deg lists {len(offsets)} angles but elevations_deg "
                                 f"lists {len(e)}; give one offset per channel")
            return cls(np.radians(np.asarray(e, dtype=float)), _azimuth_steps(steps, hfov), max_range, name,
                       horizontal_fov_deg=hfov, **common)
        channels = int(require(d, "channels", path, int))
        fov = d.get("vertical_fov_deg")
        if not (isinstance(fov, list) and len(fov) == 2):
            raise ValueError(f"{path}: vertical_fov_deg must be [lower, upper] in degrees (or give elevations_deg)")
        return cls.uniform(channels, tuple(float(x) for x in fov), steps, hfov, max_range, name, **common)

    # ------------------------------------------------------------------ CARLA
    @classmethod
    def from_carla(cls, attributes: dict, name: str = "carla") -> "LidarModel":
        """A spinning unit from CARLA ``sensor.lidar.ray_cast`` blueprint attributes: the rays CARLA casts,
        mirrored into this package's y-left frame (``place3d_kernels.carla_frame``).

        Missing attributes take CARLA's defaults (``CARLA_LIDAR_DEFAULTS``); values may be strings, as
        CARLA's blueprint attributes are. Channels in CARLA's order, from upper_fov down to lower_fov (a
        single channel fires at upper_fov, as CARLA's does); each channel fires
        ``round(points_per_second / (channels * rotation_frequency))`` times over horizontal_fov, at the
        horizontal angles of one CARLA tick of 1 / rotation_frequency from its initial angle.
        """
        from place3d_kernels.carla_frame import (azimuths_from_carla, carla_channel_elevations_deg,
                                                 carla_horizontal_angles_deg)

        unknown = set(attributes) - set(CARLA_LIDAR_DEFAULTS) - _CARLA_IGNORED
        if unknown:
            raise ValueError(f"unknown CARLA lidar attributes {sorted(unknown)}; known: "
                             f"{sorted(CARLA_LIDAR_DEFAULTS)} (ignored: {sorted(_CARLA_IGNORED)})")
        a = {**CARLA_LIDAR_DEFAULTS, **attributes}
        channels = int(float(a["channels"]))
        freq, pps = float(a["rotation_frequency"]), float(a["points_per_second"])
        if channels < 1 or freq <= 0 or pps <= 0:
            raise ValueError(f"CARLA lidar needs channels >= 1, rotation_frequency > 0 and points_per_second > 0, "
                             f"got {channels}, {freq}, {pps}")
        steps = _round_half_up(pps / (channels * freq))
        if steps < 1:
            raise ValueError(f"CARLA lidar: points_per_second {pps} gives no point per channel per revolution "
                             f"({channels} channels at {freq} Hz); raise points_per_second")
        lower, upper, hfov = float(a["lower_fov"]), float(a["upper_fov"]), float(a["horizontal_fov"])
        if not lower <= upper:
            raise ValueError(f"CARLA lidar: lower_fov {lower} is above upper_fov {upper}")
        if not (np.isfinite(hfov) and 0 < hfov <= 360.0):
            raise ValueError(f"horizontal_fov must be in (0, 360], got {hfov!r}")
        e = np.radians(carla_channel_elevations_deg(channels, lower, upper))
        az = azimuths_from_carla(carla_horizontal_angles_deg(steps, hfov))
        return cls(e, az, float(a["range"]), name, horizontal_fov_deg=hfov, frame_rate_hz=freq,
                   source="CARLA sensor.lidar.ray_cast attributes")

    def to_carla(self) -> dict:
        """CARLA ``sensor.lidar.ray_cast`` attributes giving the same elevations (one channel: upper_fov =
        lower_fov = its elevation, where CARLA fires a single channel), ray count, horizontal FOV and
        rotation frequency (``frame_rate_hz``). CARLA picks the azimuth phase itself; ``from_carla`` gives
        the angles of its first tick. Place the sensor with ``carla_frame.pose_to_carla``.

        Raises:
            ValueError: for a rosette unit, per-channel azimuth offsets, or non-uniform elevations,
                which CARLA's ray-cast LiDAR cannot express.
        """
        if not self.is_grid:
            raise ValueError(f"LidarModel {self.name!r} has a rosette scan or per-channel azimuth offsets; "
                             "CARLA's ray-cast LiDAR cannot express it")
        e = np.degrees(self._elevations)
        c = len(e)
        if c > 1 and not np.allclose(e, np.linspace(e[0], e[-1], c), rtol=0, atol=1e-9):
            raise ValueError(f"LidarModel {self.name!r} has non-uniform elevations; CARLA spreads channels "
                             "uniformly between lower_fov and upper_fov")
        steps = len(self._azimuths)
        return {"channels": c, "range": self.max_range,
                "points_per_second": int(round(steps * c * self.frame_rate_hz)),
                "rotation_frequency": self.frame_rate_hz,
                "upper_fov": round(float(e.max()), 9), "lower_fov": round(float(e.min()), 9),
                "horizontal_fov": 360.0 if self.horizontal_fov_deg is None else self.horizontal_fov_deg}


def _azimuth_steps(steps: int, horizontal_fov_deg: float) -> np.ndarray:
    """Azimuths of ``steps`` firings: from 0 round a full turn, or centred bins over a limited FOV."""
    if not (np.isfinite(horizontal_fov_deg) and 0 < horizontal_fov_deg <= 360.0):
        raise ValueError(f"horizontal_fov_deg must be in (0, 360], got {horizontal_fov_deg!r}")
    h = np.radians(horizontal_fov_deg)
    if horizontal_fov_deg >= 360.0:
        return np.arange(steps) * (2 * np.pi / steps)
    return -h / 2 + (np.arange(steps) + 0.5) * (h / steps)


def rays_from_directions(local: np.ndarray, poses) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions of sensor-frame rays ``local`` (R, 3) for (L, 6) poses, on the host.

    Same convention and arithmetic as the reference backend: R = Rz(yaw) Ry(pitch) Rx(roll) applied as
    ``R @ local``, origins repeat each pose's position; ordered (lidar, ray).
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
    d = np.einsum("lij,nj->lni", rotation_matrices(p), local).reshape(-1, 3)
    return np.repeat(p[:, :3], len(local), axis=0), d


def lidar_rays(lidar: LidarModel, placement, backend=None) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions of every ray of a rig, ordered (LiDAR, ray).

    Grid models go through the backend (rays ordered (LiDAR, channel, azimuth)); other models (azimuth
    offsets, rosette) are built on the host in float64 from ``lidar.directions()`` until the kernels take
    a direction table (issue 16).

    Args:
        lidar: the beam pattern shared by all LiDARs of the rig.
        placement: a ``Placement`` or an (L, 6) pose array.
        backend: name or Backend; default the current one.
    """
    from place3d_kernels.backends.registry import resolve

    poses = placement.poses if hasattr(placement, "poses") else np.asarray(placement, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    if not lidar.is_grid:
        return rays_from_directions(lidar.directions(), poses)
    b = resolve(backend)
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, poses)
    return np.asarray(o, dtype=np.float64), np.asarray(d, dtype=np.float64)


def list_presets() -> list[dict]:
    """One row per shipped LiDAR preset: name, channels, vertical and horizontal FOV (deg), rays per
    frame, range (m), source."""
    rows = []
    for path in sorted(config_dir("lidars").glob("*.toml")):
        m = LidarModel.load(path)
        if m.pattern is not None:
            half = m.pattern.fov_deg / 2
            vfov, hfov, ch = (-half, half), m.pattern.fov_deg, 1
        else:
            e = np.degrees(m.channel_elevations)
            vfov, ch = (float(e.min()), float(e.max())), m.n_channels
            hfov = 360.0 if m.horizontal_fov_deg is None else m.horizontal_fov_deg
        rows.append({"name": path.stem, "channels": ch, "vfov_deg": vfov, "hfov_deg": hfov,
                     "rays_per_frame": m.n_rays, "min_range_m": m.min_range, "max_range_m": m.max_range,
                     "scan": "rosette" if m.pattern is not None else "spinning", "source": m.source})
    return rows
