"""Adverse conditions: point-cloud corruptions as kernels on every backend (docs/architecture.md,
"Kernel contract").

One function per condition, each ``f(cloud, <model parameters>, seed=0, backend=None, **options) -> PointCloud``,
pure (the input cloud is never modified) and deterministic per seed on every backend:

==================  ============================================  ====================================
condition           model                                         paper setting (Place3D appendix)
==================  ============================================  ====================================
``fog``             Hahner et al. 2021 (hard + soft target)       alpha in {0, .005, .01, .02, .03, .06}, beta 0.05
``wet_ground``      Hahner et al. 2022 (water film, Fresnel)      water_height_mm 1.0 (millimetres)
``snow``            after Hahner et al. 2022 (flakes per beam)    snowfall rate 1.0 mm/h (v = 1.6 m/s)
``motion_blur``     Robo3D                                        sigma 0.30
``crosstalk``       Robo3D                                        ratio 0.07
``incomplete_echo`` Robo3D, per vehicle object                    ratio 0.85
==================  ============================================  ====================================

``apply(cloud, name, seed, backend, severity=..., **params)`` dispatches by name (or by a TOML file under
``place3d_kernels/configs/conditions/``); ``SEVERITIES[name]`` holds Robo3D's light / moderate / heavy levels (moderate =
the paper's setting). ``lidar_returns`` gives per-ray returns in a mesh (analytic, or Mitsuba 3 with the
``mitsuba`` extra).

Random numbers are drawn on the host (NumPy PCG64 streams of the seed) and passed to the kernels, so
every backend gives the reference result up to float32 rounding. A backend without condition kernels
falls back to the reference ones with a warning.
"""

from __future__ import annotations

from pathlib import Path

from place3d_kernels._toml import config_dir, read_toml
from place3d_kernels.conditions import crosstalk as _crosstalk
from place3d_kernels.conditions import fog as _fog
from place3d_kernels.conditions import incomplete_echo as _echo
from place3d_kernels.conditions import motion_blur as _blur
from place3d_kernels.conditions import snow as _snow
from place3d_kernels.conditions import wet_ground as _wet
from place3d_kernels.conditions.crosstalk import crosstalk
from place3d_kernels.conditions.fog import FOG_ALPHAS, FogSensor, FogTable, alpha_from_mor, fog, fog_lookup, mor
from place3d_kernels.conditions.incomplete_echo import cluster_points, incomplete_echo
from place3d_kernels.conditions.motion_blur import motion_blur
from place3d_kernels.conditions.returns import Returns, lidar_returns
from place3d_kernels.conditions.snow import Snowflakes, snow, snowflakes
from place3d_kernels.conditions.wet_ground import film_transmission, ground_points, laser_parameters, wet_ground

__all__ = [
    "fog", "wet_ground", "snow", "motion_blur", "crosstalk", "incomplete_echo",
    "apply", "CONDITIONS", "SEVERITIES", "load_condition",
    "fog_lookup", "FogTable", "FogSensor", "mor", "alpha_from_mor", "FOG_ALPHAS",
    "film_transmission", "ground_points", "laser_parameters", "snowflakes", "Snowflakes", "cluster_points",
    "lidar_returns", "Returns",
]

#: name -> condition function
CONDITIONS = {
    "fog": fog,
    "wet_ground": wet_ground,
    "snow": snow,
    "motion_blur": motion_blur,
    "crosstalk": crosstalk,
    "incomplete_echo": incomplete_echo,
}

#: name -> {"light" | "moderate" | "heavy": parameters}; "moderate" is the paper's setting
SEVERITIES = {
    "fog": _fog.SEVERITIES,
    "wet_ground": _wet.SEVERITIES,
    "snow": _snow.SEVERITIES,
    "motion_blur": _blur.SEVERITIES,
    "crosstalk": _crosstalk.SEVERITIES,
    "incomplete_echo": _echo.SEVERITIES,
}


def load_condition(name_or_path) -> dict:
    """Read a condition config: a shipped name (``place3d_kernels/configs/conditions/<name>.toml``) or a TOML path.

    Returns:
        ``{"condition": name, "params": {...}, "severities": {level: {...}}}``.
    """
    p = Path(str(name_or_path))
    if not p.suffix == ".toml" or not p.exists():
        shipped = config_dir("conditions") / (p.stem + ".toml")
        if not shipped.exists():
            names = sorted(q.stem for q in config_dir("conditions").glob("*.toml"))
            raise FileNotFoundError(f"No condition config {str(name_or_path)!r}: not a file, and not one of the "
                                    f"shipped names {names}")
        p = shipped
    data = read_toml(p)
    name = data.get("condition")
    if name not in CONDITIONS:
        raise ValueError(f"{p}: key 'condition' must be one of {sorted(CONDITIONS)}, got {name!r}")
    params = dict(data.get("params", {}))
    if "alphas" in params:
        params["alphas"] = tuple(params["alphas"])
    return {"condition": name, "params": params, "severities": dict(data.get("severities", {}))}


def apply(cloud, name: str, seed=0, backend=None, *, severity: str | None = None, **params):
    """Apply a condition by name: ``apply(cloud, "fog", seed=3, alpha=0.02)``.

    Args:
        cloud: the PointCloud.
        name: a key of ``CONDITIONS``, or a condition TOML file (its params are the defaults).
        seed: int or numpy Generator.
        backend: backend name or instance (None: current default).
        severity: "light", "moderate" or "heavy" (Robo3D levels); explicit ``params`` win over it.
        **params: the condition function's keyword arguments.
    """
    base: dict = {}
    levels = None
    if name not in CONDITIONS:
        if str(name).endswith(".toml"):
            cfg = load_condition(name)
            name, base, levels = cfg["condition"], cfg["params"], cfg["severities"]
        else:
            raise ValueError(f"Unknown condition {name!r}; known: {sorted(CONDITIONS)} (or a .toml config path)")
    if severity is not None:
        levels = levels or SEVERITIES[name]
        if severity not in levels:
            raise ValueError(f"Unknown severity {severity!r} for {name}; known: {sorted(levels)}")
        base = {**base, **levels[severity]}
    return CONDITIONS[name](cloud, seed=seed, backend=backend, **{**base, **params})
