"""Search over real rigs: N LiDAR slots, each with its own sensor model, on mounting surfaces of a body.

A slot's continuous genes live in [0, 1]: position DOFs move the unit on its surface (``x`` -> u,
``y`` -> v, ``z`` -> w, see ``place3d_kernels.mounting``; ``u``, ``v``, ``w`` are accepted too), angle DOFs
pick a fraction of the surface's allowed roll / pitch / yaw range. DOFs not chosen stay at the surface
centre (u = v = 0.5, w = 0) and its nominal look direction. With more than one surface each slot also has
an integer gene: which surface.

Which sensor sits in which slot is discrete. Slots are interchangeable (any slot may use any surface), so
a rig's sensors are a multiset: with few combinations (``ENUMERATE_MAX``) every multiset gets its own
CMA-ES, all run in lockstep so that each generation of every combination is scored in ONE
``Backend.score_rays`` launch (heterogeneous rigs: different sensors, ray counts and surfaces). With more,
one CMA-ES carries a sensor gene per slot as a pycma integer variable (``integer_variables``).

Penalties (minimised f = -M-SOG otherwise): a LiDAR inside the body or a rig covering nothing gets
``PENALTY``; LiDARs closer than ``min_separation`` add ``PENALTY`` plus the shortfall in metres.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from place3d_kernels.rig_metrics import msog_rigs

__all__ = ["RigProblem", "RigCandidate", "RigSearchResult", "search_rigs", "sensor_combinations", "ENUMERATE_MAX",
           "DOF_NAMES"]

ENUMERATE_MAX = 64
PENALTY = 10.0                  # larger than any -M-SOG (entropies of 22 classes are below ln 22 ~ 3.1)
DOF_NAMES = ("x", "y", "z", "u", "v", "w", "roll", "pitch", "yaw")
_POS = {"x": 0, "u": 0, "y": 1, "v": 1, "z": 2, "w": 2}
_ANG = ("roll", "pitch", "yaw")


@dataclass
class RigProblem:
    """What to search.

    Args:
        psog: the scene's P-SOG.
        sensors: ``{name: LidarModel}`` allowed sensor models.
        surfaces: ``{name: MountSurface}`` allowed surfaces.
        n_slots: LiDARs per rig (1-8).
        dofs: optimised DOFs (``DOF_NAMES``).
        body: the vehicle (None: no body).
        task, occlusion, backend: as ``msog_batch``.
        min_separation: metres between any two LiDAR origins.
        max_blind_extent: optional constraint, metres: at height ``blind_z`` no azimuth sector may see
            its nearest ground point farther than this from the body (``blindspot.max_blind_extent``);
            a rig breaking it gets ``PENALTY`` plus its blind area / 1000 m^2 (so the search can follow
            the area down towards feasible rigs).
        blind_z: plane height for that constraint, metres (0 road, 0.5 bumper height).
        normalisation: M-SOG denominator, as in ``msog_batch`` ("paper", "evidence", "uncertain").
    """

    psog: object
    sensors: dict
    surfaces: dict
    n_slots: int
    dofs: tuple
    body: object = None
    task: str = "seg"
    occlusion: str = "sog"
    backend: object = None
    min_separation: float = 0.2
    max_blind_extent: float | None = None
    blind_z: float = 0.0
    normalisation: str = "paper"

    def __post_init__(self):
        from place3d_kernels.metrics import check_normalisation

        check_normalisation(self.normalisation)
        if not 1 <= int(self.n_slots) <= 8:
            raise ValueError(f"a rig has 1-8 LiDARs, got {self.n_slots}")
        if not self.sensors:
            raise ValueError("the sensor list is empty; give at least one LiDAR preset")
        if not self.surfaces:
            raise ValueError("the surface list is empty; give at least one mounting surface")
        bad = [d for d in self.dofs if d not in DOF_NAMES]
        if bad or not self.dofs:
            raise ValueError(f"unknown or no DOFs {bad or list(self.dofs)}; choose from {list(DOF_NAMES)}")
        pos = [d for d in self.dofs if d in _POS]
        if len({_POS[d] for d in pos}) != len(pos):
            raise ValueError(f"DOFs {pos} name one surface axis twice (x = u, y = v, z = w); keep one of each")
        self.sensor_names = list(self.sensors)
        self.surface_names = list(self.surfaces)
        self.pos_axes = sorted({_POS[d] for d in pos})
        self.ang_keys = [a for a in _ANG if a in self.dofs]

    @property
    def genes_per_slot(self) -> int:
        """Continuous genes per slot (surface and sensor genes come after all of them)."""
        return len(self.pos_axes) + len(self.ang_keys)

    def decode(self, x, sensors: tuple | None) -> tuple[list, list, np.ndarray, np.ndarray]:
        """A genome to (sensor names, surface names, (L, 6) poses, (L, 3) u, v, w).

        Layout: L x continuous genes, then L surface genes (when more than one surface), then L sensor
        genes (when ``sensors`` is None: the integer sensor mode).
        """
        L, g = self.n_slots, self.genes_per_slot
        x = np.asarray(x, dtype=np.float64)
        cont = x[:L * g].reshape(L, g)
        k = L * g
        if len(self.surface_names) > 1:
            si = np.clip(np.floor(x[k:k + L] + 0.5).astype(int), 0, len(self.surface_names) - 1)
            k += L
        else:
            si = np.zeros(L, dtype=int)
        if sensors is None:
            ni = np.clip(np.floor(x[k:k + L] + 0.5).astype(int), 0, len(self.sensor_names) - 1)
            sensors = tuple(self.sensor_names[i] for i in ni)
        surf = [self.surface_names[i] for i in si]
        poses = np.zeros((L, 6))
        uvw = np.tile([0.5, 0.5, 0.0], (L, 1))
        for j in range(L):
            s = self.surfaces[surf[j]]
            for c, a in enumerate(self.pos_axes):
                uvw[j, a] = cont[j, c]
            uvw[j] = np.clip(uvw[j], 0.0, 1.0)
            poses[j, :3] = s.position(*uvw[j])
            for i, a in enumerate(_ANG):
                poses[j, 3 + i] = (s.angle(a, cont[j, len(self.pos_axes) + self.ang_keys.index(a)])
                                   if a in self.ang_keys else s.nominal[a])
        return list(sensors), surf, poses, uvw

    def x0(self, integer_sensors: bool) -> np.ndarray:
        """Start: surface centres at nominal angles; slot j on surface j mod S; sensor genes mid-range."""
        L = self.n_slots
        rows = []
        for j in range(L):
            s = self.surfaces[self.surface_names[j % len(self.surface_names)]]
            rows += [0.5 if a != 2 else 0.25 for a in self.pos_axes] + [s.nominal_fraction(a) for a in self.ang_keys]
        x = list(rows)
        if len(self.surface_names) > 1:
            x += [float(j % len(self.surface_names)) for j in range(L)]
        if integer_sensors:
            x += [float(j % len(self.sensor_names)) for j in range(L)]
        return np.asarray(x, dtype=np.float64)

    def bounds(self, integer_sensors: bool) -> tuple[list, list, list]:
        """Lower and upper bounds per gene and the indices of the integer genes."""
        L, g = self.n_slots, self.genes_per_slot
        lo, hi = [0.0] * (L * g), [1.0] * (L * g)
        ints = []
        for n in ([len(self.surface_names)] if len(self.surface_names) > 1 else []) + \
                 ([len(self.sensor_names)] if integer_sensors else []):
            ints += list(range(len(lo), len(lo) + L))
            lo += [0.0] * L
            hi += [float(n - 1)] * L
        return lo, hi, ints

    def score(self, rigs) -> tuple[np.ndarray, np.ndarray, list]:
        """(M-SOG (P,), minimised f (P,), reasons) of decoded rigs ``[(sensors, poses), ...]`` in one launch."""
        r = msog_rigs(self.psog, [([self.sensors[s] for s in sn], p) for sn, p in rigs], self.body, self.task,
                      self.occlusion, self.backend, normalisation=self.normalisation)
        f = np.where(np.isfinite(r.msog), -r.msog, PENALTY)
        reasons = list(r.reasons)
        for i, (_, p) in enumerate(rigs):
            o = np.asarray(p)[:, :3]
            if len(o) > 1:
                dist = np.linalg.norm(o[:, None] - o[None], axis=2)[np.triu_indices(len(o), 1)]
                short = float(np.maximum(self.min_separation - dist, 0.0).sum())
                if short > 0:
                    f[i] = PENALTY + short
                    reasons[i] = reasons[i] or f"LiDARs closer than {self.min_separation} m"
        if self.max_blind_extent is not None:
            from place3d_kernels.blindspot import blind_spot_map

            for i, (sn, p) in enumerate(rigs):
                if f[i] >= PENALTY:
                    continue
                # the reports' sectors (the default: whole degrees at or above the sensors' azimuth steps)
                m = blind_spot_map(self.body, [self.sensors[s] for s in sn], p, self.blind_z, cell=0.25,
                                   backend=self.backend)
                if not m.max_extent() <= self.max_blind_extent:
                    f[i] = PENALTY + m.area_m2 / 1000.0
                    ext = "a sector with no ground hit" if not np.isfinite(m.max_extent()) else \
                        f"{m.max_extent():.2f} m"
                    reasons[i] = f"blind spot at z = {self.blind_z:g} m reaches {ext} > {self.max_blind_extent:g} m"
        return np.where(f >= PENALTY, np.nan, r.msog), f, reasons


@dataclass
class RigCandidate:
    """One rig: its sensors, surfaces, poses, surface parameters and score (NaN when infeasible)."""

    sensors: list
    surfaces: list
    poses: np.ndarray
    uvw: np.ndarray
    msog: float
    reason: str = ""

    def to_dict(self) -> dict:
        return {"sensors": list(self.sensors), "surfaces": list(self.surfaces),
                "poses": np.round(self.poses, 6).tolist(), "uvw": np.round(self.uvw, 6).tolist(),
                "msog": None if not np.isfinite(self.msog) else float(self.msog), "infeasible": self.reason or None}


@dataclass
class RigSearchResult:
    """Best rig overall, best rig per sensor combination, evaluation and launch counts."""

    best: RigCandidate
    per_combination: list
    evaluations: int
    launches: int
    mode: str
    history: list = field(default_factory=list)


def sensor_combinations(names, n_slots: int, sizes=None) -> list[tuple]:
    """Multisets of sensor names for each rig size in ``sizes`` (default: just ``n_slots``)."""
    out = []
    for k in (sizes or [n_slots]):
        out += list(itertools.combinations_with_replacement(list(names), k))
    return out


def search_rigs(problem: RigProblem, max_evals: int, seed: int = 0, popsize: int | None = None,
                sigma0: float = 0.3, sizes=None, progress: bool = False) -> RigSearchResult:
    """Mixed discrete / continuous CMA-ES over rigs (see the module docstring).

    Args:
        problem: the ``RigProblem``.
        max_evals: evaluation budget, split evenly over sensor combinations (at least 2 each; the last
            generation may overrun a combination's share; ``evaluations`` reports the true count).
        seed: pycma seed (combination c uses seed + c).
        popsize: CMA-ES population (default pycma's).
        sigma0: initial step in gene units ([0, 1] for continuous genes).
        sizes: rig sizes to enumerate (Pareto runs over sensor counts); default ``[n_slots]``.
    """
    import cma

    from place3d_kernels.optimize.cmaes import quiet_pycma

    if max_evals < 1:
        raise ValueError(f"max_evals must be >= 1, got {max_evals}")
    combos = sensor_combinations(problem.sensor_names, problem.n_slots, sizes)
    integer = len(combos) > ENUMERATE_MAX
    if integer and sizes is not None and len(sizes) > 1:
        raise ValueError(f"{len(combos)} sensor combinations over rig sizes {sizes} is more than {ENUMERATE_MAX}; "
                         f"the Pareto run enumerates them: use fewer sensors or slots")
    runs = []
    n_runs = 1 if integer else len(combos)
    budget = max(2, max_evals // n_runs)
    for c, combo in enumerate([None] if integer else combos):
        sub = problem if combo is None else _resized(problem, len(combo))
        lo, hi, ints = sub.bounds(integer)
        # a budget below pycma's default population gets one generation of the budget's size
        lam = popsize or min(4 + int(3 * np.log(len(lo))), budget)
        opts = {"bounds": [lo, hi], "seed": seed + c + 1, "verbose": -9, "integer_variables": ints,
                "popsize": max(2, lam)}
        with quiet_pycma():
            es = cma.CMAEvolutionStrategy(sub.x0(integer), sigma0, opts)
        runs.append({"problem": sub, "combo": combo, "es": es, "evals": 0, "best": None})
    evals = launches = 0
    history = []
    while True:
        active = [r for r in runs if r["evals"] < budget and not r["es"].stop()]
        if not active:
            break
        asked, rigs, meta = [], [], []
        for r in active:
            with quiet_pycma():
                X = r["es"].ask()
            asked.append(X)
            for x in X:
                sn, surf, poses, uvw = r["problem"].decode(x, r["combo"])
                rigs.append((sn, poses))
                meta.append((r, sn, surf, poses, uvw))
        ms, f, reasons = problem.score(rigs)          # one score_rays launch for every active combination
        launches += 1
        evals += len(rigs)
        k = 0
        for r, X in zip(active, asked):
            fx = f[k:k + len(X)]
            with quiet_pycma():
                r["es"].tell(X, fx.tolist())
            r["evals"] += len(X)
            for i in range(len(X)):
                _, sn, surf, poses, uvw = meta[k + i]
                cand = RigCandidate(sn, surf, poses, uvw, float(ms[k + i]), reasons[k + i])
                if np.isfinite(cand.msog) and (r["best"] is None or cand.msog > r["best"].msog):
                    r["best"] = cand
            k += len(X)
        best_now = max((r["best"].msog for r in runs if r["best"] is not None), default=np.nan)
        history.append({"launch": launches, "evaluations": evals, "rigs_in_launch": len(rigs),
                        "best_msog": best_now})
        if progress:
            print(f"  launch {launches}: {len(rigs)} rigs, {evals} evaluations, best M-SOG {best_now:.6f}")
    per = []
    for r in runs:
        b = r["best"]
        if b is None:                                   # every candidate infeasible: report the start
            sn, surf, poses, uvw = r["problem"].decode(r["problem"].x0(integer), r["combo"])
            b = RigCandidate(sn, surf, poses, uvw, float("nan"), "no feasible rig found")
        per.append(b)
    feas = [c for c in per if np.isfinite(c.msog)]
    best = max(feas, key=lambda c: c.msog) if feas else per[0]
    return RigSearchResult(best, per, evals, launches, "integer" if integer else "enumerate", history)


def _resized(problem: RigProblem, n: int) -> RigProblem:
    if n == problem.n_slots:
        return problem
    return RigProblem(problem.psog, problem.sensors, problem.surfaces, n, problem.dofs, problem.body, problem.task,
                      problem.occlusion, problem.backend, problem.min_separation, problem.max_blind_extent,
                      problem.blind_z, problem.normalisation)
