"""Placement constraints as penalties: ``P(u) = 0`` when feasible, ``> 0`` when violated (paper, Sec. 3.3).

Every constraint maps a batch of poses (P, L, 6) to penalties (P,) >= 0. The optimiser minimises
``G = -F + penalty_weight * sum(penalties)``. Before a run, each constraint may reshape the search space
(``FixedHeight`` turns z into a fixed or shared value, so that every candidate satisfies it exactly) and
check that it can be met at all (``MinDistance`` refuses a distance no arrangement in the box can keep).
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Sequence

import numpy as np

from place3d_kernels.optimize.space import DEFAULT_DELTA, POSE_KEYS, SearchSpace

__all__ = ["Constraint", "MinDistance", "FixedHeight", "Bounds", "FunctionConstraint", "total_penalty",
           "prepare"]


def _poses(poses) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 2:
        p = p[None]
    if p.ndim != 3 or p.shape[2] != 6:
        raise ValueError(f"Constraints take poses of shape (P, L, 6), got {np.shape(poses)}")
    return p


class Constraint:
    """Base class. Subclasses implement ``penalty``; ``adapt_space`` and ``check`` are optional hooks."""

    def penalty(self, poses) -> np.ndarray:  # pragma: no cover - interface
        """Penalties (P,) >= 0 for poses (P, L, 6); exactly 0 where the constraint holds."""
        raise NotImplementedError

    def adapt_space(self, space: SearchSpace) -> SearchSpace:
        """The space the optimiser should search instead (default: unchanged)."""
        return space

    def bind(self, space: SearchSpace) -> "Constraint":
        """The constraint as used with ``space`` (default: itself)."""
        return self

    def check(self, space: SearchSpace, delta=DEFAULT_DELTA) -> None:
        """Raise ValueError when the constraint obviously cannot hold anywhere in ``space``."""

    def describe(self) -> dict:
        """JSON-safe description (used to check that a resumed run has the same setup)."""
        return {"type": type(self).__name__}

    def __repr__(self) -> str:
        d = self.describe()
        args = ", ".join(f"{k}={v!r}" for k, v in d.items() if k != "type")
        return f"{d['type']}({args})"


class MinDistance(Constraint):
    """Centres of every two LiDARs at least ``d`` metres apart.

    Penalty: sum over LiDAR pairs of ``max(0, d - |c_i - c_j|)`` (metres of shortfall); shortfalls up to
    1e-9 m (floating-point rounding of grid points exactly ``d`` apart) count as feasible.
    """

    def __init__(self, d: float):
        d = float(d)
        if not (math.isfinite(d) and d > 0):
            raise ValueError(f"MinDistance needs a positive finite distance in metres, got {d}")
        self.d = d

    def describe(self) -> dict:
        return {"type": "MinDistance", "d": self.d}

    def penalty(self, poses) -> np.ndarray:
        p = _poses(poses)
        L = p.shape[1]
        if L < 2:
            return np.zeros(len(p))
        i, j = np.triu_indices(L, 1)
        dist = np.linalg.norm(p[:, i, :3] - p[:, j, :3], axis=-1)
        # a nanometre of slack: grid points exactly d apart (2.4 - 2.2 = 0.19999999999999973) are feasible,
        # as in the paper's "center" rig
        short = self.d - dist
        return np.where(short > 1e-9, short, 0.0).sum(axis=1)

    def check(self, space: SearchSpace, delta=DEFAULT_DELTA) -> None:
        L = space.n_lidars
        if L < 2:
            return
        why = self.impossibility(space, delta)
        if why:
            raise ValueError(f"MinDistance({self.d:g}) cannot hold {why}. Lower the distance, widen the bounds "
                             f"or use fewer LiDARs.")

        # 2) Quick constructive search on the grid (greedy farthest point); warn if it finds nothing.
        if not self._greedy_feasible(self._axes(space, delta), L):
            warnings.warn(f"MinDistance({self.d:g}): a quick search found no arrangement of {L} LiDARs on the "
                          f"delta grid that keeps this distance; it may be impossible, and the optimiser "
                          f"may end with an infeasible placement", RuntimeWarning, stacklevel=3)

    @staticmethod
    def _axes(space: SearchSpace, delta) -> list:
        # Reachable centre coordinates per axis: grid values of a per-LiDAR variable, a shared variable
        # (one value for all), or fixed values (one per LiDAR).
        kmin, kmax = space.grid_index_bounds(delta)
        steps = space.grid_steps(delta)
        axes = []
        for c, name in enumerate("xyz"):
            if name in space.fixed:
                axes.append(("fixed", space.fixed[name]))
                continue
            i = space.dim_variables.index(name)
            vals = np.clip(np.round(np.arange(kmin[i], kmax[i] + 1) * steps[i], 12), space.lower[i], space.upper[i])
            axes.append(("shared" if name in space.shared else "var", vals))
        return axes

    def impossibility(self, space: SearchSpace, delta=DEFAULT_DELTA) -> str | None:
        """Why no placement of ``space``'s LiDARs on the ``delta`` grid can keep this distance ("for L
        LiDARs in the search box (...): reason"), or None when the quick bounds find no reason."""
        L = space.n_lidars
        if L < 2:
            return None
        axes = self._axes(space, delta)
        # 1) Impossibility bounds (only when fixed coordinates do not already separate the LiDARs).
        if all(kind != "fixed" or np.all(v == v[0]) for kind, v in axes):
            ext = [float(v.max() - v.min()) if kind == "var" else 0.0 for kind, v in axes]
            live = [e for e in ext if e > 0]
            box = " x ".join(f"{e:g}" for e in ext)
            why = None
            if not live:
                why = "all LiDAR centres coincide (no position varies per LiDAR)"
            elif self.d > math.sqrt(sum(e * e for e in live)) + 1e-12:
                why = f"it exceeds the box diagonal {math.sqrt(sum(e * e for e in live)):.3g} m"
            elif len(live) == 1 and (L - 1) * self.d > live[0] + 1e-12:
                why = f"{L} LiDARs on a {live[0]:g} m segment are at most {live[0] / (L - 1):.3g} m apart"
            elif len(live) >= 2:
                r = self.d / 2
                ball = math.pi * r * r if len(live) == 2 else 4 / 3 * math.pi * r ** 3
                if L * ball > math.prod(e + self.d for e in live) * (1 + 1e-9):
                    why = (f"{L} disjoint balls of diameter {self.d:g} m do not fit around a "
                           f"{' x '.join(f'{e:g}' for e in live)} m region")
            if why is None and live:
                # pigeonhole: fewer than L cells of diameter < d -> two LiDARs share a cell
                for cuts in itertools.product(range(1, L), repeat=len(live)):
                    if math.prod(cuts) < L and \
                            math.sqrt(sum((e / c) ** 2 for e, c in zip(live, cuts))) < self.d - 1e-12:
                        why = (f"the region splits into {math.prod(cuts)} cells of diameter below {self.d:g} m, "
                               f"fewer than the {L} LiDARs")
                        break
            if why:
                return f"for {L} LiDARs in the search box (x, y, z extents {box} m): {why}"
        return None

    def _greedy_feasible(self, axes, L: int) -> bool:
        def thin(v):  # at most 25 values per axis, endpoints kept
            return v if len(v) <= 25 else v[np.unique(np.linspace(0, len(v) - 1, 25).round().astype(int))]

        # A shared coordinate is equal for all LiDARs and never separates them: any one value will do.
        per_axis = [np.array([v[l] for l in range(L)]) if kind == "fixed" else v[:1] if kind == "shared"
                    else thin(v) for kind, v in axes]

        def cand(l):
            vals = [p[l:l + 1] if kind == "fixed" else p for (kind, _), p in zip(axes, per_axis)]
            return np.stack(np.meshgrid(*vals, indexing="ij"), -1).reshape(-1, 3)

        first = cand(0)
        i, j = np.triu_indices(L, 1)
        for start in (0, len(first) - 1, len(first) // 2):
            chosen = [first[start]]
            for l in range(1, L):
                c = cand(l)
                dmin = np.min(np.linalg.norm(c[:, None, :] - np.asarray(chosen)[None], axis=-1), axis=1)
                chosen.append(c[int(np.argmax(dmin))])
            ch = np.asarray(chosen)
            if np.all(np.linalg.norm(ch[i] - ch[j], axis=-1) >= self.d - 1e-9):
                return True
        return False


class FixedHeight(Constraint):
    """All LiDARs at one height (the paper's 2-D plane study).

    With ``z`` given, the optimiser drops z from the variables and fixes every LiDAR at ``z``; with
    ``z=None`` the LiDARs share one free common height (z becomes a shared variable). Either way every
    candidate satisfies the constraint exactly, so its penalty is 0 during the search.

    Penalty (for poses from elsewhere): ``sum_l |z_l - z|``, or ``max z - min z`` when ``z`` is None.
    """

    def __init__(self, z: float | None = None):
        if z is not None:
            z = float(z)
            if not math.isfinite(z):
                raise ValueError(f"FixedHeight needs a finite height in metres (or None), got {z}")
        self.z = z

    def describe(self) -> dict:
        return {"type": "FixedHeight", "z": self.z}

    def penalty(self, poses) -> np.ndarray:
        zs = _poses(poses)[:, :, 2]
        if self.z is None:
            return zs.max(axis=1) - zs.min(axis=1)
        return np.abs(zs - self.z).sum(axis=1)

    def adapt_space(self, space: SearchSpace) -> SearchSpace:
        if "z" in space.fixed:
            zf = space.fixed["z"]
            if self.z is None and not np.all(zf == zf[0]):
                raise ValueError(f"FixedHeight() conflicts with the space's fixed heights {zf.tolist()}")
            if self.z is not None and not np.all(zf == self.z):
                raise ValueError(f"FixedHeight({self.z:g}) conflicts with the space's fixed heights {zf.tolist()}")
            return space
        if self.z is None:
            if "z" in space.shared:
                return space
            return space.replace(shared=tuple(space.shared) + ("z",))
        if space.variables == ("z",):
            raise ValueError(f"FixedHeight({self.z:g}) fixes z, the only variable of the space: nothing is "
                             f"left to optimise")
        fixed = {k: v for k, v in space.fixed.items()}
        fixed["z"] = self.z
        return space.replace(variables=tuple(v for v in space.variables if v != "z"),
                             shared=tuple(v for v in space.shared if v != "z"), fixed=fixed)


class Bounds(Constraint):
    """Pose components inside a box: penalty = total distance outside ``{name: (lower, upper)}``.

    Implicit in every run (candidates are snapped inside the search space's bounds, so this penalty is 0
    there); pass it explicitly with a narrower box to make that box a soft constraint. ``Bounds()``
    without a box takes the bounds of the search space it is used with.
    """

    def __init__(self, bounds: dict | SearchSpace | None = None):
        if isinstance(bounds, SearchSpace):
            bounds = bounds.bounds
        self.box = None if bounds is None else {k: (float(a), float(b)) for k, (a, b) in dict(bounds).items()}
        if self.box is not None:
            bad = [k for k in self.box if k not in POSE_KEYS]
            if bad:
                raise ValueError(f"Bounds: unknown pose components {bad}; use {list(POSE_KEYS)}")
            inv = {k: b for k, b in self.box.items() if not b[0] <= b[1]}
            if inv:
                raise ValueError(f"Bounds: inverted bounds {inv}")

    def describe(self) -> dict:
        return {"type": "Bounds", "bounds": None if self.box is None else {k: list(v) for k, v in self.box.items()}}

    def bind(self, space: SearchSpace) -> "Bounds":
        return self if self.box is not None else Bounds(space.bounds)

    def penalty(self, poses) -> np.ndarray:
        if self.box is None:
            raise ValueError("Bounds() without a box needs a search space: use Bounds(space) or pass it to optimize")
        p = _poses(poses)
        out = np.zeros(len(p))
        for k, (lo, hi) in self.box.items():
            v = p[:, :, POSE_KEYS.index(k)]
            out += (np.maximum(0.0, lo - v) + np.maximum(0.0, v - hi)).sum(axis=1)
        return out


class FunctionConstraint(Constraint):
    """A user penalty: ``fn(poses (P, L, 6)) -> (P,)`` finite values >= 0, 0 where feasible."""

    def __init__(self, fn, name: str | None = None):
        if not callable(fn):
            raise ValueError(f"FunctionConstraint needs a function poses -> penalties, got {fn!r}")
        self.fn = fn
        self.name = name or getattr(fn, "__qualname__", type(fn).__name__)

    def describe(self) -> dict:
        # "Callable" is the class's former name; checkpoints compare this description on resume, so it stays
        return {"type": "Callable", "name": self.name}

    def penalty(self, poses) -> np.ndarray:
        p = _poses(poses)
        v = np.asarray(self.fn(p), dtype=np.float64)
        if v.shape != (len(p),):
            raise ValueError(f"Constraint {self.name!r} returned shape {v.shape}; expected ({len(p)},), one "
                             f"penalty per candidate")
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise ValueError(f"Constraint {self.name!r} must return finite penalties >= 0, got {v.tolist()}")
        return v


def prepare(space: SearchSpace, constraints: Sequence[Constraint] | Constraint, delta=DEFAULT_DELTA
            ) -> tuple[SearchSpace, list[Constraint]]:
    """The space actually searched and the bound constraints, after adapting and checking.

    Raises:
        ValueError: a constraint is not a Constraint, two constraints conflict, or one cannot hold.
    """
    if isinstance(constraints, Constraint):
        constraints = [constraints]
    constraints = list(constraints or ())
    for c in constraints:
        if not isinstance(c, Constraint):
            raise ValueError(f"Constraints must be Constraint objects (MinDistance, FixedHeight, Bounds, "
                             f"FunctionConstraint); got {c!r}. Wrap a function as FunctionConstraint(fn).")
    search = space
    for c in constraints:
        search = c.adapt_space(search)
    bound = [c.bind(search) for c in constraints]
    for c in bound:
        c.check(search, delta)
    return search, bound


def total_penalty(constraints: Sequence[Constraint], poses) -> np.ndarray:
    """Sum of the penalties (P,) of all constraints."""
    p = _poses(poses)
    out = np.zeros(len(p))
    for c in constraints:
        out += c.penalty(p)
    return out
