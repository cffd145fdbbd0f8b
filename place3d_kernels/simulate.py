"""Semantic LiDAR simulation: frames of labelled returns along a scene's ego route.

Ego body. With ``body=`` (a ``VehicleBody`` in the ego frame) the collection LiDAR's rays are blocked by the
ego vehicle, which moves with the ego pose: a ray whose first hit is the body gives no return (a real
pipeline drops the sensor's own-vehicle returns; they are not part of the scene). The sensor's rays are
the same in the ego frame every frame, so the body is cast once per sweep pattern in the ego frame (float64
t along the unit ray) and each frame keeps the scene hits nearer than that t. ``body=None`` is the
paper's setting (no ego body).
"""

from __future__ import annotations

import logging
import os

import numpy as np

from place3d_kernels.backends.base import first_far_row
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.classes import REFLECTIVITY
from place3d_kernels.lidar import LidarModel
from place3d_kernels.mesh import Mesh
from place3d_kernels.ops import Hits, MeshGroups, raycast
from place3d_kernels.pointcloud import PointCloud
from place3d_kernels.pose import pose_from_matrix, pose_matrix
from place3d_kernels.profiling import section
from place3d_kernels.rig_metrics import check_outside_body

__all__ = ["simulate_frame", "simulate", "device_returns", "sensor_poses", "body_hits", "DEFAULT_MOUNT",
           "SWEEP_BATCH_RAYS", "check_frames", "simulation_size", "BYTES_PER_RETURN", "ANNOUNCE_RAYS"]

log = logging.getLogger(__name__)

#: Host memory of one return of a simulated frame (``PointCloud``: float64 point and origin, int32 label,
#: float32 intensity). ``simulate`` returns every frame, and a P-SOG build holds them all before it votes.
BYTES_PER_RETURN = 3 * 8 + 3 * 8 + 4 + 4

#: A simulation of at least this many rays says how big it is (frames x rays, memory) before it starts
#: (``check_frames(announce=True)``; about 1,500 frames of the collection LiDAR, minutes on a CPU).
ANNOUNCE_RAYS = 10 ** 8

#: Share of the physical memory the returns of one simulation may take: they are not all a run holds (the
#: scene with an actor mesh per frame, the vote's arrays, the process itself).
MEMORY_SHARE = 0.5

#: Pose of the collection LiDAR in the ego frame (roof centre, 2.5 m above ground).
DEFAULT_MOUNT = np.array([0.0, 0.0, 2.5, 0.0, 0.0, 0.0])

#: Rays ``simulate`` makes and casts into the static mesh per call: whole sweeps, up to this many (16 sweeps
#: of the 65,536-ray collection LiDAR; about 80 MB of rays and hits on the host). One call per sweep cost a
#: ray launch, a ray-mesh launch and their downloads per frame.
SWEEP_BATCH_RAYS = 1 << 20

#: ``PLACE3D_ACTOR_GROUPS=0``: cast each frame's actors through a tree of their own (one build and one cast
#: per frame) also where the backend can cast all frames' actors through one grouped tree (``MeshGroups``)
ACTOR_GROUPS_ENV = "PLACE3D_ACTOR_GROUPS"

#: ``PLACE3D_DEVICE_RETURNS=0``: make every frame's returns on the host (``_returns``) also where the backend
#: makes them on its device (``device_returns``)
DEVICE_RETURNS_ENV = "PLACE3D_DEVICE_RETURNS"


def physical_memory() -> int | None:
    """Bytes of physical memory of this machine, or None where the system does not say."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def simulation_size(n_frames: int, lidar: LidarModel | str) -> tuple[int, int]:
    """(rays, bytes): the rays ``n_frames`` sweeps of ``lidar`` cast and the host memory their returns take
    at most (every ray a return)."""
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    rays = int(n_frames) * len(lidar.elevations) * len(lidar.azimuths)
    return rays, rays * BYTES_PER_RETURN


def check_frames(n_frames: int, lidar: LidarModel | str, what: str = "--frames", announce: bool = False) -> None:
    """Refuse a frame count whose returns cannot fit in this machine's memory (``simulate`` returns every
    frame; a P-SOG build holds them all), naming the most that can, before any work. With ``announce``, a
    simulation of ``ANNOUNCE_RAYS`` rays or more says how big it is (an INFO line on this module's logger,
    which the command prints unless --quiet).

    Raises:
        ValueError: the returns of ``n_frames`` sweeps of ``lidar`` could take more than ``MEMORY_SHARE`` of
            the physical memory.
    """
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    rays, size = simulation_size(n_frames, lidar)
    per_sweep = len(lidar.elevations) * len(lidar.azimuths)
    mem = physical_memory()
    if mem is not None and size > MEMORY_SHARE * mem:
        most = int(MEMORY_SHARE * mem) // simulation_size(1, lidar)[1]
        raise ValueError(f"{what} {n_frames} would hold up to {size / 2**30:,.0f} GiB of returns in memory "
                         f"({n_frames:,} frames x {per_sweep:,} rays of {lidar.name}); this machine has "
                         f"{mem / 2**30:.0f} GiB: use at most {most:,} frames (the paper uses 40)")
    if announce and rays >= ANNOUNCE_RAYS:
        log.info("simulating %s frames x %s rays of %s: %.3g rays, up to %.1f GiB of returns in memory; the "
                 "scene and the frames take a while", f"{n_frames:,}", f"{per_sweep:,}", lidar.name, rays,
                 size / 2**30)


def _intensity(normals: np.ndarray, d: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Lambertian return: class reflectivity times |cos(incidence)| (``normals``: the hit faces' normals)."""
    cos = np.abs(np.einsum("ij,ij->i", normals, d))
    return (REFLECTIVITY[np.clip(labels, 0, len(REFLECTIVITY) - 1)] * cos).astype(np.float32)


def simulate_frame(static: Mesh, dynamic: Mesh | None, lidar: LidarModel, sensor_pose_world: np.ndarray,
                   backend=None, body_t=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cast one LiDAR sweep into a static mesh (+ optional dynamic mesh); keep the closest hits.

    Args:
        body_t: optional (R,) distance along each ray of the sweep to the ego body (inf where the ray
            misses it, see :func:`body_hits`); a ray whose scene hit is not nearer than this gives no return.

    Returns:
        points (N, 3) world, labels (N,), intensity (N,), origin (3,) of the sweep.
    """
    b = get_backend(backend)
    with section("simulate: rays"):
        o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, np.asarray(sensor_pose_world)[None])
    with section("simulate: static mesh"):
        hits = raycast(static, o, d, lidar.max_range, backend=b)
    return _returns(static, dynamic, lidar, o, d, hits, b, body_t)


def _returns(static: Mesh, dynamic: Mesh | None, lidar: LidarModel, o, d, hits, b, body_t, dh=None,
             intensity: bool = True, faces: bool = False):
    """``simulate_frame`` after its sweep's rays ``o``, ``d`` were cast into the static mesh (``hits``) and,
    when ``dh`` is given, into the actors' mesh ``dynamic``; without ``intensity`` the returns' intensities
    are None (no normals read). With ``faces``, a fifth item: (from_actors (N,) bool, face (N,) int32), the
    mesh and face each return hit."""
    t, face, lab, src = hits.t, hits.face, hits.label, np.zeros(len(o), dtype=bool)
    if dynamic is not None:
        if dh is None:
            with section("simulate: actors' BVH"):
                dynamic.handle(b)           # built here, so that the profile tells it from the cast below
            with section("simulate: actors' mesh"):
                dh = raycast(dynamic, o, d, lidar.max_range, backend=b)
        closer = dh.t < t
        t = np.where(closer, dh.t, t)
        face = np.where(closer, dh.face, face)
        lab = np.where(closer, dh.label, lab)
        src = closer
    hit = np.isfinite(t)
    if body_t is not None:
        body_t = np.asarray(body_t, dtype=np.float64)
        if body_t.shape != t.shape:
            raise ValueError(f"body_t must hold one distance per ray ({t.shape}), got {body_t.shape}")
        # the body is hit first (ties included): the return is the ego vehicle's own, dropped
        hit &= t < body_t
    # one gather per array, by index; ndarray.take along axis 0 gives the rows that d[at] gives, several
    # times faster for (N, 3) arrays
    at = np.flatnonzero(hit)
    d_hit, face_hit, lab_hit = d.take(at, axis=0), face.take(at), lab.take(at)
    pts = o.take(at, axis=0) + t.take(at)[:, None] * d_hit
    hit_ids = (src.take(at), face_hit.astype(np.int32)) if faces else None
    if not intensity:
        return (pts, lab_hit.astype(np.int32), None, o[0]) + ((hit_ids,) if faces else ())
    if dynamic is None:                         # every return is the static mesh's
        normals = static.normals.take(face_hit, axis=0)
    else:
        # each return's normal from the mesh it hit: both tables read at the face id (clipped into the other
        # table's range, where np.where does not pick it), so one intensity pass serves all returns
        s_hit = src.take(at)
        normals = np.where(s_hit[:, None],
                           dynamic.normals.take(np.minimum(face_hit, len(dynamic.normals) - 1), axis=0),
                           static.normals.take(np.minimum(face_hit, len(static.normals) - 1), axis=0))
    inten = _intensity(normals, d_hit, lab_hit)
    return (pts, lab_hit.astype(np.int32), inten, o[0]) + ((hit_ids,) if faces else ())


def body_hits(body, lidar: LidarModel, mount=DEFAULT_MOUNT, backend=None) -> np.ndarray | None:
    """(R,) float64 distance along each ray of one sweep from ``mount`` (ego frame) to ``body``; inf where
    the ray misses it. None for no body.

    Raises:
        ValueError: the mount lies inside (or on) the body (the message names its position).
    """
    if body is None:
        return None
    b = get_backend(backend)
    m = np.asarray(mount, dtype=np.float64).reshape(6)
    msg = check_outside_body(body, m[None, :3])
    if msg:
        raise ValueError(f"collection {msg}")
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, m[None])
    return np.asarray(raycast(body.mesh, o, d, lidar.max_range, backend=b).t, dtype=np.float64)


def sensor_poses(scene, frames, mount=DEFAULT_MOUNT) -> np.ndarray:
    """(F, 6) world poses of the sensor mounted at ``mount`` (ego frame) at each of ``frames``: ``simulate``'s."""
    mount_T = pose_matrix(np.asarray(mount, dtype=np.float64))
    return np.stack([pose_from_matrix(pose_matrix(scene.ego_poses[f]) @ mount_T) for f in frames])


def device_returns(static: Mesh, groups, lidar: LidarModel, poses, backend=None, first: int = 0):
    """``simulate``'s returns without intensities and without an ego body (each frame's points, labels and
    origin) of one sweep from each of ``poses`` ((F, 6) sensor poses, ``sensor_poses``) into ``static`` and,
    with ``groups`` (a ``MeshGroups`` of the frames' actor meshes), sweep k into mesh ``first + k`` too, made
    on the backend's device (``sweep_returns``): the same arrays as ``simulate``'s host pass
    (``_returns``), without the rays and their hits coming to the host. None where the backend cannot (no
    ``sweep_returns``, no grouped casts) or a ray would fail ``raycast``'s checks: then the host pass.

    Returns:
        one (points (H, 3) float64, labels (H,) int32, origin (3,)) per sweep, or None.
    """
    b = get_backend(backend)
    poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 6)
    if not hasattr(b, "sweep_returns") or not len(poses) or first_far_row(poses[:, :3], static.shift) >= 0:
        return None
    handle = shifts = None
    if groups is not None:
        if not 0 <= first <= len(groups.meshes) - len(poses):
            raise ValueError(f"sweeps {first}..{first + len(poses) - 1} need as many actor meshes, "
                             f"got {len(groups.meshes)}")
        handle, shifts = groups.handle_near(poses[:, :3]), groups.shifts
        if handle is None:
            return None
    return b.sweep_returns(static.handle(b), static.shift, handle, shifts, lidar.elevations, lidar.azimuths, poses,
                           lidar.max_range, first)


def simulate(scene, lidar: LidarModel | str = "collection_64ch", mount=DEFAULT_MOUNT, frames=None,
             backend=None, progress: bool = False, body=None, dynamic=None,
             intensity: bool = True, hit_faces: bool = False):
    """Semantic LiDAR frames along the scene's ego route (world points, ego pose, sensor origin per return).

    Args:
        scene: a ``Scene``.
        lidar: the sensor model (default: the dense collection LiDAR used to build P-SOGs).
        mount: (6,) pose of the sensor in the ego frame.
        frames: indices of the frames to simulate (default: all).
        backend: backend name or instance.
        progress: show a progress bar.
        body: optional ``VehicleBody`` (ego frame) blocking the sensor's rays (None: the paper's setting).
        dynamic: optional dict {frame: ``scene.dynamic(frame)``} of meshes already built (``scene_psog``
            builds some while the backend is still being probed); each is taken out of the dict when its
            frame is cast, and frames not in it are built here.
        intensity: compute each return's intensity (False: the frames' intensities are zeros and no face
            normal is read; a P-SOG without a condition votes on labels alone, so ``scene_psog`` skips
            them there).
        hit_faces: also say which triangle each return hit: returns (frames, faces), ``faces`` one
            (from_actors, face) pair per frame: (N,) bool, True where the return is on the frame's actors
            (``scene.dynamic(f)``, actors concatenated in ``scene.actors`` order) rather than the static
            mesh, and (N,) int32 face index into that mesh. The frames are the same as without it.

    Returns:
        list of ``PointCloud``, one per frame (with ``hit_faces``: (that list, the faces list)).
    """
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    idx = range(scene.n_frames) if frames is None else frames
    body_t = body_hits(body, lidar, mount, backend)
    frames = list(idx)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(frames), desc="simulate", unit="frame", leave=False)
    # the sweeps of up to SWEEP_BATCH_RAYS rays at a time: their rays made in one call and cast into the
    # static mesh in one call (each ray's hit is its own, so these are the per-frame calls' arrays); the
    # actors, a mesh per frame, through one grouped tree where the backend has one (MeshGroups: a subtree
    # per frame, one cast per call), else frame by frame
    per_batch = max(1, SWEEP_BATCH_RAYS // max(len(lidar.elevations) * len(lidar.azimuths), 1))
    b = get_backend(backend)
    groups = None
    if (scene.actors and frames and os.environ.get(ACTOR_GROUPS_ENV, "1").strip() != "0"
            and MeshGroups.supported(b)):
        # every frame's actor mesh in one tree with a subtree per frame
        with section("simulate: actors (build)"):
            groups = MeshGroups([dynamic.pop(f) if dynamic and f in dynamic else scene.dynamic(f) for f in frames], b)
    # the returns made on the device where nothing the host pass adds is asked for (intensities, an ego body,
    # hit faces) and the backend can (device_returns: Warp): the rays and their hits stay there
    on_device = (not intensity and body is None and not hit_faces and hasattr(b, "sweep_returns")
                 and (groups is not None or not scene.actors)
                 and os.environ.get(DEVICE_RETURNS_ENV, "1").strip() != "0")
    out, faces = [], []
    for at in range(0, len(frames), per_batch):
        batch = frames[at:at + per_batch]
        sensor = sensor_poses(scene, batch, mount)
        got = None
        if on_device:
            with section("simulate: returns on the device"):
                got = device_returns(scene.static, groups, lidar, sensor, b, first=at)
        if got is not None:
            for f, (pts, lab, origin) in zip(batch, got):
                out.append(PointCloud(pts, lab, None, origin, ego_pose=scene.ego_poses[f].copy()))
                if bar is not None:
                    bar.update(1)
            continue
        with section("simulate: rays"):
            o_all, d_all = b.lidar_rays(lidar.elevations, lidar.azimuths, sensor)
        with section("simulate: static mesh"):
            h_all = raycast(scene.static, o_all, d_all, lidar.max_range, backend=b)
        rays_per_sweep = len(o_all) // len(batch)      # lidar_rays: sweep after sweep, each the same size
        dh_all = None
        if groups is not None:
            with section("simulate: actors, grouped"):
                dh_all = groups.cast(o_all, d_all, lidar.max_range, rays_per_sweep, first=at)
        for j, f in enumerate(batch):
            with section("simulate: actors (build)"):
                if groups is not None:
                    dyn = groups.meshes[at + j]
                else:
                    dyn = dynamic.pop(f) if dynamic and f in dynamic else scene.dynamic(f)
            r = slice(j * rays_per_sweep, (j + 1) * rays_per_sweep)
            hits = Hits(h_all.t[r], h_all.face[r], h_all.label[r])
            dh = None if dh_all is None else Hits(dh_all.t[r], dh_all.face[r], dh_all.label[r])
            pts, lab, inten, origin, *ids = _returns(scene.static, dyn, lidar, o_all[r], d_all[r], hits, b, body_t,
                                                     dh, intensity, hit_faces)
            if hit_faces:
                faces.append(ids[0])
            out.append(PointCloud(pts, lab, inten, origin, ego_pose=scene.ego_poses[f].copy()))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return (out, faces) if hit_faces else out
