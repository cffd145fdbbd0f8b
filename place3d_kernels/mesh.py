"""Triangle meshes with one semantic label per face."""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.base import COORDINATE_LIMIT

__all__ = ["Mesh"]


def _twice_areas(vt: np.ndarray, f: np.ndarray) -> np.ndarray:
    """|(b - a) x (c - a)| per face of vertices given as columns ``vt`` (3, V): ``np.linalg.norm(np.cross(...),
    axis=1)`` to the bit (the same products and differences, the squares added x, y, z in order), without its
    (F, 3) temporaries: a town's 95k faces in 6.3 instead of 11.7 ms (dev VM)."""
    f0, f1, f2 = f[:, 0], f[:, 1], f[:, 2]
    ax, ay, az = (c[f1] - c[f0] for c in vt)
    bx, by, bz = (c[f2] - c[f0] for c in vt)
    x, y, z = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return np.sqrt(x * x + y * y + z * z)


class Mesh:
    """A labelled triangle mesh.

    Args:
        vertices: (V, 3) float positions in metres.
        faces: (F, 3) int vertex indices.
        labels: (F,) int Place3D class per face (see ``place3d_kernels.classes``); default 0 (unlabeled).

    Backends build their acceleration structure once per mesh and cache it on the object
    (``Mesh.handle(backend)``); vertices are shifted by ``Mesh.shift`` (float64, on the host) before they
    become float32 on a device, so far-from-origin scenes keep their precision. The handle also holds
    the face labels as they are at first use: a mesh's arrays are not meant to change after construction.
    """

    def __init__(self, vertices, faces, labels=None):
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"Mesh vertices must have shape (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"Mesh faces must have shape (F, 3), got {f.shape}")
        if len(f) == 0 or len(v) == 0:
            raise ValueError("Mesh is empty (no faces or no vertices): a scene needs at least one triangle")
        if not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"Mesh faces must be integer vertex indices, got dtype {f.dtype}")
        if not np.all(np.isfinite(v)):
            bad = int(np.argmax(~np.all(np.isfinite(v), axis=1)))
            raise ValueError(f"Mesh vertex {bad} is not finite: {v[bad].tolist()}")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"Mesh face indices must lie in [0, {len(v) - 1}], got range [{f.min()}, {f.max()}]")
        f = f.astype(np.int32)
        if labels is None:
            lab = np.zeros(len(f), dtype=np.int32)
        else:
            lab = np.asarray(labels).astype(np.int32).reshape(-1)
            if lab.shape != (len(f),):
                raise ValueError(f"Mesh labels must have one entry per face ({len(f)}), got {lab.shape}")
        vt = np.ascontiguousarray(v.T)          # columns: contiguous reductions and gathers
        area2 = _twice_areas(vt, f)
        if not np.any(area2 > 0):
            raise ValueError(f"Mesh is degenerate: all {len(f)} triangles have zero area")
        self.vertices = v
        self.faces = f
        self.labels = lab
        #: faces with non-zero area in world coordinates; only these are uploaded, so a triangle that is
        #: degenerate as given can never be hit, however the origin shift rounds its corners
        self.valid_faces = np.flatnonzero(area2 > 0).astype(np.int64)
        lo, hi = vt.min(axis=1), vt.max(axis=1)     # v.min(axis=0), v.max(axis=0): exact either way
        #: float64 offset subtracted from vertices and ray origins before kernels run
        self.shift = np.round((lo + hi) / 2.0)
        self._box = (lo, hi)
        self._handles: dict[object, object] = {}
        self._normals: np.ndarray | None = None
        #: the mesh whose vertices, faces and labels this one begins with (``extended``), else None
        self.prefix: Mesh | None = None
        self._parts: dict[object, object] = {}

    @classmethod
    def extended(cls, prefix: "Mesh", vertices, faces, labels=None) -> "Mesh":
        """``prefix`` followed by more triangles: ``faces`` index ``vertices``, which come after the prefix's.
        The same mesh as one made from the concatenated arrays, which also remembers ``prefix``: a backend
        that extends acceleration structures (``Backend.extends_meshes``) then builds the prefix's part once
        (kept on ``prefix``, ``part``) and per mesh only the rest's (an OpenDRIVE town's roads and ground,
        shared by the static meshes of all its routes, ``scene.opendrive``)."""
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(faces).reshape(-1, 3)
        if not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"Mesh faces must be integer vertex indices, got dtype {f.dtype}")
        lab = np.zeros(len(f), dtype=np.int32) if labels is None else np.asarray(labels).astype(np.int32).reshape(-1)
        mesh = cls(np.concatenate([prefix.vertices, v]), np.concatenate([prefix.faces, f + len(prefix.vertices)]),
                   np.concatenate([prefix.labels, lab]))
        mesh.prefix = prefix
        return mesh

    def __getstate__(self) -> dict:
        # a pickled mesh (a scene sent from a prefetching child) travels without its prefix: the arrays hold it
        # already, and a prefix's tree is only shared within a process
        state = dict(self.__dict__)
        state["prefix"], state["_parts"] = None, {}
        return state

    def part(self, backend) -> object:
        """``backend.mesh_part`` of this mesh's uploaded faces, built on first use and kept: what the meshes
        ``extended`` from this one reuse on that backend."""
        p = self._parts.get(backend)
        if p is None:
            v, faces, _, _ = self.upload_parts()
            p = self._parts[backend] = backend.mesh_part(v, faces)
        return p

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    @property
    def normals(self) -> np.ndarray:
        """(F, 3) unit face normals (zero for degenerate faces), computed once."""
        if self._normals is None:
            v, f = self.vertices, self.faces
            n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            norm = np.linalg.norm(n, axis=1, keepdims=True)
            self._normals = n / np.where(norm > 0, norm, 1.0)
        return self._normals

    @property
    def bounds(self) -> np.ndarray:
        return np.stack(self._box)

    def handle(self, backend) -> object:
        """The backend's acceleration structure for this mesh, built on first use."""
        # keyed by the backend object, not its name: two instances with one name (e.g. an fp32 and an
        # fp64 OpenCL backend) own buffers in different device contexts
        h = self._handles.get(backend)
        if h is None:
            v, faces, ids, labels = self.upload_parts()
            if getattr(backend, "raycast_checks_rays", False):
                # the face map and labels travel with the BVH, so raycast_checked reports this mesh's
                # face ids and labels without a host pass
                extra = {}
                if self.prefix is not None and getattr(backend, "extends_meshes", False) \
                        and len(self.prefix.valid_faces) < len(faces):
                    # the prefix's uploaded faces are this mesh's first ones (the same vertices, so the same
                    # non-zero areas); its part is built in its own frame, moved by the shifts' difference
                    extra["prefix"] = (self.prefix.part(backend), self.prefix.shift - self.shift)
                h = backend.upload_mesh(v, faces, face_ids=ids, labels=labels, **extra)
            else:   # backends written before upload_mesh took the tables need not know them
                h = backend.upload_mesh(v, faces)
            self._handles[backend] = h
        return h

    def upload_parts(self):
        """What a backend uploads: (shifted vertices, the faces with non-zero area, their face ids (None when
        all are), their labels).

        Raises:
            ValueError: a vertex lies more than ``COORDINATE_LIMIT`` (1e5 m) from the mesh's centre on some
                axis: beyond what float32 backends represent (``backends/base.py``); refused on every backend.
        """
        lo, hi = self._box
        reach = float(np.max(np.maximum(hi - self.shift, self.shift - lo)))
        if not reach <= COORDINATE_LIMIT:
            raise ValueError(f"Mesh spans {(hi - lo).tolist()} m: its vertices reach {reach:.6g} m from its centre "
                             f"{self.shift.tolist()}, beyond the {COORDINATE_LIMIT:g} m that every backend accepts "
                             f"(float32 backends cannot place them to a voxel; backends/base.py COORDINATE_LIMIT). "
                             f"Split or crop the scene")
        if len(self.valid_faces) == len(self.faces):
            return self.vertices - self.shift, self.faces, None, self.labels
        return (self.vertices - self.shift, self.faces[self.valid_faces], self.valid_faces,
                self.labels[self.valid_faces])

    def original_face(self, uploaded: np.ndarray) -> np.ndarray:
        """Map face ids of the uploaded (non-degenerate) faces back to this mesh's face ids (-1 stays)."""
        uploaded = np.asarray(uploaded, dtype=np.int64)
        if len(self.valid_faces) == len(self.faces):
            return uploaded
        return np.where(uploaded >= 0, self.valid_faces[np.clip(uploaded, 0, None)], -1)

    @staticmethod
    def concatenate(meshes: list["Mesh"]) -> "Mesh":
        meshes = [m for m in meshes if m is not None]
        if not meshes:
            raise ValueError("Mesh.concatenate needs at least one mesh")
        offs = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(np.concatenate([m.vertices for m in meshes]),
                    np.concatenate([m.faces + o for m, o in zip(meshes, offs)]),
                    np.concatenate([m.labels for m in meshes]))

    def to_trimesh(self):
        import trimesh
        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def __repr__(self) -> str:
        return f"Mesh({len(self.vertices)} vertices, {self.n_faces} faces, labels {sorted(set(self.labels.tolist()))[:8]}...)"
