"""Segmentation scores: confusion matrix -> per-class IoU -> mIoU, and bootstrap intervals over training
seeds and test drives (NumPy only).

Conventions: a confusion matrix ``conf[g, p]`` counts points of ground-truth class ``g`` predicted as
``p``; class 0 ("unlabeled") is never scored. IoU_c = TP / (TP + FP + FN) (Everingham et al., PASCAL VOC;
the SemanticKITTI benchmark's definition). mIoU is the mean over an explicit class list, so every rig of a
study is scored on the same classes (``present_classes`` of the test sets).

Detection proxy (``detection_counts``, ``bootstrap_recall``): per-object recall from the segmentation
models' point predictions, with no extra training. An object is one instance (one actor or parked car, by
the instance ids of the dataset) in one test frame; the ground truth of a (drive, frame) is every object of
the class that at least one rig of the study hits with ``OBJECT_MIN_POINTS`` points inside the ROI (one
list for all rigs, so their recalls share a denominator). A rig's model finds an object when at least
``DETECT_MIN_POINTS`` of the object's points in that rig's cloud, and at least ``DETECT_MIN_SHARE`` of them,
are predicted as its class; an object the rig hits with fewer points is missed. Recall = found / objects.
This is not average precision: there are no boxes, no scores and no false positives, and two objects
side by side predicted as one blob both count as found.

Intervals: the statistic of a rig is the mean over its training seeds of each seed's mIoU on all its test
drives pooled (confusion matrices summed). The bootstrap resamples seeds (per rig) and test drives (the
same drive draw for every rig: the rigs drive the same routes, so their scores are paired) with
replacement; the interval is the percentile interval of the resampled statistic.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["confusion_matrix", "per_class_iou", "miou", "present_classes", "seed_mious", "bootstrap_miou",
           "kendall_tau", "bootstrap_tau", "OBJECT_MIN_POINTS", "DETECT_MIN_POINTS", "DETECT_MIN_SHARE",
           "detection_counts", "bootstrap_recall", "bootstrap_recall_tau"]

#: an object (one instance in one frame) is in the ground truth when some rig of the study puts at least this
#: many of its points inside the ROI
OBJECT_MIN_POINTS = 5
#: a rig's model finds an object when at least this many of its points are predicted as its class ...
DETECT_MIN_POINTS = 5
#: ... and at least this share of them
DETECT_MIN_SHARE = 0.5


def confusion_matrix(gt, pred, n_classes: int, ignore: int | None = 0) -> np.ndarray:
    """(C, C) int64 counts ``conf[g, p]``; points with ground truth ``ignore`` are left out."""
    gt = np.asarray(gt, dtype=np.int64).reshape(-1)
    pred = np.asarray(pred, dtype=np.int64).reshape(-1)
    if gt.shape != pred.shape:
        raise ValueError(f"one prediction per point: {gt.shape} labels, {pred.shape} predictions")
    keep = np.ones(gt.shape, bool) if ignore is None else gt != ignore
    for name, a in (("labels", gt), ("predictions", pred)):
        if a.size and (a.min() < 0 or a.max() >= n_classes):
            raise ValueError(f"{name} must lie in [0, {n_classes}), got {a.min()}..{a.max()}")
    idx = gt[keep] * n_classes + pred[keep]
    return np.bincount(idx, minlength=n_classes * n_classes).reshape(n_classes, n_classes).astype(np.int64)


def per_class_iou(conf) -> np.ndarray:
    """(..., C) IoU per class of (..., C, C) confusion matrices; NaN where a class has no ground-truth point
    and no prediction (TP + FP + FN = 0)."""
    conf = np.asarray(conf, dtype=np.float64)
    tp = np.diagonal(conf, axis1=-2, axis2=-1)
    fn = conf.sum(axis=-1) - tp
    fp = conf.sum(axis=-2) - tp
    den = tp + fp + fn
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, tp / np.where(den > 0, den, 1.0), np.nan)


def miou(conf, classes) -> np.ndarray:
    """Mean IoU over ``classes`` of (..., C, C) confusion matrices (a class no one saw or predicted counts
    as IoU 0 here: it is in the list because the test set has it)."""
    classes = np.asarray(list(classes), dtype=np.int64)
    if classes.size == 0:
        raise ValueError("mIoU needs at least one class")
    iou = np.nan_to_num(per_class_iou(conf)[..., classes], nan=0.0)
    return iou.mean(axis=-1)


def present_classes(conf, min_points: int = 1, ignore=(0,)) -> list[int]:
    """Classes with at least ``min_points`` ground-truth points: in a (C, C) matrix, or, for (R, ..., C, C)
    matrices (rigs first), in every rig's matrices summed over its other axes (the classes every rig's test
    set holds, so all rigs are scored on one list)."""
    conf = np.asarray(conf)
    C = conf.shape[-1]
    if conf.ndim == 2:
        gt = conf.sum(axis=-1)
    else:
        gt = conf.reshape(conf.shape[0], -1, C, C).sum(axis=(1, 3)).min(axis=0)
    return [c for c in range(C) if c not in ignore and gt[c] >= min_points]


def seed_mious(confs, classes) -> np.ndarray:
    """(S,) mIoU per seed of (S, D, C, C) confusion matrices (drives summed)."""
    return miou(np.asarray(confs).sum(axis=1), classes)


def _draws(rng, n: int, size: int, resamples: int) -> np.ndarray:
    return rng.integers(0, n, size=(resamples, size))


def _resampled_stat(confs, classes, rng, resamples: int) -> np.ndarray:
    """(B, R) resampled statistic for (R, S, D, C, C) confusion matrices."""
    confs = np.asarray(confs, dtype=np.float64)
    R, S, D = confs.shape[:3]
    out = np.empty((resamples, R))
    drive_draws = _draws(rng, D, D, resamples)
    seed_draws = rng.integers(0, S, size=(resamples, R, S))
    for b in range(resamples):
        m = np.bincount(drive_draws[b], minlength=D).astype(np.float64)
        pooled = np.einsum("rsdgp,d->rsgp", confs, m)                              # (R, S, C, C)
        per_seed = miou(pooled, classes)                                           # (R, S)
        out[b] = np.take_along_axis(per_seed, seed_draws[b], axis=1).mean(axis=1)
    return out


def bootstrap_miou(confs, classes, resamples: int = 1000, seed: int = 0, level: float = 0.95) -> dict:
    """Point estimate and percentile interval of each rig's mean-over-seeds mIoU.

    Args:
        confs: (R, S, D, C, C) or (S, D, C, C) confusion matrices (rigs, seeds, test drives).
    Returns: {"miou": (R,), "lo": (R,), "hi": (R,), "per_seed": (R, S)} (rig axis dropped for 4-D input).
    """
    confs = np.asarray(confs)
    single = confs.ndim == 4
    if single:
        confs = confs[None]
    per_seed = miou(confs.sum(axis=2), classes)
    samples = _resampled_stat(confs, classes, np.random.default_rng(seed), resamples)
    a = (1 - level) / 2
    res = {"miou": per_seed.mean(axis=1), "lo": np.quantile(samples, a, axis=0),
           "hi": np.quantile(samples, 1 - a, axis=0), "per_seed": per_seed}
    return {k: v[0] for k, v in res.items()} if single else res


def kendall_tau(a, b) -> float:
    """Kendall's tau-b (scipy.stats.kendalltau); NaN if either vector is constant or not finite."""
    from scipy.stats import kendalltau

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(a) < 2 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return float("nan")
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(kendalltau(a, b).statistic)


def _tau_interval(scores, point: float, samples, level: float) -> dict:
    """{"tau": point, "lo", "hi": percentile interval of the taus of ``scores`` against each resampled
    statistic in ``samples``, "p_positive": share of them > 0}; NaN where no resample gives a finite tau."""
    taus = np.array([kendall_tau(scores, s) for s in samples])
    taus = taus[np.isfinite(taus)]
    a = (1 - level) / 2
    if taus.size == 0:
        return {"tau": point, "lo": float("nan"), "hi": float("nan"), "p_positive": float("nan")}
    return {"tau": point, "lo": float(np.quantile(taus, a)), "hi": float(np.quantile(taus, 1 - a)),
            "p_positive": float(np.mean(taus > 0))}


def bootstrap_tau(scores, confs, classes, resamples: int = 1000, seed: int = 0, level: float = 0.95) -> dict:
    """Kendall tau between ``scores`` (R,) (M-SOG of the rigs) and the rigs' mean-over-seeds mIoU, with a
    percentile interval over resampled seeds and test drives (``confs``: (R, S, D, C, C)).

    Returns: {"tau", "lo", "hi", "p_positive"} (p_positive: share of resamples with tau > 0).
    """
    confs = np.asarray(confs)
    point = kendall_tau(scores, miou(confs.sum(axis=2), classes).mean(axis=1))
    samples = _resampled_stat(confs, classes, np.random.default_rng(seed), resamples)
    return _tau_interval(scores, point, samples, level)


def detection_counts(tables, n_drives: int, cls: int, min_points: int = OBJECT_MIN_POINTS,
                     detect_points: int = DETECT_MIN_POINTS, detect_share: float = DETECT_MIN_SHARE) -> dict:
    """Objects of class ``cls`` found per rig, seed and drive (see the module docstring).

    Args:
        tables: ``tables[r][s]``: (K, 6) int arrays of rig r, seed s, one row per (drive, frame, instance)
            with a point in the ROI: drive, frame, instance id, class, points, points predicted as the class
            (``train.evaluate(objects=...)`` per drive, the drive index put first). A rig's points do not
            depend on the seed; its seeds' predictions do.
    Returns: {"found": (R, S, D) int64, "objects": (D,) int64 ground-truth objects, "seen": (R, D) int64
        objects the rig hits with ``min_points`` points or more}.
    """
    R, S = len(tables), len(tables[0])
    keyed = [[_keyed(t, cls) for t in row] for row in tables]
    truth = set()
    for row in keyed:
        truth |= {k for k, (pts, _) in row[0].items() if pts >= min_points}
    objects = np.bincount([k[0] for k in truth], minlength=n_drives).astype(np.int64)
    found = np.zeros((R, S, n_drives), np.int64)
    seen = np.zeros((R, n_drives), np.int64)
    for r, row in enumerate(keyed):
        for k in truth:
            pts = row[0].get(k, (0, 0))[0]
            seen[r, k[0]] += pts >= min_points
        for s, tab in enumerate(row):
            for k in truth:
                pts, hits = tab.get(k, (0, 0))
                found[r, s, k[0]] += hits >= detect_points and hits >= detect_share * pts
    return {"found": found, "objects": objects, "seen": seen}


def _keyed(table, cls: int) -> dict:
    t = np.asarray(table, dtype=np.int64).reshape(-1, 6)
    t = t[t[:, 3] == cls]
    return {(int(d), int(f), int(i)): (int(p), int(h)) for d, f, i, _, p, h in t}


def _resampled_recall(found, objects, rng, resamples: int) -> np.ndarray:
    """(B, R) resampled mean-over-seeds recall; drives drawn once for all rigs, seeds per rig."""
    found = np.asarray(found, dtype=np.float64)
    objects = np.asarray(objects, dtype=np.float64)
    R, S, D = found.shape
    out = np.empty((resamples, R))
    drive_draws = _draws(rng, D, D, resamples)
    seed_draws = rng.integers(0, S, size=(resamples, R, S))
    for b in range(resamples):
        m = np.bincount(drive_draws[b], minlength=D).astype(np.float64)
        den = float(objects @ m)
        per_seed = found @ m / den if den > 0 else np.full((R, S), np.nan)
        out[b] = np.take_along_axis(per_seed, seed_draws[b], axis=1).mean(axis=1)
    return out


def bootstrap_recall(found, objects, resamples: int = 1000, seed: int = 0, level: float = 0.95) -> dict:
    """Each rig's recall (found / objects over all drives), the mean over its seeds, with a percentile
    interval over resampled seeds and drives (as ``bootstrap_miou``).

    Args:
        found: (R, S, D) objects found; objects: (D,) ground-truth objects per drive.
    Returns: {"recall": (R,), "lo": (R,), "hi": (R,), "per_seed": (R, S)} (NaN where there is no object).
    """
    found = np.asarray(found, dtype=np.float64)
    total = float(np.sum(objects))
    per_seed = found.sum(axis=2) / total if total > 0 else np.full(found.shape[:2], np.nan)
    samples = _resampled_recall(found, objects, np.random.default_rng(seed), resamples)
    a = (1 - level) / 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)              # all-NaN columns: no object at all
        lo, hi = np.nanquantile(samples, a, axis=0), np.nanquantile(samples, 1 - a, axis=0)
    return {"recall": per_seed.mean(axis=1), "lo": lo, "hi": hi, "per_seed": per_seed}


def bootstrap_recall_tau(scores, found, objects, resamples: int = 1000, seed: int = 0, level: float = 0.95) -> dict:
    """Kendall tau between ``scores`` (R,) and the rigs' mean-over-seeds recall, with a percentile interval
    over the resamples of ``bootstrap_recall``. Returns {"tau", "lo", "hi", "p_positive"}."""
    found = np.asarray(found, dtype=np.float64)
    total = float(np.sum(objects))
    point = kendall_tau(scores, found.sum(axis=2).mean(axis=1) / total) if total > 0 else float("nan")
    samples = _resampled_recall(found, objects, np.random.default_rng(seed), resamples)
    return _tau_interval(scores, point, samples, level)
