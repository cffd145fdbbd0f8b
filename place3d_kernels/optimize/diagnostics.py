"""Diagnostics of an optimised rig: is the winner real, or did it game the metric?

M-SOG divides the entropy summed over the covered voxels by their number N_L. A voxel no frame ever saw
occupied has entropy 0, so a rig whose beams cross empty air (LiDARs rolled to the bound, beams to the sky)
gains covered voxels that cost nothing and lower the mean (docs/metric-normalisation.md). The signs:
several variables on a bound of the search box, and a small share of covered voxels that carry entropy
compared with the paper's placements. ``diagnose`` reports both and flags a ``degenerate`` winner;
``holdout`` re-scores the winner and the baselines on P-SOGs of other routes or towns.
"""

from __future__ import annotations

import math
import re

import numpy as np

from place3d_kernels.metrics import coverage_counts, score_from_counts

__all__ = ["bound_variables", "coverage_shares", "diagnose", "holdout", "format_diagnostics", "format_holdout",
           "SHARE_RATIO", "BOUND_TOL"]

#: "Much lower": the winner's entropy share below this fraction of the baselines' median share.
#: A judgement call, not a derived constant (docs/metric-normalisation.md gives the figures it was set from).
SHARE_RATIO = 0.8
#: A value within this distance (metres or radians) of a bound, or of the outermost grid value, is on it.
BOUND_TOL = 1e-9


def _label(name: str) -> str:
    """'roll[2]' -> 'lidar2.roll' (per-LiDAR variable); a shared variable keeps its name."""
    m = re.fullmatch(r"(\w+)\[(\d+)\]", name)
    return f"lidar{m.group(2)}.{m.group(1)}" if m else name


def bound_variables(space, x, delta=None) -> list[str]:
    """Variables of vector ``x`` of ``space`` that sit on a bound, e.g. ``"lidar2.roll = -0.3 (lower bound)"``.

    A variable is on a bound when it equals the bound or, on the delta grid (``delta`` given), the
    outermost grid value inside it (the grid is anchored at 0, so a bound that is not a multiple of delta
    is not itself reachable). Variables whose bounds coincide (fixed) are never reported.
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    lo, hi = space.lower.copy(), space.upper.copy()
    if delta is not None:
        steps = space.grid_steps(delta)
        kmin, kmax = space.grid_index_bounds(delta)
        lo, hi = np.maximum(lo, kmin * steps), np.minimum(hi, kmax * steps)
    out = []
    for name, v, a, b, la, hb in zip(space.names, x, lo, hi, space.lower, space.upper):
        if b - a <= BOUND_TOL:
            continue
        if v <= a + BOUND_TOL:
            out.append(f"{_label(name)} = {v:+.4g} (lower bound)")
        elif v >= b - BOUND_TOL:
            out.append(f"{_label(name)} = {v:+.4g} (upper bound)")
    return out


def coverage_shares(psog, lidar, poses, occlusion="sog", task="seg", backend=None) -> list[dict]:
    """Per rig of ``poses`` (P, L, 6): N_L, covered voxels with evidence / with H > 0, their shares of N_L,
    and M-SOG under each normalisation (exact integer counts from ``coverage_counts``)."""
    c = coverage_counts(psog, lidar, poses, occlusion, task, backend)
    scores = {n: score_from_counts(c, n) for n in ("paper", "evidence", "uncertain")}
    rows = []
    for i in range(len(c["sum"])):
        n = int(c["n_covered"][i])
        rows.append({"n_covered": n, "n_evidence": int(c["n_evidence"][i]), "n_uncertain": int(c["n_uncertain"][i]),
                     "entropy_share": c["n_uncertain"][i] / n if n else None,
                     "evidence_share": c["n_evidence"][i] / n if n else None,
                     "msog": {k: _finite(v[i]) for k, v in scores.items()}})
    return rows


def _finite(v):
    return float(v) if math.isfinite(v) else None


def diagnose(psog, lidar, search_space, best_poses, baselines: dict, delta=None, occlusion="sog", task="seg",
             backend=None) -> dict:
    """Bound variables, entropy shares and a ``degenerate`` verdict for an optimised rig.

    Args:
        psog, lidar: the P-SOG and LiDAR model the rig was optimised on.
        search_space: the space actually searched (``OptimizeResult.search_space``: fixed heights are not
            variables there, so they are not reported as bound-hugging).
        best_poses: (L, 6) poses of the winner.
        baselines: ``{name: (L, 6) poses}`` of the reference rigs (the paper's placements); may be empty.
        delta: the search grid step (bounds are compared with the outermost grid values).
        occlusion, task, backend: as for ``msog_batch``.

    Returns:
        dict with ``on_bounds`` (list of "lidar2.roll = -0.3 (lower bound)"), ``n_on_bounds``,
        ``n_variables``, ``n_lidars``, ``best`` and ``baselines`` (``coverage_shares`` rows),
        ``baseline_median_entropy_share``, ``bound_hugging``, ``degenerate`` and ``reason`` (one line).
    """
    best_poses = np.asarray(best_poses, dtype=np.float64)
    x = search_space.from_poses(best_poses[None])[0]
    on = bound_variables(search_space, x, delta)
    names = list(baselines)
    stack = np.stack([best_poses] + [np.asarray(baselines[n], dtype=np.float64) for n in names])
    rows = coverage_shares(psog, lidar, stack, occlusion, task, backend)
    best, base = rows[0], dict(zip(names, rows[1:]))
    n_l = int(best_poses.shape[0])
    # bound-hugging: on average at least one variable per LiDAR pinned to the box
    hugging = len(on) >= max(1, n_l)
    shares = [r["entropy_share"] for r in base.values() if r["entropy_share"] is not None]
    med = float(np.median(shares)) if shares else None
    bs = best["entropy_share"]
    low = med is not None and bs is not None and bs < SHARE_RATIO * med
    degenerate = bool(hugging and low)
    if bs is None:
        reason = "the rig covers no voxel"
    elif degenerate:
        reason = (f"{len(on)} of {len(x)} variables on a bound and only {bs:.1%} of its {best['n_covered']:,} "
                  f"covered voxels carry entropy (baselines' median {med:.1%}): its score comes from beams "
                  f"through never-occupied voxels (H = 0), not from certain ones")
    elif med is None:
        reason = "no baselines to compare the entropy share with"
    elif hugging:
        reason = (f"{len(on)} variables on a bound, but its entropy share {bs:.1%} is close to the baselines' "
                  f"median {med:.1%}")
    else:
        reason = f"{len(on)} variables on a bound; entropy share {bs:.1%} vs baselines' median {med:.1%}"
    return {"on_bounds": on, "n_on_bounds": len(on), "n_variables": int(len(x)), "n_lidars": n_l,
            "best": best, "baselines": base, "baseline_median_entropy_share": med, "share_ratio": SHARE_RATIO,
            "bound_hugging": bool(hugging), "degenerate": degenerate, "reason": reason}


def holdout(scenes, lidar, best_poses, baselines: dict, occlusion="sog", task="seg", backend=None,
            normalisation="paper") -> list[dict]:
    """Re-score the winner and the baselines on held-out P-SOGs.

    Args:
        scenes: iterable of ``(scene_name, seed, psog)``.
        best_poses, baselines: as in ``diagnose``.
        normalisation: the M-SOG denominator the run optimised.

    Returns:
        one dict per scene: ``scene``, ``seed``, ``best``, ``baselines`` ({name: score}),
        ``beats_all_baselines`` (strictly above every baseline), ``entropy_share`` of the winner.
    """
    names = list(baselines)
    stack = np.stack([np.asarray(best_poses, np.float64)] + [np.asarray(baselines[n], np.float64) for n in names])
    out = []
    for scene, seed, psog in scenes:
        rows = coverage_shares(psog, lidar, stack, occlusion, task, backend)
        sc = [r["msog"][normalisation] for r in rows]
        best, base = sc[0], dict(zip(names, sc[1:]))
        beats = best is not None and all(v is None or best > v for v in base.values())
        out.append({"scene": scene, "seed": int(seed), "best": best, "baselines": base,
                    "beats_all_baselines": bool(beats), "entropy_share": rows[0]["entropy_share"]})
    return out


def _fmt(v, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def format_diagnostics(d: dict) -> list[str]:
    """Printable lines of a ``diagnose`` result."""
    b = d["best"]
    lines = [f"diagnostics: N_L {b['n_covered']:,} covered voxels, {_fmt(b['entropy_share'], '.1%')} carry entropy "
             f"(H > 0), {_fmt(b['evidence_share'], '.1%')} have occupancy evidence"]
    lines.append("  on a bound: " + ("; ".join(d["on_bounds"]) if d["on_bounds"] else "none"))
    for name, r in sorted(d["baselines"].items(), key=lambda kv: -(kv[1]["entropy_share"] or 0)):
        lines.append(f"  {name:14s} N_L {r['n_covered']:>10,}  entropy share {_fmt(r['entropy_share'], '.1%')}")
    lines.append(("DEGENERATE: " if d["degenerate"] else "not degenerate: ") + d["reason"])
    return lines


def format_holdout(rows: list[dict]) -> list[str]:
    """Printable lines of a ``holdout`` result."""
    lines = []
    for r in rows:
        top = max((v for v in r["baselines"].values() if v is not None), default=None)
        verdict = "beats every baseline" if r["beats_all_baselines"] else "does NOT beat every baseline"
        if not r["baselines"]:
            verdict = "no baselines to compare"
        lines.append(f"held out {r['scene']} seed {r['seed']}: best {_fmt(r['best'], '.6f')}, best baseline "
                     f"{_fmt(top, '.6f')}: {verdict}")
    return lines
