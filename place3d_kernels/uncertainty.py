"""Uncertainty on M-SOG scores and rankings: bootstrap over drives (routes) or over subsets.

A pooled P-SOG is an estimate from a sample of drives; another sample of routes would give other voxel
probabilities and possibly another order of the placements. The bootstrap resamples the drives with
replacement (each resample: a multiplicity per drive, summing to D), rebuilds the pooled P-SOG from the
per-drive counts (``PooledPSOG.psog(multiplicity)``, sums of sparse counts, no simulation) and rescores
every placement with one batched ``msog_batch`` call. From the R resamples:

- a percentile interval per placement (Efron and Tibshirani, *An Introduction to the Bootstrap*, 1993,
  ch. 13), and a standard error;
- ``P(A > B)``: the share of resamples in which placement A outscored B (ties count one half);
- pairs whose order holds in fewer than 95 % of resamples are "within noise".

A single drive is resampled the same way over its subsets (``subset_records`` gives one record per
subset of k frames).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from place3d_kernels.pooled import PooledPSOG

__all__ = ["Bootstrap", "resample_multiplicities", "bootstrap_pooled", "bootstrap_drives",
           "bootstrap_subsets", "within_noise", "plot_scores", "NOISE_LEVEL"]

#: An order of two placements counts as settled when it holds in at least this share of resamples.
NOISE_LEVEL = 0.95


def resample_multiplicities(n: int, n_resamples: int, seed: int = 0, strata=None) -> np.ndarray:
    """(R, n) int64: how often each of n units is drawn in each resample (n draws with replacement).

    Args:
        strata: optional (n,) labels; units are then resampled within each stratum (as many draws as the
            stratum has units), so e.g. every resample keeps each town's share of routes: the towns are
            fixed by the study's design, the routes are the random sample.
    """
    if n < 1 or n_resamples < 1:
        raise ValueError(f"need n >= 1 units and n_resamples >= 1, got n={n}, n_resamples={n_resamples}")
    rng = np.random.default_rng(seed)
    if strata is None:
        return rng.multinomial(n, np.full(n, 1.0 / n), size=int(n_resamples)).astype(np.int64)
    strata = np.asarray(strata)
    if strata.shape != (n,):
        raise ValueError(f"strata must have one label per unit ({n}), got shape {strata.shape}")
    out = np.zeros((int(n_resamples), n), dtype=np.int64)
    for s in np.unique(strata):
        idx = np.flatnonzero(strata == s)
        out[:, idx] = rng.multinomial(len(idx), np.full(len(idx), 1.0 / len(idx)), size=int(n_resamples))
    return out


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


def bootstrap_pooled(pooled: PooledPSOG, score: Callable, n_resamples: int = 200, seed: int = 0,
                     progress: bool = False, strata=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Apply ``score(psog) -> (S,) array`` to the full pool and to R drive resamples.

    Args:
        strata: optional per-drive labels (e.g. the town) to resample within (``resample_multiplicities``).

    Returns:
        point (S,), samples (R, S), multiplicities (R, D).
    """
    mult = resample_multiplicities(len(pooled), n_resamples, seed, strata)
    point = np.asarray(score(pooled.psog()), dtype=np.float64)
    it = mult
    if progress:
        from tqdm import tqdm

        it = tqdm(mult, desc="bootstrap", unit="resample", leave=False)
    samples = np.stack([np.asarray(score(pooled.psog(m)), dtype=np.float64) for m in it])
    return point, samples, mult


def _placement_scorer(lidar, poses: np.ndarray, task: str, occlusion: str, backend) -> Callable:
    from place3d_kernels.metrics import msog_batch

    def score(psog):
        return msog_batch(psog, lidar, poses, occlusion=occlusion, task=task, backend=backend)

    return score


def _poses(placements) -> tuple[list, np.ndarray]:
    if isinstance(placements, dict):
        names = list(placements)
        rows = [getattr(p, "poses", p) for p in placements.values()]
    else:
        rows = [getattr(p, "poses", p) for p in placements]
        names = [getattr(p, "name", f"placement {i}") for i, p in enumerate(placements)]
    return names, np.stack([np.asarray(r, dtype=np.float64) for r in rows])


def bootstrap_drives(pooled: PooledPSOG, lidar, placements, task: str = "seg", occlusion: str = "sog",
                     n_resamples: int = 200, seed: int = 0, backend=None, level: float = 0.95,
                     progress: bool = False, strata=None) -> Bootstrap:
    """Bootstrap over drives of the M-SOG of each placement (one batched call per resample).

    Args:
        pooled: the pooled P-SOG's per-drive records.
        lidar: the rig's ``LidarModel`` (or name).
        placements: {name: Placement or (L, 6) poses} or a list of ``Placement``.
        task, occlusion, backend: as ``msog_batch``.
        n_resamples, seed: R and the resampling seed (results depend on nothing else).
        level: interval coverage.
        strata: optional per-drive labels to resample within (e.g. the town of each drive).
    """
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel

    L = LidarModel.load(lidar) if isinstance(lidar, str) else lidar
    names, poses = _poses(placements)
    scorer = _placement_scorer(L, poses, task, occlusion, get_backend(backend))
    point, samples, _ = bootstrap_pooled(pooled, scorer, n_resamples, seed, progress, strata)
    return Bootstrap(names, point, samples, level, "drives", len(pooled))


def bootstrap_subsets(drive, lidar, placements, settings=None, task: str = "seg", occlusion: str = "sog",
                      n_resamples: int = 200, seed: int = 0, level: float = 0.95) -> Bootstrap:
    """Bootstrap over the subsets (SOGs of k frames) of a single drive.

    The point estimate equals the drive's ordinary P-SOG score. Subsets of one drive overlap in space
    and follow each other in time, so they are not independent draws: this interval is narrower than
    one over routes and says how stable the estimate is within the drive, not across drives.
    """
    from place3d_kernels.pooled import PoolSettings, subset_records

    settings = settings or PoolSettings()
    pooled = PooledPSOG(settings.grid, subset_records(drive, settings))
    b = bootstrap_drives(pooled, lidar, placements, task, occlusion, n_resamples, seed, settings.backend, level)
    b.unit = "subsets"
    return b


# ====================================================================== plot
def plot_scores(boots: dict, path, title: str = "M-SOG with bootstrap intervals", reference: dict | None = None,
                reference_label: str = "paper") -> str:
    """Scores with their intervals, one panel per entry of ``boots`` ({panel title: Bootstrap}).

    Args:
        boots: {panel title: Bootstrap}.
        path: PNG path.
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
        err = np.abs(np.stack([b.point - ci[:, 0], ci[:, 1] - b.point]))
        h1 = ax.errorbar(x, b.point, yerr=err, fmt="o", color="tab:blue", capsize=4,
                         label=f"pooled M-SOG, {int(b.level * 100)} % interval ({b.n_units} {b.unit}, "
                               f"{len(b.samples)} resamples)")
        ax.set_xticks(x)
        ax.set_xticklabels(b.names, rotation=35, ha="right")
        ax.set_xlabel("placement")
        ax.set_ylabel("M-SOG [nats per covered voxel] (higher is better)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        handles = [h1]
        if reference and name in reference:
            ax2 = ax.twinx()
            (h2,) = ax2.plot(x, np.asarray(reference[name], dtype=np.float64), "s", color="tab:red", alpha=0.7,
                             label=reference_label)
            ax2.set_ylabel(reference_label, color="tab:red")
            handles.append(h2)
        ax.legend(handles=handles, loc="best", fontsize=7, framealpha=0.85)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def kendall_tau(a: Sequence[float], b: Sequence[float]) -> float:
    """Kendall's tau-b of two score vectors (scipy.stats.kendalltau); NaN if either is constant."""
    from scipy.stats import kendalltau

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return float("nan")
    return float(kendalltau(a, b).statistic)


__all__ += ["kendall_tau"]
