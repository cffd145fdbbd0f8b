"""The search space of a placement optimisation: which pose components vary, their bounds, the grid.

A parameter vector holds, LiDAR by LiDAR, the per-LiDAR variables in the order given by ``variables``
(``[x0, y0, z0, roll0, x1, y1, ...]`` by default), followed by the shared variables (one value for the
whole rig, e.g. the common height of a fixed-height study). Components that are not variables are fixed.

The grid (the paper's delta-density grid) is anchored at 0: grid values are integer multiples
``k * delta`` of the step, so that optimised placements read like the paper's (``0.4``, ``2.6``,
``-0.3``) whatever the bounds. Only the multiples inside ``[lower, upper]`` belong to the grid, so a
snapped point never leaves the bounds; a bound that is not itself a multiple of delta is simply not a
grid value (snapping rounds to the nearest inside multiple).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from place3d_kernels.placement import Placement

__all__ = ["SearchSpace", "POSE_KEYS", "DEFAULT_BOUNDS", "DEFAULT_DELTA", "MAX_LIDARS"]

#: Pose components, in the column order of a (L, 6) pose array.
POSE_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")
_COL = {k: i for i, k in enumerate(POSE_KEYS)}
_ANGLES = ("roll", "pitch", "yaw")

#: The paper's search box above the roof (ego frame, metres and radians).
DEFAULT_BOUNDS = {"x": (-0.6, 0.6), "y": (-0.6, 0.6), "z": (2.2, 2.8), "roll": (-0.3, 0.3)}
#: The paper's grid density: 0.1 m for positions, 0.1 rad for angles.
DEFAULT_DELTA = 0.1
MAX_LIDARS = 8

# Grid values are rounded to this many decimals so that 3 * 0.1 reads 0.3 (stable cache keys, clean files).
_DECIMALS = 12


def _names(seq, what: str) -> tuple[str, ...]:
    if isinstance(seq, str):
        seq = (seq,)
    seq = tuple(seq)
    for v in seq:
        if v not in _COL:
            raise ValueError(f"Unknown {what} {v!r}; pose components are {list(POSE_KEYS)}")
    if len(set(seq)) != len(seq):
        raise ValueError(f"Duplicate names in {what}s {list(seq)}")
    return seq


class SearchSpace:
    """Variables, bounds and fixed values of the LiDAR poses being optimised.

    Args:
        n_lidars: number of LiDARs in the rig, 1 to 8.
        bounds: ``{name: (lower, upper)}`` per variable, merged over the paper's box
            ``x, y in [-0.6, 0.6] m, z in [2.2, 2.8] m, roll in [-0.3, 0.3] rad``; pitch and yaw have no
            default and need bounds when they are variables. Entries for non-variables are ignored.
        variables: pose components optimised per LiDAR (any of x, y, z, roll, pitch, yaw).
        fixed: values of the components that are not variables: a scalar for all LiDARs or one value
            per LiDAR. Angles that are neither variables nor fixed default to 0; x, y, z must be one or
            the other.
        shared: variables (a subset of ``variables``) that take one common value for the whole rig,
            e.g. ``shared=("z",)`` for LiDARs at one free common height.

    Raises:
        ValueError: bad LiDAR count, unknown names, empty or inverted bounds, missing values.
    """

    def __init__(self, n_lidars: int = 4, bounds: Mapping | None = None,
                 variables: Sequence[str] = ("x", "y", "z", "roll"), fixed: Mapping | None = None,
                 shared: Sequence[str] = ()):
        if isinstance(n_lidars, bool) or not isinstance(n_lidars, (int, np.integer)):
            raise ValueError(f"n_lidars must be an int from 1 to {MAX_LIDARS}, got {n_lidars!r}")
        if not 1 <= int(n_lidars) <= MAX_LIDARS:
            raise ValueError(f"n_lidars must be from 1 to {MAX_LIDARS}, got {n_lidars}")
        self.n_lidars = L = int(n_lidars)
        variables = _names(variables, "variable")
        shared = _names(shared, "shared variable")
        if not variables:
            raise ValueError("A search space needs at least one variable, e.g. variables=('x', 'y')")
        extra = [v for v in shared if v not in variables]
        if extra:
            raise ValueError(f"shared variables {extra} must also be listed in variables {list(variables)}")
        self.variables = variables
        self.shared = tuple(v for v in variables if v in shared)
        self.per_lidar = tuple(v for v in variables if v not in shared)

        given = dict(bounds or {})
        _names(tuple(given), "bounds key")
        merged = {**DEFAULT_BOUNDS, **given}
        self.bounds: dict[str, tuple[float, float]] = {}
        for v in variables:
            if v not in merged:
                raise ValueError(f"Variable {v!r} needs bounds, e.g. bounds={{'{v}': (-0.3, 0.3)}}")
            b = merged[v]
            try:
                lo, hi = (float(t) for t in b)
            except (TypeError, ValueError):
                raise ValueError(f"bounds[{v!r}] must be a pair (lower, upper), got {b!r}") from None
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"bounds[{v!r}] must be finite, got ({lo}, {hi})")
            if lo > hi:
                raise ValueError(f"bounds[{v!r}] = ({lo}, {hi}) is inverted: lower > upper")
            if lo == hi:
                raise ValueError(f"bounds[{v!r}] = ({lo}, {hi}) is empty; to hold {v} at {lo}, drop it "
                                 f"from variables and pass fixed={{'{v}': {lo}}}")
            self.bounds[v] = (lo, hi)

        fixed = dict(fixed or {})
        _names(tuple(fixed), "fixed key")
        both = [v for v in fixed if v in variables]
        if both:
            raise ValueError(f"{both} cannot be both variables and fixed; remove them from one of the two")
        self.fixed: dict[str, np.ndarray] = {}
        for k in POSE_KEYS:
            if k in variables:
                continue
            if k not in fixed:
                if k in _ANGLES:
                    fixed[k] = 0.0
                else:
                    raise ValueError(f"Pose component {k!r} is neither a variable nor fixed; add it to "
                                     f"variables or pass fixed={{'{k}': value}}")
            val = np.asarray(fixed[k], dtype=np.float64)
            if val.ndim == 0:
                val = np.full(L, float(val))
            if val.shape != (L,):
                raise ValueError(f"fixed[{k!r}] must be a scalar or {L} values (one per LiDAR), "
                                 f"got shape {val.shape}")
            if not np.all(np.isfinite(val)):
                raise ValueError(f"fixed[{k!r}] must be finite, got {val.tolist()}")
            self.fixed[k] = val + 0.0

        # Per-dimension layout.
        self.names: tuple[str, ...] = tuple(f"{v}[{i}]" for i in range(L) for v in self.per_lidar) + self.shared
        self._kind = [v for _ in range(L) for v in self.per_lidar] + list(self.shared)
        self.lower = np.array([self.bounds[v][0] for v in self._kind])
        self.upper = np.array([self.bounds[v][1] for v in self._kind])

    # ------------------------------------------------------------------ basics
    @property
    def dim(self) -> int:
        """Length D of a parameter vector."""
        return len(self.names)

    @property
    def widths(self) -> np.ndarray:
        """Side lengths ``upper - lower`` of the box, per dimension (D,)."""
        return self.upper - self.lower

    @property
    def dim_variables(self) -> tuple[str, ...]:
        """The pose component of each dimension (``'x'``, ``'roll'``, ...)."""
        return tuple(self._kind)

    def center(self) -> np.ndarray:
        return (self.lower + self.upper) / 2

    def to_dict(self) -> dict:
        """JSON-safe description; ``SearchSpace.from_dict(s.to_dict()) == s``."""
        return {"n_lidars": self.n_lidars, "variables": list(self.variables), "shared": list(self.shared),
                "bounds": {v: list(b) for v, b in self.bounds.items()},
                "fixed": {k: v.tolist() for k, v in self.fixed.items()}}

    @classmethod
    def from_dict(cls, d: Mapping) -> "SearchSpace":
        return cls(n_lidars=d["n_lidars"], bounds={k: tuple(v) for k, v in d["bounds"].items()},
                   variables=tuple(d["variables"]), fixed=d["fixed"], shared=tuple(d.get("shared", ())))

    def __eq__(self, other) -> bool:
        return isinstance(other, SearchSpace) and self.to_dict() == other.to_dict()

    def __repr__(self) -> str:
        fx = {k: (float(v[0]) if np.all(v == v[0]) else v.tolist()) for k, v in self.fixed.items()}
        sh = f", shared={self.shared}" if self.shared else ""
        return (f"SearchSpace(n_lidars={self.n_lidars}, variables={self.variables}{sh}, "
                f"bounds={self.bounds}, fixed={fx}, dim={self.dim})")

    def replace(self, **changes) -> "SearchSpace":
        """A copy with some constructor arguments changed."""
        d = {"n_lidars": self.n_lidars, "bounds": dict(self.bounds), "variables": self.variables,
             "fixed": {k: v.copy() for k, v in self.fixed.items()}, "shared": self.shared}
        d.update(changes)
        return SearchSpace(**d)

    # ------------------------------------------------------------- conversions
    def _as_2d(self, X) -> tuple[np.ndarray, bool]:
        X = np.asarray(X, dtype=np.float64)
        single = X.ndim == 1
        if single:
            X = X[None]
        if X.ndim != 2 or X.shape[1] != self.dim:
            raise ValueError(f"Expected parameter vectors of length {self.dim} ({', '.join(self.names)}), "
                             f"as shape ({self.dim},) or (P, {self.dim}); got shape {np.shape(X)}")
        return X, single

    def to_poses(self, X) -> np.ndarray:
        """Poses of parameter vectors: (P, D) -> (P, L, 6); a single (D,) vector -> (L, 6)."""
        X, single = self._as_2d(X)
        P, L = len(X), self.n_lidars
        poses = np.empty((P, L, 6))
        for k, val in self.fixed.items():
            poses[:, :, _COL[k]] = val[None, :]
        nper = len(self.per_lidar)
        if nper:
            per = X[:, :L * nper].reshape(P, L, nper)
            for j, v in enumerate(self.per_lidar):
                poses[:, :, _COL[v]] = per[:, :, j]
        for j, v in enumerate(self.shared):
            poses[:, :, _COL[v]] = X[:, L * nper + j][:, None]
        return poses[0] if single else poses

    def from_poses(self, poses) -> np.ndarray:
        """Parameter vectors of poses: (P, L, 6) -> (P, D); (L, 6) -> (D,).

        Fixed components are not checked; a shared variable takes the value of the first LiDAR.
        """
        p = np.asarray(poses, dtype=np.float64)
        single = p.ndim == 2
        if single:
            p = p[None]
        if p.ndim != 3 or p.shape[1:] != (self.n_lidars, 6):
            raise ValueError(f"Expected poses of shape (P, {self.n_lidars}, 6) or ({self.n_lidars}, 6), "
                             f"got {np.shape(poses)}")
        cols = [_COL[v] for v in self.per_lidar]
        per = p[:, :, cols].reshape(len(p), -1)
        sh = p[:, 0, [_COL[v] for v in self.shared]]
        X = np.concatenate([per, sh], axis=1) + 0.0
        return X[0] if single else X

    def from_placement(self, placement: Placement) -> np.ndarray:
        """The parameter vector (D,) of a placement with ``n_lidars`` LiDARs."""
        if not isinstance(placement, Placement):
            placement = Placement(placement)
        if len(placement) != self.n_lidars:
            raise ValueError(f"Placement {placement.name!r} has {len(placement)} LiDARs; this space has "
                             f"{self.n_lidars}")
        for v in self.shared:
            col = placement.poses[:, _COL[v]]
            if not np.all(col == col[0]):
                raise ValueError(f"Placement {placement.name!r} has different {v} values {col.tolist()}, "
                                 f"but {v} is shared by all LiDARs in this space")
        return self.from_poses(placement.poses)

    def to_placement(self, x, name: str = "") -> Placement:
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 1:
            raise ValueError(f"to_placement takes one vector of length {self.dim}, got shape {x.shape}")
        return Placement(self.to_poses(x), name=name)

    def contains(self, X, tol: float = 0.0) -> np.ndarray:
        """Whether each vector lies inside the bounds: (P, D) -> (P,) bool."""
        X, single = self._as_2d(X)
        ok = np.all((X >= self.lower - tol) & (X <= self.upper + tol), axis=1)
        return ok[0] if single else ok

    # -------------------------------------------------------------------- grid
    def grid_steps(self, delta=DEFAULT_DELTA) -> np.ndarray:
        """Grid step per dimension (D,). ``delta`` is one step for all, or ``{variable: step}``."""
        if isinstance(delta, Mapping):
            _names(tuple(delta), "delta key")
            missing = [v for v in self.variables if v not in delta]
            if missing:
                raise ValueError(f"delta mapping has no step for variables {missing}")
            steps = np.array([float(delta[v]) for v in self._kind])
        else:
            try:
                d = float(delta)
            except (TypeError, ValueError):
                raise ValueError(f"delta must be a positive number or {{variable: step}}, got {delta!r}") from None
            steps = np.full(self.dim, d)
        if not np.all(np.isfinite(steps) & (steps > 0)):
            raise ValueError(f"delta must be positive and finite, got {delta!r}")
        return steps

    def grid_index_bounds(self, delta=DEFAULT_DELTA) -> tuple[np.ndarray, np.ndarray]:
        """Integer index range ``[kmin, kmax]`` per dimension: grid values are ``k * step``.

        Raises:
            ValueError: a variable's bounds contain no multiple of its step.
        """
        steps = self.grid_steps(delta)
        kmin = np.ceil(self.lower / steps - 1e-9).astype(np.int64)
        kmax = np.floor(self.upper / steps + 1e-9).astype(np.int64)
        bad = np.flatnonzero(kmin > kmax)
        if len(bad):
            i = bad[0]
            raise ValueError(f"bounds of {self.names[i]} ({self.lower[i]}, {self.upper[i]}) contain no multiple "
                             f"of delta={steps[i]} (the grid is anchored at 0); widen the bounds or use a "
                             f"smaller delta")
        return kmin, kmax

    def grid_values(self, K, delta=DEFAULT_DELTA) -> np.ndarray:
        """Values of integer grid indices K (P, D) (or (D,)), rounded and kept inside the bounds."""
        steps = self.grid_steps(delta)
        K = np.asarray(K)
        X = np.round(K * steps, _DECIMALS)
        return np.clip(X, self.lower, self.upper) + 0.0  # + 0.0 turns -0.0 into 0.0 (stable bytes)

    def snap_indices(self, X, delta=DEFAULT_DELTA) -> np.ndarray:
        """Integer grid indices (int64) of the nearest grid points inside the bounds."""
        X, single = self._as_2d(X)
        if not np.all(np.isfinite(X)):
            raise ValueError("Cannot snap non-finite parameter vectors")
        steps = self.grid_steps(delta)
        kmin, kmax = self.grid_index_bounds(delta)
        K = np.clip(np.rint(X / steps), kmin, kmax).astype(np.int64)
        return K[0] if single else K

    def snap(self, X, delta=DEFAULT_DELTA) -> np.ndarray:
        """Nearest points of the delta grid inside the bounds (grid anchored at 0: values ``k * delta``).

        Args:
            X: (P, D) or (D,) parameter vectors (out-of-bounds values are clipped first).
            delta: grid step (metres for x, y, z; radians for angles), or ``{variable: step}``.
        """
        K = self.snap_indices(X, delta)
        return self.grid_values(K, delta)

    def grid_size(self, delta=DEFAULT_DELTA) -> int:
        """Number of grid points in the box (an exact Python int; can be astronomically large)."""
        kmin, kmax = self.grid_index_bounds(delta)
        return math.prod(int(n) for n in (kmax - kmin + 1))

    def covering_radius(self, delta=DEFAULT_DELTA) -> float:
        """Largest l2 distance from a point of the box to its nearest grid point (the theorem's delta)."""
        steps = self.grid_steps(delta)
        kmin, kmax = self.grid_index_bounds(delta)
        lo_gap = kmin * steps - self.lower
        hi_gap = self.upper - kmax * steps
        h = np.maximum(np.maximum(lo_gap, hi_gap), np.where(kmax > kmin, steps / 2, 0.0))
        return float(np.sqrt(np.sum(np.maximum(h, 0.0) ** 2)))
