"""Interval estimates from resampled scores: what the scores of P placements on R resamples say.

The resampling itself (which pool is scored, and how) is ``place3d_kernels.uncertainty``'s; this module
holds what it returns and how that is read, and needs no P-SOG, LiDAR or backend:

- ``Bootstrap``: scores on resamples drawn with replacement; a percentile interval per placement (Efron
  and Tibshirani, *An Introduction to the Bootstrap*, 1993, ch. 13), a standard error and the bias;
- ``Jackknife``: scores with each unit (subset or route) left out once, optionally stratified by scene,
  with normal or Student's t intervals (``route_df`` gives the routes' degrees of freedom);
- from either: ``P(A > B)`` per pair (``order_freq``, ``pairwise``), and the pairs whose order holds in
  fewer than ``NOISE_LEVEL`` (95 %) of resamples, "within noise" (``within_noise``);
- ``MIN_SUBSETS`` and ``too_few_subsets``: when a drive has too few subsets for any interval;
- ``interval_method`` (the method in words), ``plot_scores`` (the figure) and ``kendall_tau`` (rank
  agreement of two score vectors).
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist
from typing import Sequence

import numpy as np

__all__ = ["NOISE_LEVEL", "MIN_SUBSETS", "too_few_subsets", "interval_method", "Bootstrap", "Jackknife",
           "within_noise", "route_df", "pairwise", "kendall_tau", "plot_scores"]


#: An order of two placements counts as settled when it holds in at least this share of resamples.
NOISE_LEVEL = 0.95

#: Fewest subsets of one drive that an interval over them needs. Leaving one of two out (the jackknife), or
#: drawing one of them twice (the bootstrap), pools a single subset, whose every voxel holds one class: each
#: rescored M-SOG is 0, so the jackknife's interval has zero width and every order looks certain.
MIN_SUBSETS = 3


def too_few_subsets(n_subsets: int) -> str | None:
    """Why no interval over a drive's ``n_subsets`` subsets can be estimated (one line), or None."""
    if n_subsets >= MIN_SUBSETS:
        return None
    return f"intervals need at least {MIN_SUBSETS} subsets; this drive has {n_subsets}"


def interval_method(b) -> str:
    """What the intervals of ``b`` (a ``Bootstrap`` or ``Jackknife``) are, in words, for titles and legends:
    "jackknife over 8 routes ...", "jackknife over 10 subsets ..." or "bootstrap over 10 subsets ..."."""
    unit = "routes" if b.unit == "drives" else b.unit
    if getattr(b, "method", "bootstrap") == "jackknife":
        how = "each left out once"
        if getattr(b, "strata", None) is not None and len(set(b.strata)) > 1:
            how += ", stratified by scene"
        if getattr(b, "df", None) is not None:
            how += f", t with {b.df} df"
        return f"jackknife over {b.n_units} {unit} ({how})"
    return f"bootstrap over {b.n_units} {unit} ({len(b.samples)} resamples, percentile)"


@dataclass
class Bootstrap:
    """Scores of P placements on the full sample and on R resamples.

    Attributes:
        names: P placement names.
        point: (P,) scores on the full sample.
        samples: (R, P) scores on the resamples (NaN where a rig covered no voxel).
        level: interval coverage (0.95 = 2.5th..97.5th percentiles).
        unit: what was resampled ("drives" or "subsets") and how many (``n_units``).
    """

    names: list
    point: np.ndarray
    samples: np.ndarray
    level: float = 0.95
    unit: str = "drives"
    n_units: int = 0

    @property
    def ci(self) -> np.ndarray:
        """(P, 2) percentile interval."""
        a = (1.0 - self.level) / 2.0
        return np.nanquantile(self.samples, [a, 1.0 - a], axis=0).T

    @property
    def se(self) -> np.ndarray:
        """(P,) bootstrap standard error (sample sd of the resampled scores, ddof = 1)."""
        return np.nanstd(self.samples, axis=0, ddof=1)

    @property
    def bias(self) -> np.ndarray:
        """(P,) mean resampled score minus the point score. Entropy is concave, so a resample that repeats
        drives pools fewer distinct ones and scores higher: M-SOG's bootstrap bias is positive, and with
        few drives the point sits near the lower end of the percentile interval."""
        return np.nanmean(self.samples, axis=0) - self.point

    @property
    def order_freq(self) -> np.ndarray:
        """(P, P): entry [a, b] = share of resamples with score_a > score_b (ties count 1/2)."""
        s = self.samples
        gt = (s[:, :, None] > s[:, None, :]).mean(axis=0)
        eq = (s[:, :, None] == s[:, None, :]).mean(axis=0)
        return gt + 0.5 * eq

    def within_noise(self, level: float = NOISE_LEVEL) -> list[tuple[str, str, float]]:
        return within_noise(self, level)

    def to_dict(self) -> dict:
        ci = self.ci
        return {"names": list(self.names), "point": self.point.tolist(), "ci_low": ci[:, 0].tolist(),
                "ci_high": ci[:, 1].tolist(), "se": self.se.tolist(), "bias": self.bias.tolist(), "level": self.level, "unit": self.unit,
                "n_units": self.n_units, "n_resamples": int(len(self.samples)),
                "order_freq": np.round(self.order_freq, 4).tolist(),
                "within_noise": [list(p) for p in self.within_noise()]}


def within_noise(boot: Bootstrap, level: float = NOISE_LEVEL) -> list[tuple[str, str, float]]:
    """Pairs (A, B, P(A > B)) with A ahead on the full sample whose order holds in < ``level`` of resamples."""
    f = boot.order_freq
    out = []
    P = len(boot.names)
    for a in range(P):
        for b in range(a + 1, P):
            hi, lo = (a, b) if boot.point[a] >= boot.point[b] else (b, a)
            if f[hi, lo] < level:
                out.append((boot.names[hi], boot.names[lo], float(f[hi, lo])))
    return out


@dataclass
class Jackknife:
    """Delete-one-unit jackknife of P placements' scores (same reading interface as ``Bootstrap``).

    Leaving one subset (or drive) out never repeats a unit, so unlike the bootstrap it does not pool
    fewer distinct units than the full sample; for a smooth statistic such as the entropy of pooled
    frequencies it estimates the standard error and the bias at the cost of n rescorings (Efron & Tibshirani,
    "An Introduction to the Bootstrap", ch. 11). Intervals are point +- q * se, so they contain the point by
    construction; pairwise orders are F(d / se_d) with se_d the jackknife standard error of the difference
    of the two scores. q and F are the normal's, or Student's t with ``df`` degrees of freedom when ``df``
    is set (the routes' intervals: with a handful of routes the se itself is uncertain).

    Over routes of several scenes (``strata``: the scene of each unit) the scenes are the design and the
    routes the sample: the stratified jackknife (Wolter, "Introduction to Variance Estimation", 2nd ed.,
    2007, sec. 4.5) sums, per stratum h of n_h units, (n_h - 1) / n_h times the squared deviations of its
    leave-one-out scores from their stratum mean; a stratum of one unit adds nothing.

    Attributes:
        names: P placement names.
        point: (P,) scores on the full sample.
        samples: (n, P) leave-one-out scores (row i: unit i left out).
        strata: optional (n,) stratum label of each unit (None: one stratum).
        df: degrees of freedom of the t quantile (None: the normal's; ``route_df`` gives n - strata).
    """

    names: list
    point: np.ndarray
    samples: np.ndarray
    level: float = 0.95
    unit: str = "subsets"
    n_units: int = 0
    method: str = "jackknife"
    strata: tuple | None = None
    df: int | None = None

    def _groups(self):
        n = len(self.samples)
        if self.strata is None:
            return [np.arange(n)]
        lab = np.asarray(self.strata)
        if lab.shape != (n,):
            raise ValueError(f"strata must label each of the {n} units, got shape {lab.shape}")
        return [np.flatnonzero(lab == h) for h in dict.fromkeys(lab.tolist())]

    def _var(self, x: np.ndarray) -> np.ndarray:
        """Jackknife variance of the statistic whose leave-one-out values are ``x`` (n, ...)."""
        v = np.zeros(x.shape[1:])
        for idx in self._groups():
            m = len(idx)
            if m < 2:
                continue
            dev = x[idx] - np.nanmean(x[idx], axis=0)
            v = v + (m - 1) / m * np.nansum(dev * dev, axis=0)
        return v

    def _z(self) -> float:
        # the standard library's normal quantile: importing scipy.stats for it was a visible part of an optimise
        if self.df is None:
            return NormalDist().inv_cdf(0.5 + self.level / 2.0)
        if self.df < 1:
            return float("nan")         # no replication within any stratum: no interval
        from scipy.special import stdtrit

        return float(stdtrit(self.df, 0.5 + self.level / 2.0))

    def _cdf(self, z):
        if self.df is None:
            phi = NormalDist().cdf                                # Phi(+-inf) = 1, 0; Phi(0) = 1/2
            return np.array([phi(v) for v in np.ravel(z)], dtype=np.float64).reshape(np.shape(z))
        from scipy.special import stdtr

        return stdtr(max(self.df, 1), z)

    @property
    def se(self) -> np.ndarray:
        return np.sqrt(self._var(np.asarray(self.samples, dtype=np.float64)))

    @property
    def bias(self) -> np.ndarray:
        """(P,) jackknife bias estimate, sum over strata of (n_h - 1) (mean leave-one-out - point)."""
        b = np.zeros(np.shape(self.point))
        for idx in self._groups():
            if len(idx) > 1:
                b = b + (len(idx) - 1) * (np.nanmean(self.samples[idx], axis=0) - self.point)
        return b

    @property
    def ci(self) -> np.ndarray:
        h = self._z() * self.se
        return np.stack([self.point - h, self.point + h], axis=1)

    @property
    def order_freq(self) -> np.ndarray:
        """(P, P): entry [a, b] = F((score_a - score_b) / se of the difference); 1/2 where both agree."""
        d = self.samples[:, :, None] - self.samples[:, None, :]              # (n, P, P) leave-one-out diffs
        se = np.sqrt(self._var(d))
        diff = self.point[:, None] - self.point[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(se > 0, diff / se, np.where(diff > 0, np.inf, np.where(diff < 0, -np.inf, 0.0)))
        return self._cdf(z)

    def within_noise(self, level: float = NOISE_LEVEL) -> list[tuple[str, str, float]]:
        return within_noise(self, level)

    def to_dict(self) -> dict:
        ci = self.ci
        return {"method": self.method, "names": list(self.names), "point": self.point.tolist(),
                "ci_low": ci[:, 0].tolist(), "ci_high": ci[:, 1].tolist(), "se": self.se.tolist(),
                "bias": self.bias.tolist(), "level": self.level, "unit": self.unit, "n_units": self.n_units,
                "df": self.df, "strata": None if self.strata is None else list(self.strata),
                "order_freq": np.round(self.order_freq, 4).tolist(),
                "within_noise": [list(p) for p in self.within_noise()]}


def route_df(n_units: int, strata=None) -> int:
    """Degrees of freedom of a (stratified) jackknife over routes: units minus strata."""
    return int(n_units) - (1 if strata is None else len(set(np.asarray(strata).tolist())))


def pairwise(boot: Bootstrap) -> dict:
    """{A: {B: P(A > B)}} over the resamples (ties count one half, so P(A>B) + P(B>A) = 1 exactly when
    no score is NaN; a NaN never compares greater, so the sum may fall below 1)."""
    f = boot.order_freq
    return {a: {b: round(float(f[i, j]), 4) for j, b in enumerate(boot.names) if j != i}
            for i, a in enumerate(boot.names)}


def kendall_tau(a: Sequence[float], b: Sequence[float]) -> float:
    """Kendall's tau-b of two score vectors (scipy.stats.kendalltau); NaN if either is constant."""
    from scipy.stats import kendalltau

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return float("nan")
    return float(kendalltau(a, b).statistic)


def plot_scores(boots: dict, path, title: str | None = None, reference: dict | None = None,
                reference_label: str = "paper"):
    """Scores with their intervals, one panel per entry of ``boots`` ({panel title: Bootstrap}); returns the
    path as a string (for a file object, the object).

    Args:
        boots: {panel title: Bootstrap or Jackknife}; each panel's legend names its method (``interval_method``).
        path: PNG path (written atomically), or a binary file object the PNG is written into.
        title: the figure's title; default "M-SOG with 95 % intervals: <method>" (the first panel's method).
        reference: optional {panel title: (P,) values} drawn on a second y axis (other scale).
        reference_label: legend label of the reference values.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = list(boots.items())
    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 4.8), squeeze=False)
    for ax, (name, b) in zip(axes[0], panels):
        x = np.arange(len(b.names))
        ci = b.ci
        # the interval is drawn from its own ends, not as error bars around the point: a percentile interval
        # need not contain the point (bootstrap bias, see Bootstrap.bias)
        h0 = ax.errorbar(x, ci.mean(axis=1), yerr=(ci[:, 1] - ci[:, 0]) / 2.0, fmt="none", ecolor="tab:blue",
                         capsize=4, label=f"{int(b.level * 100)} % interval: {interval_method(b)}")
        (h1,) = ax.plot(x, b.point, "o", color="tab:blue", label="M-SOG of the full sample")
        ax.set_xticks(x)
        ax.set_xticklabels(b.names, rotation=35, ha="right")
        ax.set_xlabel("placement")
        ax.set_ylabel("M-SOG [nats per covered voxel] (higher is better)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        handles = [h1, h0]
        if reference and name in reference:
            ax2 = ax.twinx()
            (h2,) = ax2.plot(x, np.asarray(reference[name], dtype=np.float64), "s", color="tab:red", alpha=0.7,
                             label=reference_label)
            ax2.set_ylabel(reference_label, color="tab:red")
            handles.append(h2)
        ax.legend(handles=handles, loc="best", fontsize=7, framealpha=0.85)
    if title is None:
        first = panels[0][1]
        title = f"M-SOG with {int(first.level * 100)} % intervals: {interval_method(first)}"
    fig.suptitle(title)
    fig.tight_layout()
    if hasattr(path, "write"):
        fig.savefig(path, format="png", dpi=120)
    else:
        from place3d_kernels.atomic import atomic_savefig

        atomic_savefig(fig, path, dpi=120)
    plt.close(fig)
    return path if hasattr(path, "write") else str(path)
