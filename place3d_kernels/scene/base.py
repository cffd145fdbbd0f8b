"""Scenes: a static labelled mesh, dynamic actors per frame, and an ego route."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from place3d_kernels.mesh import Mesh

__all__ = ["Scene", "Actor"]


@dataclass
class Actor:
    """A rigid labelled body that moves between frames.

    Attributes:
        mesh: the body in its own frame (x forward, z up, origin on the ground under its centre).
        poses: (n_frames, 6) world poses per frame.
        kind: free-form tag ("vehicle", "pedestrian", ...).
    """

    mesh: Mesh
    poses: np.ndarray
    kind: str = ""


@dataclass
class Scene:
    """A drive through a world.

    Attributes:
        static: the static world as one labelled Mesh (its acceleration structure is built once).
        ego_poses: (n_frames, 6) world poses (x, y, z, roll, pitch, yaw) of the ego vehicle per frame;
            z = 0 of the ego frame is the ground under the vehicle centre.
        actors: moving bodies (their poses have n_frames rows).
        name, seed: provenance; ``key`` identifies the scene for on-disk caches.
        frame_interval: seconds between frames.
    """

    static: Mesh
    ego_poses: np.ndarray
    actors: list[Actor] = field(default_factory=list)
    name: str = "scene"
    seed: int = 0
    frame_interval: float = 0.5
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ego_poses = np.asarray(self.ego_poses, dtype=np.float64).reshape(-1, 6)
        for a in self.actors:
            if len(a.poses) != len(self.ego_poses):
                raise ValueError(f"Actor {a.kind!r} has {len(a.poses)} poses for {len(self.ego_poses)} frames")

    @property
    def n_frames(self) -> int:
        return len(self.ego_poses)

    @property
    def key(self) -> str:
        """Identity for on-disk caches: name, seed, and a hash of the builder version (``meta["builder"]``,
        if any), geometry, labels, route and actors."""
        if "_key" not in self.__dict__:
            import hashlib

            h = hashlib.blake2b(digest_size=12)
            # a builder version (meta["builder"]) keys what the geometry hash may not show (actor kinds, boxes)
            if "builder" in self.meta:
                h.update(str(self.meta["builder"]).encode())
            for arr in (self.static.vertices, self.static.faces, self.static.labels, self.ego_poses):
                h.update(np.ascontiguousarray(arr).tobytes())
            for a in self.actors:
                for arr in (a.mesh.vertices, a.mesh.faces, a.mesh.labels, a.poses):
                    h.update(np.ascontiguousarray(arr).tobytes())
            self.__dict__["_key"] = f"{self.name}-seed{self.seed}-f{self.n_frames}-{h.hexdigest()}"
        return self.__dict__["_key"]

    def dynamic(self, frame: int) -> Mesh | None:
        """All actors at one frame as one Mesh (None when the scene has no actors)."""
        from place3d_kernels.pose import pose_matrix

        if not self.actors:
            return None
        # one Mesh of the moved actors, the same arrays as Mesh.concatenate of one Mesh per actor (each
        # actor's vertices moved alike; faces shifted by the vertices before them), without validating and
        # measuring every actor's moved copy on its own (actor meshes were validated when they were made)
        verts, faces, labels, offset = [], [], [], 0
        for a in self.actors:
            T = pose_matrix(a.poses[frame])
            verts.append(a.mesh.vertices @ T[:3, :3].T + T[:3, 3])
            faces.append(a.mesh.faces + offset)
            labels.append(a.mesh.labels)
            offset += len(a.mesh.vertices)
        return Mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(labels))

    def keep_prebuilt(self, dynamic: dict) -> None:
        """Keep actor meshes per frame (``{frame: dynamic(frame)}``) made ahead, e.g. in another process,
        for the next ``take_prebuilt``."""
        self.__dict__["_prebuilt"] = dict(dynamic)

    def take_prebuilt(self) -> dict:
        """The actor meshes kept by ``keep_prebuilt`` (handed out once), else {}."""
        return self.__dict__.pop("_prebuilt", {})

    def mesh(self, frame: int) -> Mesh:
        """Static world plus the actors at ``frame``."""
        dyn = self.dynamic(frame)
        return self.static if dyn is None else Mesh.concatenate([self.static, dyn])
