"""The optimality certificate of Place3D (paper Theorem 1 and its corollary), estimated from samples.

Theorem 1: with ``k_G`` the Lipschitz constant of ``G`` (l2 norm) and ``C_M >= max_S G - min_S G`` over
the delta-density grid S, the grid optimum is within ``C_M + k_G * delta`` of the global optimum.
Corollary: on a box with side lengths ``U_i``, the bound is ``k_G * sum_i U_i + k_G * delta``.

Estimators (as the paper suggests, from the values of G at the evaluated grid samples):
  * ``k_G``: the largest slope ``|G(u) - G(v)| / ||u - v||_2`` over all pairs of distinct evaluated
    points (exact over all pairs up to ``max_points`` samples; above that over a fixed, seeded subset of
    ``max_points`` samples that always keeps the best ones). This is a LOWER bound on the true Lipschitz
    constant, so the certificate is an estimate, not a guarantee.
  * ``C_M``: ``max G - min G`` over the evaluated samples (again a lower estimate of the grid range).
  * ``bound = C_M + k_G * delta`` with ``delta`` the grid step, as in the paper. Strictly, the theorem's
    delta is the grid's covering radius (every point of the box within delta of a grid point); for a
    grid of step ``s`` in n dimensions that is about ``s * sqrt(n) / 2``. It is reported as ``delta_l2``
    with ``bound_l2 = C_M + k_G * delta_l2``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["certificate"]


def _max_slope(U: np.ndarray, G: np.ndarray) -> tuple[float, int]:
    n, D = U.shape
    chunk = max(1, 4_000_000 // max(1, n * max(D, 1)))  # rows per block: about 32 MB of differences
    best, pairs = 0.0, 0
    for a in range(0, n, chunk):
        Ua, Ga = U[a:a + chunk], G[a:a + chunk]
        # pairs (i, j) with j > i only
        j0 = a + 1
        if j0 >= n:
            break
        Ub, Gb = U[j0:], G[j0:]
        d = np.sqrt(((Ua[:, None, :] - Ub[None, :, :]) ** 2).sum(-1))
        dg = np.abs(Ga[:, None] - Gb[None, :])
        ii = np.arange(a, a + len(Ua))[:, None]
        jj = np.arange(j0, n)[None, :]
        mask = (jj > ii) & (d > 0)
        pairs += int(mask.sum())
        if mask.any():
            best = max(best, float(np.max(np.where(mask, dg / np.where(d > 0, d, 1.0), 0.0))))
    return best, pairs


def certificate(points, values, delta, side_lengths, delta_l2: float | None = None,
                max_points: int = 4000) -> dict:
    """Estimate k_G, C_M and the bounds of Theorem 1 and its corollary.

    Args:
        points: (n, D) evaluated grid points, in the searched coordinates (metres, radians).
        values: (n,) values of G at them (non-finite values are ignored).
        delta: grid step (a scalar; with a per-variable step pass the largest).
        side_lengths: (D,) side lengths U_i of the searched box.
        delta_l2: covering radius of the grid, if known (else ``delta``).
        max_points: exact all-pairs slope estimate up to this many samples.

    Returns:
        dict with ``k_G``, ``C_M``, ``bound``, ``bound_corollary``, ``delta``, ``delta_l2``, ``bound_l2``,
        ``n_samples``, ``n_pairs``, ``subsampled`` and ``estimator`` (all JSON-safe; values are None
        when there are no samples).
    """
    U = np.asarray(points, dtype=np.float64)
    G = np.asarray(values, dtype=np.float64)
    if U.ndim != 2 or G.shape != (len(U),):
        raise ValueError(f"certificate needs points (n, D) and values (n,), got {U.shape} and {G.shape}")
    keep = np.isfinite(G)
    U, G = U[keep], G[keep]
    delta = float(delta)
    delta_l2 = delta if delta_l2 is None else float(delta_l2)
    sides = np.asarray(side_lengths, dtype=np.float64)
    out = {"k_G": None, "C_M": None, "bound": None, "bound_corollary": None, "delta": delta,
           "delta_l2": delta_l2, "bound_l2": None, "sum_U": float(sides.sum()), "n_samples": int(len(U)),
           "n_pairs": 0, "subsampled": False,
           "estimator": "k_G = max |G(u)-G(v)|/||u-v||_2 over pairs of distinct evaluated grid points; "
                        "C_M = max G - min G over evaluated points (both lower estimates)"}
    if len(U) == 0:
        return out
    C_M = float(G.max() - G.min())
    if len(U) > max_points:
        rng = np.random.default_rng(0)
        order = np.argsort(G, kind="stable")
        top = order[: max_points // 4]
        rest = rng.choice(order[max_points // 4:], size=max_points - len(top), replace=False)
        sel = np.sort(np.concatenate([top, rest]))
        U, G = U[sel], G[sel]
        out["subsampled"] = True
    k, pairs = _max_slope(U, G)
    out.update(k_G=k, C_M=C_M, bound=C_M + k * delta, bound_corollary=k * float(sides.sum()) + k * delta,
               bound_l2=C_M + k * delta_l2, n_pairs=pairs)
    return out
