"""What a run is made of, as plain data: the scene, the ROI grid, the adverse condition and the P-SOG inputs.

Every spec is a frozen, picklable dataclass with ``to_dict()`` / ``from_dict()``. The CLI builds them once
from its arguments (``specs_from_args``); the local path and the Ray tasks (``place3d_app.executors``)
consume the same objects, so a task rebuilds exactly what the driver would have built in-process.

The grid spec is called ``RoiSpec``: ``backends.base.GridSpec`` is the kernel-facing grid (voxel size and
shape only, no ROI corners), and ``Grid.spec`` returns that one; ``RoiSpec`` is the domain choice a user
makes (the ROI box and its voxel size, ``--roi`` / ``--voxel-size``) and builds a ``Grid`` with ``.grid()``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from place3d_kernels.grid import Grid, check_roi, roi_grid
from place3d_kernels.profiling import section

__all__ = ["SceneSpec", "RoiSpec", "ConditionSpec", "PSOGSpec", "specs_from_args", "backend_name", "resolve_lidar",
           "parse_params", "condition_parameters", "check_condition_params", "read_route"]

#: LiDAR whose frames build P-SOGs (the dense collection sensor).
COLLECTION_LIDAR = "collection_64ch"


def backend_name(backend) -> str:
    """A backend name a worker can resolve.

    Explicit names pass through unresolved (the driver may lack the device, e.g. 'warp:cuda:0' on a CPU
    head node); None / 'auto' resolve here so that all tasks agree; an instance gives its name.
    """
    if backend is not None and not isinstance(backend, str):
        return backend.name
    if backend in (None, "auto"):
        from place3d_kernels.backends.registry import get_backend

        return get_backend(backend).name
    return backend


def resolve_lidar(lidar):
    """A ``LidarModel`` from a model name / TOML path, or the model itself."""
    from place3d_kernels.lidar import LidarModel

    return LidarModel.load(lidar) if isinstance(lidar, str) else lidar


def parse_params(pairs) -> dict:
    """``["alpha=0.03", "mode=x"]`` -> ``{"alpha": 0.03, "mode": "x"}`` (numbers become floats)."""
    params = {}
    for kv in pairs or []:
        if "=" not in kv:
            raise ValueError(f"--param expects KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        try:
            params[k] = float(v)
        except ValueError:
            params[k] = v
    return params


def condition_parameters(name: str) -> dict:
    """``{parameter: default}`` a condition accepts through ``--param`` (its function's keyword arguments
    besides the cloud, seed and backend); a condition TOML file takes its condition's parameters."""
    import inspect

    from place3d_kernels import conditions

    if name not in conditions.CONDITIONS:
        name = conditions.load_condition(name)["condition"]
    sig = inspect.signature(conditions.CONDITIONS[name])
    return {k: p.default for k, p in sig.parameters.items() if k not in ("cloud", "seed", "backend")}


def check_condition_params(name: str, params: dict) -> None:
    """Raise ``ValueError`` naming a parameter the condition does not take (with the allowed set) or a
    text value where the condition expects a number."""
    allowed = condition_parameters(name)
    for k, v in params.items():
        if k not in allowed:
            raise ValueError(f"--param {k}: condition {name!r} has no parameter {k!r}; allowed: {sorted(allowed)}")
        if isinstance(v, str) and isinstance(allowed[k], (int, float)) and not isinstance(allowed[k], bool):
            raise ValueError(f"--param {k}={v}: {k} takes a number (default {allowed[k]})")
        if isinstance(v, str) and allowed[k] is None and k in ("alpha", "threshold", "noise_level", "p_out"):
            raise ValueError(f"--param {k}={v}: {k} takes a number")


# ============================================================================== scene
@dataclass(frozen=True)
class SceneSpec:
    """A scene from explicit inputs.

    ``name``: 'town' (the procedural town), 'opendrive:PATH' (an OpenDRIVE map), 'mesh:PATH' (a mesh file
    trimesh reads, or a Mitsuba XML scene; 'mitsuba:PATH' names the latter explicitly; ``labels`` maps part names to classes, ``route`` gives the ego
    poses) or 'semantickitti:DIR' (labelled frames with poses: the P-SOG is built from them, nothing is
    simulated). ``seed`` and ``frames`` apply to generated scenes.
    """

    name: str = "town"
    seed: int = 0
    frames: int = 40
    labels: str | None = None
    route: str | None = None

    def build(self):
        """The ``Scene`` (memoised per process: tasks of one worker share it)."""
        return _build_scene(self)

    def for_cache(self, folder):
        """What ``scene_psog`` needs to find a cached P-SOG: a ``SceneRef`` (name and key, built only on a
        cache miss) when this scene's key is remembered in ``folder`` (``scene.keymemo``), else the built
        ``Scene``, whose key is then remembered."""
        from place3d_kernels.scene.keymemo import SceneRef, identity, recall, remember

        ident = identity(self.to_dict(), self.kind, self.path)
        known = recall(folder, ident)
        if known is not None:
            return SceneRef(known[0], known[1], self.build)
        scene = self.build()
        remember(folder, ident, scene.name, scene.key)
        return scene

    @property
    def kind(self) -> str:
        """'town', 'opendrive', 'mesh' (also for 'mitsuba:PATH', a Mitsuba XML scene read as a mesh scene)
        or 'semantickitti'."""
        k = self.name.split(":", 1)[0] if ":" in self.name else self.name
        return "mesh" if k == "mitsuba" else k

    @property
    def path(self) -> Path | None:
        """The scene's file; for 'opendrive:Town06' (a shipped CARLA map by name, no such file here) the
        shipped map's plain .xodr file, so every reader (the scene key, the builder) finds it."""
        if ":" not in self.name:
            return None
        p = Path(self.name.split(":", 1)[1])
        if self.kind == "opendrive" and not p.is_file():
            return _shipped_map(p.name) or p
        return p

    def validate(self) -> "SceneSpec":
        """Raise ``ValueError`` / ``FileNotFoundError`` for an unknown scene kind, a missing file or a
        frame count below 1, before any work starts."""
        if self.frames < 1:
            raise ValueError(f"--frames must be >= 1, got {self.frames}")
        if self.route is not None and not Path(self.route).is_file():
            raise FileNotFoundError(f"--route {self.route}: no such file")
        if self.route is not None and self.kind != "mesh":
            raise ValueError(f"--route applies to mesh scenes ('mesh:PATH'), not {self.name!r}")
        if self.name == "town":
            return self
        if self.name.startswith("mitsuba:") and self.path.suffix.lower() != ".xml":
            raise ValueError(f"scene {self.name!r}: 'mitsuba:PATH' takes a Mitsuba 3 XML scene (.xml); other mesh "
                             f"files go with 'mesh:PATH'")
        if self.kind in ("opendrive", "mesh"):
            if not self.path.is_file():
                raise FileNotFoundError(f"scene {self.name!r}: no such file {self.path}"
                                        + (" (shipped maps by name: opendrive:Town01, ...)" if self.kind == "opendrive" else ""))
            return self
        if self.kind == "semantickitti":
            if not (self.path / "velodyne").is_dir():
                raise FileNotFoundError(f"scene {self.name!r}: {self.path} has no velodyne/ folder (a "
                                        f"SemanticKITTI sequence: velodyne/, labels/, poses.txt)")
            return self
        raise ValueError(f"unknown scene {self.name!r}; use 'town', 'opendrive:PATH' (an OpenDRIVE .xodr file), "
                         f"'mesh:PATH' (a mesh or Mitsuba XML file), 'mitsuba:PATH' (a Mitsuba XML scene) or "
                         f"'semantickitti:DIR' (labelled frames)")

    @property
    def label(self) -> str:
        base = self.name if self.name == "town" else Path(self.name.split(":", 1)[-1]).stem
        return f"{base}-s{self.seed}-f{self.frames}"

    def to_dict(self) -> dict:
        d = {"name": self.name, "seed": self.seed, "frames": self.frames}
        if self.labels is not None or self.route is not None:
            d.update(labels=self.labels, route=self.route)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SceneSpec":
        return cls(str(d.get("name", "town")), int(d.get("seed", 0)), int(d.get("frames", 40)), d.get("labels"),
                   d.get("route"))


@functools.lru_cache(maxsize=16)
def _shipped_map(name: str) -> Path | None:
    """The shipped CARLA map called ``name`` ('Town06' or 'Town06.xodr') as a plain file, or None."""
    from place3d_kernels.data import CARLA_TOWNS, opendrive_path

    if name.removesuffix(".xodr") not in CARLA_TOWNS:
        return None
    return opendrive_path(name)


def read_route(path) -> "np.ndarray":
    """Ego poses from a text file: one pose per line, 6 numbers ``x y z roll pitch yaw`` (metres, radians)
    or 3 numbers ``x y yaw`` (on the ground); commas or spaces; ``#`` starts a comment."""
    import numpy as np

    rows = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").split()
        if not line:
            continue
        try:
            v = [float(x) for x in line]
        except ValueError:
            raise ValueError(f"{path}:{n}: route rows are numbers (x y z roll pitch yaw, or x y yaw)") from None
        if len(v) == 3:
            v = [v[0], v[1], 0.0, 0.0, 0.0, v[2]]
        if len(v) != 6:
            raise ValueError(f"{path}:{n}: a route row has 6 numbers (x y z roll pitch yaw) or 3 (x y yaw), "
                             f"got {len(v)}")
        rows.append(v)
    if not rows:
        raise ValueError(f"{path}: no ego poses")
    return np.asarray(rows, dtype=np.float64)


#: Where scenes built ahead of need come from: a callable ``(SceneSpec) -> Scene | None`` set by the
#: application (its forked build, ``place3d_app.prefetch``); None: every scene is built here.
_supplier = None


def supply_scenes(supplier) -> None:
    """Let ``supplier(scene_spec)`` hand over scenes built elsewhere (None where it has none); the library
    asks it before building a scene itself. ``None`` removes it."""
    global _supplier
    _supplier = supplier


@functools.lru_cache(maxsize=4)
def _build_scene(spec: SceneSpec):
    scene = None if _supplier is None else _supplier(spec)
    return make_scene(spec) if scene is None else scene


def make_scene(spec: SceneSpec):
    """Build the scene ``spec`` names, here and now."""
    from place3d_kernels import scene as scenes

    if spec.name == "town":
        return scenes.town(seed=spec.seed, n_frames=spec.frames)
    if spec.kind == "opendrive":
        return scenes.from_opendrive(str(spec.path), seed=spec.seed, n_frames=spec.frames)
    if spec.kind == "mesh":
        route = None if spec.route is None else read_route(spec.route)
        return scenes.load_scene(spec.path, labels=spec.labels, ego_poses=route)
    if spec.kind == "semantickitti":
        raise ValueError(f"scene {spec.name!r} is recorded frames, not a scene to simulate; its P-SOG is built "
                         f"from the frames (evaluate / optimize)")
    spec.validate()
    raise ValueError(f"unknown scene {spec.name!r}")


# ============================================================================== grid
@dataclass(frozen=True)
class RoiSpec:
    """The ROI grid: a box (``roi``: None for the default 80 x 80 x 5 m, 3 sizes or 6 corners in metres,
    ``grid.roi_bounds``) at ``voxel_size`` metres (None: 0.1 m). Both None: the default grid itself."""

    voxel_size: float | None = None
    roi: tuple | None = None

    def __post_init__(self):
        if self.roi is not None:
            object.__setattr__(self, "roi", tuple(float(x) for x in self.roi))

    def grid(self) -> Grid:
        return roi_grid(self.roi, self.voxel_size)

    def to_dict(self) -> dict:
        # "roi" only when chosen, so the manifests of runs made before ROIs could be chosen still match
        return {"voxel_size": self.voxel_size, **({"roi": list(self.roi)} if self.roi is not None else {})}

    @classmethod
    def from_dict(cls, d: dict) -> "RoiSpec":
        v, roi = d.get("voxel_size"), d.get("roi")
        return cls(None if v is None else float(v), None if roi is None else tuple(roi))


# ============================================================================== condition
@dataclass(frozen=True)
class ConditionSpec:
    """An adverse condition as data (name, run seed, severity, sorted params); ``condition()`` builds the
    ``FrameCondition`` that applies it to frames."""

    name: str
    seed: int = 0
    severity: str | None = None
    params: tuple = ()          # sorted (key, value) pairs

    @classmethod
    def of(cls, cond) -> "ConditionSpec | None":
        """From a ``ConditionSpec``, a study-config dict, a ``FrameCondition`` or None (no condition)."""
        if cond is None or isinstance(cond, ConditionSpec):
            return cond
        if isinstance(cond, dict):
            return cls.from_dict(cond)
        return cls(cond.name, int(cond.seed), cond.severity, tuple(sorted(cond.params.items())))

    def condition(self, backend=None):
        """The ``FrameCondition`` (callable ``(frame, index) -> frame``) for ``backend``."""
        from place3d_kernels.pipeline import FrameCondition

        return FrameCondition(self.name, seed=self.seed, backend=backend, severity=self.severity,
                              **dict(self.params))

    @property
    def label(self) -> str:
        extra = "".join(f"-{k}{v}" for k, v in self.params)
        return f"{self.name}" + (f"-{self.severity}" if self.severity else "") + extra + f"-s{self.seed}"

    def to_dict(self) -> dict:
        return {"name": self.name, "seed": self.seed, "severity": self.severity, "params": dict(self.params)}

    @classmethod
    def from_dict(cls, d: dict) -> "ConditionSpec | None":
        """From ``to_dict()`` output or a study ``[[conditions]]`` table (extra keys are params);
        'clean' / 'none' / '' mean no condition (None)."""
        d = dict(d)
        name = d.pop("name")
        if name in (None, "", "clean", "none"):
            return None
        seed, sev = int(d.pop("seed", 0)), d.pop("severity", None)
        params = d.pop("params", {}) or {}
        params = {**params, **d}
        return cls(name, seed, sev, tuple(sorted(params.items())))


# ============================================================================== P-SOG
@dataclass(frozen=True)
class PSOGSpec:
    """The inputs of ``scene_psog`` as data.

    Args:
        scene: the scene; backend: backend name (or instance, locally) that builds it.
        grid: the ROI (a ``RoiSpec``; a voxel size or None is accepted and wrapped).
        condition: the adverse condition on the collection frames, or None.
        lidar: the collection LiDAR; frames_per_subset: k (None: ``DEFAULT_FRAMES_PER_SUBSET``).
        cache: cache folder, resolved in the driver (workers may have another $HOME); None: the default.
        mount: (6,) collection-sensor pose in the ego frame (None: ``simulate.DEFAULT_MOUNT``).
        vehicle: the ego body blocking the collection LiDAR's rays and, in the commands, the scored rigs'
            rays: a preset name (car, suv, van, truck) or a mesh file path; None (or "none"): no body, the
            paper's setting. The body's name and content hash enter the P-SOG cache key and manifest.
    """

    scene: SceneSpec
    backend: Any = None
    grid: RoiSpec = field(default_factory=RoiSpec)
    condition: ConditionSpec | None = None
    lidar: Any = COLLECTION_LIDAR
    frames_per_subset: int | None = None
    cache: str | None = None
    mount: tuple | None = None
    vehicle: str | None = None

    def __post_init__(self):
        if self.vehicle is not None and str(self.vehicle).strip().lower() in ("none", ""):
            object.__setattr__(self, "vehicle", None)
        if not isinstance(self.grid, RoiSpec):
            object.__setattr__(self, "grid", RoiSpec(None if self.grid is None else float(self.grid)))
        if self.mount is not None:
            object.__setattr__(self, "mount", tuple(float(v) for v in self.mount))

    def vehicle_body(self):
        """The ``VehicleBody`` named by ``vehicle`` (None for no body); memoised per process."""
        return _vehicle_body(self.vehicle)

    @property
    def voxel_size(self) -> float | None:
        return self.grid.voxel_size

    def check_mount(self) -> None:
        """``ValueError`` naming --roi when the collection LiDAR's mount lies outside the ROI."""
        from place3d_kernels.grid import check_inside
        from place3d_kernels.simulate import DEFAULT_MOUNT

        check_inside(self.grid.grid(), (DEFAULT_MOUNT if self.mount is None else self.mount)[:3],
                     "the collection LiDAR")

    def build(self, backend=None, cache: bool | str = True, progress: bool = False, aggregate=None,
              save_in_background: bool = False):
        """Run ``scene_psog`` (reading the on-disk cache when present) with an explicit backend / cache
        (``aggregate`` and ``save_in_background``: as ``scene_psog``'s; ``aggregate`` e.g.
        ``subset_records.records_aggregator(spec)``, which keeps the per-subset records of a cache miss for
        the intervals)."""
        from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET, scene_psog

        b = self.backend if backend is None else backend
        if self.scene.kind == "semantickitti":
            # recorded, labelled frames: the P-SOG comes straight from them (label scheme and mount from
            # the folder's sequence.json when it has one); nothing to simulate, so nothing to cache
            from place3d_kernels.io import psog_from_semantickitti

            if self.condition is not None:
                raise ValueError("--condition applies to simulated frames, not to a semantickitti: sequence")
            if self.vehicle is not None:
                raise ValueError(f"--vehicle {self.vehicle} blocks simulated rays; a semantickitti: sequence is "
                                 f"recorded (its own vehicle already in it): drop --vehicle for the P-SOG")
            return psog_from_semantickitti(self.scene.path, self.grid.grid(),
                                           self.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET, backend=b)
        cond = None if self.condition is None else self.condition.condition(b)
        return scene_psog(**self._psog_inputs(cache, cond), backend=b, progress=progress, aggregate=aggregate,
                          save_in_background=save_in_background)

    def subsets(self) -> int:
        """T, the subsets ``build`` votes for this drive (``pipeline.drive_subsets``; a generated scene's
        ``frames``), or 1 where the frames are not known before the scene is read (files, sequences)."""
        from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET, drive_subsets

        if self.scene.kind not in ("town", "opendrive"):
            return 1
        return drive_subsets(self.scene.frames, self.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET)

    def build_part(self, subsets: range, backend=None, cache: bool | str = True):
        """The P-SOG of the subsets ``subsets`` of this drive alone (``pipeline.part_psog``; never read from or
        written to the cache). ``cache``: the folder whose remembered scene keys are used and kept
        (``scene.keymemo``), so ``save`` finds the file name without building the scene again."""
        from place3d_kernels.pipeline import part_psog

        if self.scene.kind not in ("town", "opendrive"):
            raise ValueError(f"build_part: a {self.scene.kind} scene's drive is built whole (build)")
        b = self.backend if backend is None else backend
        inputs = self._psog_inputs(cache, None if self.condition is None else self.condition.condition(b))
        del inputs["cache"]
        return part_psog(subsets=subsets, backend=b, **inputs)

    def save(self, psog, cache: bool | str = True):
        """Write ``psog``, this drive's whole P-SOG (e.g. its ``build_part`` parts merged), to the cache file
        ``build`` reads (``pipeline.save_psog``); returns the file, or None without a cache."""
        from place3d_kernels.pipeline import save_psog

        cond = None if self.condition is None else self.condition.condition(None)
        return save_psog(psog, **self._psog_inputs(cache, cond))

    def cached(self, cache: bool | str = True, warn: bool = True):
        """The P-SOG ``build`` would read from the cache, or None; needs no backend (an application that
        probes its backend meanwhile asks this first and waits for the probe only on a miss). ``warn``: as
        ``pipeline.cached_psog``'s."""
        from place3d_kernels.pipeline import cached_psog

        if not cache or self.scene.kind == "semantickitti":
            return None
        cond = None if self.condition is None else self.condition.condition(None)
        return cached_psog(**self._psog_inputs(cache, cond), warn=warn)

    def cache_file(self, cache: bool | str = True) -> Path | None:
        """The cache file ``build`` would read, found without building the scene, or None when that cannot
        be known so: a scene whose cache key was never remembered (``scene.keymemo``), a scene read from a
        file or a recorded sequence, or no cache. The file may not exist; nothing is read or verified."""
        from place3d_kernels.pipeline import cache_file
        from place3d_kernels.scene.keymemo import identity, recall
        from place3d_kernels.sog import cache_folder

        if not cache or self.scene.kind not in ("town", "opendrive"):
            return None
        folder = cache_folder(cache)
        if recall(folder, identity(self.scene.to_dict(), self.scene.kind, self.scene.path)) is None:
            return None
        cond = None if self.condition is None else self.condition.condition(None)
        return cache_file(**self._psog_inputs(cache, cond))

    def _psog_inputs(self, cache, cond) -> dict:
        """``scene_psog``'s inputs but the backend: the scene (built here unless its key is remembered in
        the cache folder; then ``scene_psog`` builds it on a cache miss), grid, sensor, k, mount, body."""
        from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET
        from place3d_kernels.simulate import DEFAULT_MOUNT

        with section("P-SOG build: scene"):
            if cache:
                from place3d_kernels.sog import cache_folder

                scene = self.scene.for_cache(cache_folder(cache))
            else:
                scene = self.scene.build()
        return dict(scene=scene, grid=self.grid.grid(), lidar=resolve_lidar(self.lidar),
                    frames_per_subset=self.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET,
                    mount=DEFAULT_MOUNT if self.mount is None else self.mount, cache=cache, condition=cond,
                    body=self.vehicle_body())

    def load(self):
        """The P-SOG with this spec's backend and cache folder (memoised per process; tasks call this)."""
        return _load_psog(self)

    def resolved(self) -> "PSOGSpec":
        """The spec with a backend name and a cache folder fixed in the driver, ready to ship to tasks."""
        from place3d_kernels.sog import cache_dir

        return PSOGSpec(self.scene, backend_name(self.backend), self.grid, self.condition, self.lidar,
                        self.frames_per_subset, self.cache or str(cache_dir()), self.mount, self.vehicle)

    def to_dict(self) -> dict:
        return {"scene": self.scene.to_dict(), "backend": backend_name(self.backend) if self.backend else None,
                "grid": self.grid.to_dict(),
                "condition": None if self.condition is None else self.condition.to_dict(),
                "lidar": self.lidar if isinstance(self.lidar, str) else self.lidar.name,
                "frames_per_subset": self.frames_per_subset, "cache": self.cache,
                "mount": None if self.mount is None else list(self.mount), "vehicle": self.vehicle}

    @classmethod
    def from_dict(cls, d: dict) -> "PSOGSpec":
        cond = d.get("condition")
        return cls(SceneSpec.from_dict(d["scene"]), d.get("backend"), RoiSpec.from_dict(d.get("grid") or {}),
                   None if cond is None else ConditionSpec.from_dict(cond), d.get("lidar", COLLECTION_LIDAR),
                   d.get("frames_per_subset"), d.get("cache"), d.get("mount"), d.get("vehicle"))


@functools.lru_cache(maxsize=8)
def _vehicle_body(vehicle: str | None):
    from place3d_kernels.blindspot import vehicle_from_arg

    return vehicle_from_arg(vehicle)


@functools.lru_cache(maxsize=4)
def _load_psog(spec: PSOGSpec):
    return spec.build(cache=spec.cache if spec.cache else True)


# ============================================================================== CLI
def specs_from_args(args, frames_lidar=COLLECTION_LIDAR) -> PSOGSpec:
    """The P-SOG spec named by the CLI's common options (--scene, --seed, --frames, --voxel-size, --roi,
    --condition, --severity, --param, --backend, --vehicle), built once per command.

    ``--frames`` sweeps of ``frames_lidar`` (the collection LiDAR of the P-SOG; ``place3d simulate``: its
    --lidar; None: no check) must fit in memory (``simulate.check_frames``), checked before the scene is built."""
    cond = None
    params = parse_params(getattr(args, "param", []))
    if params and not getattr(args, "condition", None):
        raise ValueError(f"--param {sorted(params)} given without --condition; name the condition they belong to")
    if getattr(args, "severity", None) and not getattr(args, "condition", None):
        raise ValueError(f"--severity {args.severity} given without --condition; name the condition it applies to")
    if getattr(args, "condition", None):
        cond = ConditionSpec(args.condition, int(args.seed), args.severity, tuple(sorted(params.items())))
        cond.condition(None)            # an unknown name fails here, before any work starts
        check_condition_params(cond.name, params)
    voxel = getattr(args, "voxel_size", None)
    if voxel is not None and not voxel > 0:
        raise ValueError(f"--voxel-size must be > 0 metres, got {voxel}")
    roi = getattr(args, "roi", None)
    check_roi(roi, voxel)                # malformed or too many voxels for memory: refused before any work
    scene = SceneSpec(args.scene, args.seed, args.frames, getattr(args, "labels", None), getattr(args, "route", None))
    if frames_lidar is not None and scene.kind in ("town", "opendrive") and args.frames >= 1:
        from place3d_kernels.simulate import check_frames

        # before the scene is built: a town of 100,000 frames took minutes to build alone
        check_frames(args.frames, frames_lidar, announce=True)
    spec = PSOGSpec(scene.validate(), getattr(args, "backend", None), RoiSpec(voxel, roi), cond,
                    vehicle=getattr(args, "vehicle", None))
    spec.check_mount()                   # the collection LiDAR inside the ROI
    spec.vehicle_body()                 # an unknown preset or a missing mesh fails here, before any work
    return spec
