"""Downstream check of M-SOG: train LiDAR segmentation models on each rig's simulated data and ask whether
M-SOG orders the rigs as their trained models' mIoU does (issue 35; the Place3D paper's central claim,
Li et al., NeurIPS 2024, Tables 1-3).

Modules, one topic each:

- ``dataset``: per rig and drive (scene x route seed), the merged multi-LiDAR semantic point clouds per
  frame in the ego frame, written as SemanticKITTI sequences; train / test routes disjoint, held-out towns;
  resumable, keyed by a manifest per sequence.
- ``model``: two LiDAR segmentation networks in plain PyTorch (no custom CUDA): a bird's-eye-view U-Net
  with a per-cell PointNet (PolarNet / PointPillars style) and a range-image U-Net (RangeNet / SalsaNext
  style), both with a point branch for per-point labels.
- ``train``: a fixed number of AdamW steps per rig and seed; evaluation into confusion matrices.
- ``metrics``: confusion matrix -> per-class IoU -> mIoU, bootstrap intervals, Kendall tau with an
  interval.
- ``study``: rigs x scenes -> datasets -> trained models -> mIoU table, M-SOG of the same rigs on the
  pooled P-SOG of the same drives, tau, plot, ``results.json``; resumable.
- ``command``: the ``place3d downstream`` subcommand (``add_parser``, ``run``).

PyTorch is an optional extra (``pip install place3d-kernels[downstream]``); only ``model`` and ``train``
import it, when a model is trained.
"""
