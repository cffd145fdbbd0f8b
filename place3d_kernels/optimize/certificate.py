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

__all__ = ["certificate", "certify"]


def _pair_slopes(U: np.ndarray, G: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """|G_i - G_j| / ||U_i - U_j||_2 for index pairs (i, j), the sum of squares taken over the last axis of a
    contiguous array: the arithmetic that defines k_G's value here, bit for bit."""
    d = np.sqrt(((U[i] - U[j]) ** 2).sum(-1))
    return np.abs(G[i] - G[j]) / d


#: relative slack of the screening pass: ``pdist`` sums the squares in another order than NumPy, within
#: 24 u relative for 24 variables (u = 2^-53), far inside this
_SCREEN_SLACK = 1e-12


def _max_slope(U: np.ndarray, G: np.ndarray) -> tuple[float, int]:
    """(largest slope over the pairs of distinct points, number of such pairs).

    Screened with SciPy's ``pdist`` (all n (n-1) / 2 distances in C, many times faster than broadcasting the
    differences in NumPy, which was a visible part of a warm optimise through ``place3d serve`` for 2,000
    samples), then recomputed exactly (``_pair_slopes``) for every pair within ``_SCREEN_SLACK`` of the
    screened maximum. The pair that attains the exact maximum is among those, so the value is the exact one,
    whatever order ``pdist`` sums in.
    """
    from scipy.spatial.distance import pdist

    n = len(U)
    if n < 2:
        return 0.0, 0
    d = pdist(U)                                   # condensed: pairs (i, j), i < j, row by row
    if d.min() > 0:
        # every pair distinct (the usual case: the optimiser scores each grid point once): the slopes of
        # all pairs, in place, without the index arrays of the general case (three more arrays of n^2 / 2)
        pairs = len(d)
        screened = pdist(G[:, None], "cityblock")
        screened /= d
        cand = np.flatnonzero(screened >= screened.max() * (1.0 - _SCREEN_SLACK))
    else:
        pos = d > 0                                # d = 0 exactly when the points are equal
        pairs = int(pos.sum())
        if pairs == 0:
            return 0.0, 0
        k = np.flatnonzero(pos)
        screened = pdist(G[:, None], "cityblock")[k] / d[k]
        cand = k[screened >= screened.max() * (1.0 - _SCREEN_SLACK)]
    row_start = np.arange(n) * n - np.arange(n) * (np.arange(n) + 1) // 2
    i = np.searchsorted(row_start, cand, side="right") - 1
    j = cand - row_start[i] + i + 1
    return float(_pair_slopes(U, G, i, j).max()), pairs


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


def certify(points, values, feasible, **kw) -> dict:
    """``certificate(points, values, **kw)`` with a ``"feasible"`` entry: the certificate over the rows where
    ``feasible`` (bool (n,)) holds, the same dict when every row does. What ``optimize`` reports; a module-level
    function so that it can run in another process (``optimize(certificate_executor=...)``)."""
    U = np.asarray(points, dtype=np.float64)
    G = np.asarray(values, dtype=np.float64)
    feas = np.asarray(feasible, dtype=bool)
    cert = certificate(U, G, **kw)
    # over the feasible samples: when every sample is feasible, the same inputs and so the same dict
    cert["feasible"] = dict(cert) if feas.all() else certificate(U[feas], G[feas], **kw)
    return cert
