"""Two LiDAR semantic segmentation networks in plain PyTorch (no custom CUDA: grids are filled with
``scatter_reduce``), both "projection + 2-D U-Net + point branch":

- ``bev`` (``BEVUNet``): a bird's-eye-view grid over the ego ROI. Each point is embedded by a shared MLP
  (a simplified PointNet) and max-pooled into its BEV cell, as PolarNet (Zhang et al., CVPR 2020; one of the
  four segmentation models of the Place3D paper) and PointPillars (Lang et al., CVPR 2019) do, on a
  Cartesian grid here; a 2-D U-Net (Ronneberger et al., 2015) runs over the grid.
- ``range`` (``RangeUNet``): a spherical range image seen from one point above the ego origin (``origin_z``),
  as RangeNet++ (Milioto et al., IROS 2019) and SalsaNext (Cortinhal et al., 2020) do for one sensor. A
  merged multi-LiDAR cloud has several origins, so several points can fall into one pixel: the pixel keeps
  the max-pooled embedding of all of them (no point is dropped), instead of the nearest point's range.

Both heads predict each point's class from its grid cell's U-Net feature concatenated with the point's own
embedding (a point branch, as in SPVCNN, Tang et al., ECCV 2020), so points of one cell at different heights
(road under a car, a pole above a sidewalk) get their own labels without a 3-D grid.

Inputs are ego-frame points inside ``ModelConfig``'s ROI (``in_roi``); the caller drops the others from
training and scoring alike. Intensity is not an input: the simulator's intensity is the class's
reflectivity times the incidence cosine, which would hand the network the label.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from place3d_kernels.classes import N_CLASSES

__all__ = ["ModelConfig", "BEVUNet", "RangeUNet", "build_model", "in_roi", "MODELS"]


@dataclass(frozen=True)
class ModelConfig:
    """Network and grid settings.

    Args:
        name: "bev" or "range".
        n_classes: output classes (the Place3D classes; 0, unlabeled, is never a target).
        extent: the ROI is |x|, |y| <= extent metres (default 40: the P-SOG's ROI, ``grid.DEFAULT_GRID``).
        z_range: the ROI's height band in metres (ego frame, 0 on the ground).
        bev_cells: BEV grid cells per side (extent 40, 256 cells: 0.3125 m).
        range_shape: range image rows x columns.
        elevation_deg: the range image's elevation span seen from (0, 0, origin_z); points beyond it land
            in the first or last row.
        origin_z: height of the range image's viewpoint (metres).
        width: channels of the U-Net's first stage (doubled per stage).
        depth: U-Net stages (each halves the grid).
        point_width: channels of the point embedding.
    """

    name: str = "bev"
    n_classes: int = N_CLASSES
    extent: float = 40.0
    z_range: tuple = (-1.0, 7.0)
    bev_cells: int = 256
    range_shape: tuple = (64, 512)
    elevation_deg: tuple = (-35.0, 15.0)
    origin_z: float = 2.0
    width: int = 32
    depth: int = 4
    point_width: int = 64

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def in_roi(points, cfg: ModelConfig):
    """Boolean mask (NumPy or torch, as given) of points inside the model's ROI."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    e = cfg.extent
    return (x > -e) & (x < e) & (y > -e) & (y < e) & (z >= cfg.z_range[0]) & (z < cfg.z_range[1])


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class UNet2d(nn.Module):
    """A 2-D U-Net: ``depth`` stages of two 3x3 convolutions (BatchNorm, ReLU), 2x2 max-pool down,
    bilinear 2x up with skip concatenation; returns ``width`` channels at the input's size."""

    def __init__(self, cin: int, width: int, depth: int):
        super().__init__()
        chans = [width * 2 ** i for i in range(depth)]
        self.down = nn.ModuleList([_block(cin if i == 0 else chans[i - 1], c) for i, c in enumerate(chans)])
        self.up = nn.ModuleList([_block(chans[i] + chans[i - 1], chans[i - 1]) for i in range(depth - 1, 0, -1)])
        self.pool = nn.MaxPool2d(2)

    def forward(self, x):
        skips = []
        for i, blk in enumerate(self.down):
            x = blk(x if i == 0 else self.pool(x))
            skips.append(x)
        for blk, skip in zip(self.up, reversed(skips[:-1])):
            x = nn.functional.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = blk(torch.cat([x, skip], dim=1))
        return x


def _mlp(cin: int, cout: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, hidden, bias=False), nn.BatchNorm1d(hidden), nn.ReLU(inplace=True),
                         nn.Linear(hidden, cout, bias=False), nn.BatchNorm1d(cout), nn.ReLU(inplace=True))


class _ProjectedUNet(nn.Module):
    """Point MLP -> max-pool into a 2-D grid (plus log point count) -> U-Net -> per-point head."""

    n_point_features = 0

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        pw = cfg.point_width
        self.point_mlp = _mlp(self.n_point_features, pw, pw)
        self.unet = UNet2d(pw + 1, cfg.width, cfg.depth)
        self.head = nn.Sequential(nn.Linear(cfg.width + pw, pw, bias=False), nn.BatchNorm1d(pw),
                                  nn.ReLU(inplace=True), nn.Linear(pw, cfg.n_classes))

    def project(self, points):
        """(cell (N,) long index into the H x W grid, (H, W), point features (N, F))."""
        raise NotImplementedError

    def forward(self, points, batch, batch_size: int):
        """Per-point logits (N, n_classes) for ``points`` (N, 3) of ``batch_size`` frames (``batch``: (N,)
        frame index of each point)."""
        cell, (H, W), feats = self.project(points)
        h = self.point_mlp(feats)
        idx = batch.long() * (H * W) + cell
        n = batch_size * H * W
        grid = torch.zeros(n, h.shape[1], dtype=h.dtype, device=h.device)
        # max-pool: order independent, so the same grid whatever order the atomics run in
        grid = grid.scatter_reduce(0, idx[:, None].expand_as(h), h, reduce="amax", include_self=False)
        count = torch.zeros(n, dtype=h.dtype, device=h.device).index_add_(0, idx, torch.ones_like(idx, dtype=h.dtype))
        grid = torch.cat([grid, torch.log1p(count)[:, None]], dim=1)
        grid = grid.view(batch_size, H, W, -1).permute(0, 3, 1, 2)
        f = self.unet(grid).permute(0, 2, 3, 1).reshape(n, -1)
        return self.head(torch.cat([f[idx], h], dim=1))


class BEVUNet(_ProjectedUNet):
    """Bird's-eye-view U-Net with a per-cell PointNet (module docstring)."""

    n_point_features = 7

    def project(self, p):
        c = self.cfg
        n = c.bev_cells
        size = 2 * c.extent / n
        ix = ((p[:, 0] + c.extent) / size).floor().clamp(0, n - 1)
        iy = ((p[:, 1] + c.extent) / size).floor().clamp(0, n - 1)
        zlo, zhi = c.z_range
        # the point's offset from its cell centre (PointPillars' x_p, y_p) and its place in the ROI
        dx = (p[:, 0] + c.extent) / size - ix - 0.5
        dy = (p[:, 1] + c.extent) / size - iy - 0.5
        r = torch.linalg.vector_norm(p[:, :2], dim=1)
        feats = torch.stack([p[:, 0] / c.extent, p[:, 1] / c.extent, (p[:, 2] - zlo) / (zhi - zlo) * 2 - 1,
                             r / c.extent, dx, dy, (p[:, 2] - zlo) / (zhi - zlo)], dim=1)
        return (iy * n + ix).long(), (n, n), feats


class RangeUNet(_ProjectedUNet):
    """Range-image U-Net seen from (0, 0, origin_z) (module docstring)."""

    n_point_features = 7

    def project(self, p):
        c = self.cfg
        H, W = c.range_shape
        lo, hi = (math.radians(v) for v in c.elevation_deg)
        dz = p[:, 2] - c.origin_z
        rxy = torch.linalg.vector_norm(p[:, :2], dim=1)
        az = torch.atan2(p[:, 1], p[:, 0])
        el = torch.atan2(dz, rxy)
        col = ((az + math.pi) / (2 * math.pi) * W).floor().clamp(0, W - 1)
        row = ((hi - el) / (hi - lo) * H).floor().clamp(0, H - 1)
        rng = torch.sqrt(rxy ** 2 + dz ** 2)
        zlo, zhi = c.z_range
        feats = torch.stack([p[:, 0] / c.extent, p[:, 1] / c.extent, (p[:, 2] - zlo) / (zhi - zlo) * 2 - 1,
                             rng / c.extent, torch.cos(az), torch.sin(az), (el - lo) / (hi - lo)], dim=1)
        return (row * W + col).long(), (H, W), feats


MODELS = {"bev": BEVUNet, "range": RangeUNet}


def build_model(cfg: ModelConfig) -> nn.Module:
    if cfg.name not in MODELS:
        raise ValueError(f"unknown model {cfg.name!r}; choose one of {sorted(MODELS)}")
    return MODELS[cfg.name](cfg)


def n_parameters(model: nn.Module) -> int:
    return int(sum(np.prod(p.shape) for p in model.parameters()))
