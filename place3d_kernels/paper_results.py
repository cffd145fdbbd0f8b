"""The Place3D paper's own numbers for its eight placements (Li et al., NeurIPS 2024).

Placements in the order of the paper's Table 1: the seven heuristic baselines, then "Ours" (the
placement optimised for the task: ``ours-seg`` for segmentation, ``ours-det`` for detection).

Sources (LaTeX source of the paper, ``../shared/paper``):
- ``PAPER_MSOG``: Table 1 (``tab:m_sog``, "Optimized M-SOG Metrics", main text Sec. 4), values x 1e-6.
- ``SEG_MIOU``: appendix Table ``tab:supp_robo_seg`` ("Benchmark results of LiDAR semantic segmentation
  under clean and adverse conditions"), clean mIoU (%) of MinkUNet, SPVCNN, PolarNet, Cylinder3D.
- ``DET_CAR_AP``: appendix Table ``tab:supp_robo_det`` ("Benchmark results of 3D object detection ..."),
  clean Car mAP (%) of PointPillars, CenterPoint, BEVFusion-L, FSTR.
The main-text Tables 2 and 3 (``tab:robo3d_seg``, ``tab:robo3d_det``) repeat three of the four models;
they agree with the appendix except CenterPoint on Trapezoid (56.4 in Table 3, 55.4 in the appendix);
the appendix value is used here because it comes with the full four-model table.
The downstream reference of a placement is the mean over the four models (clean condition).
"""

from __future__ import annotations

__all__ = ["PLACEMENTS", "OURS", "PAPER_MSOG", "SEG_MODELS", "SEG_MIOU", "DET_MODELS", "DET_CAR_AP", "downstream",
           "paper_msog"]

#: The eight placements of the paper's Table 1; "ours" is task-specific (see ``OURS``).
PLACEMENTS = ("center", "line", "pyramid", "square", "trapezoid", "line-roll", "pyramid-roll", "ours")
#: Which shipped placement "ours" is per task.
OURS = {"seg": "ours-seg", "det": "ours-det"}

#: Table 1 (tab:m_sog), x 1e-6; higher is better. Only the order is comparable with this package.
PAPER_MSOG = {
    "det": (-1.26, -1.65, -1.34, -1.54, -1.52, -1.41, -1.35, -1.18),
    "seg": (-1.58, -2.62, -2.56, -2.35, -2.89, -3.13, -1.63, -1.29),
}

SEG_MODELS = ("MinkUNet", "SPVCNN", "PolarNet", "Cylinder3D")
#: tab:supp_robo_seg, clean mIoU (%), per placement: (MinkUNet, SPVCNN, PolarNet, Cylinder3D).
SEG_MIOU = {
    "center": (65.7, 67.1, 71.0, 72.7),
    "line": (59.7, 59.3, 67.7, 68.9),
    "pyramid": (62.7, 67.6, 67.7, 68.4),
    "square": (60.7, 63.4, 69.3, 69.9),
    "trapezoid": (59.0, 61.0, 66.8, 68.5),
    "line-roll": (58.5, 60.6, 67.2, 69.8),
    "pyramid-roll": (62.2, 67.9, 70.9, 69.3),
    "ours": (66.5, 68.3, 76.7, 73.0),
}

DET_MODELS = ("PointPillars", "CenterPoint", "BEVFusion-L", "FSTR")
#: tab:supp_robo_det, clean Car mAP (%), per placement: (PointPillars, CenterPoint, BEVFusion-L, FSTR).
DET_CAR_AP = {
    "center": (46.5, 55.8, 52.5, 55.3),
    "line": (43.4, 54.0, 49.3, 51.9),
    "pyramid": (46.1, 55.9, 51.0, 55.7),
    "square": (43.8, 54.0, 49.2, 52.8),
    "trapezoid": (43.5, 55.4, 50.2, 54.6),
    "line-roll": (44.6, 55.2, 50.8, 53.5),
    "pyramid-roll": (46.1, 56.2, 50.7, 55.5),
    "ours": (46.8, 57.1, 53.0, 56.6),
}


def paper_msog(task: str) -> tuple:
    """Table 1 M-SOG (x 1e-6) of the eight placements for 'seg' or 'det'."""
    if task not in PAPER_MSOG:
        raise ValueError(f"task must be 'seg' or 'det', got {task!r}")
    return PAPER_MSOG[task]


def downstream(task: str) -> tuple:
    """Mean over the paper's four models of clean mIoU ('seg') or clean car mAP ('det'), in %."""
    table = {"seg": SEG_MIOU, "det": DET_CAR_AP}.get(task)
    if table is None:
        raise ValueError(f"task must be 'seg' or 'det', got {task!r}")
    return tuple(sum(table[p]) / len(table[p]) for p in PLACEMENTS)
