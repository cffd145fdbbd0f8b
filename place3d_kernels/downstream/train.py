"""Training and evaluation of one segmentation model on one rig's frames: a fixed number of AdamW steps
(the same budget for every rig, counted in steps, not time), seeded, deterministic where PyTorch allows.

Frames are packed once into device tensors (``FrameBank``: points inside the model's ROI, their labels,
offsets per frame), so a step gathers its batch on the device. Loss: cross-entropy over points with class
0 (unlabeled) ignored, classes weighted by the inverse square root of their training frequency (rare
classes such as poles and signs would otherwise never be predicted within a short budget). Schedule:
linear warm-up over 10 % of the steps, then cosine decay (``lr_factor``). Augmentation: per frame, a mirror across the ego's x axis with
probability 0.5 and a scale in [0.95, 1.05]; no rotation, since the rig's layout relative to the driving
direction is what the study compares.

Determinism: seeds for PyTorch and the batch sampler, ``torch.use_deterministic_algorithms(True,
warn_only=True)`` while training. On the CPU two runs with one seed give the same weights; on CUDA the
scatter and interpolation kernels use atomics, so runs agree to float rounding, not bit for bit.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from place3d_kernels.downstream.model import ModelConfig, build_model, in_roi

__all__ = ["TrainConfig", "FrameBank", "train_model", "train_step", "evaluate", "class_weights", "resolve_device"]


@dataclass(frozen=True)
class TrainConfig:
    """Training budget and optimiser.

    Args:
        steps: optimiser steps (the fixed budget per rig).
        batch_size: frames per step.
        lr: peak learning rate (``lr_factor``).
        weight_decay: AdamW's decoupled weight decay.
        class_weights: "sqrt-inverse" or "none".
        augment: mirror and scale per frame.
        amp: bfloat16 autocast on CUDA (ignored on the CPU).
        eval_batch: frames per evaluation forward pass.
    """

    steps: int = 400
    batch_size: int = 4
    lr: float = 3e-3
    weight_decay: float = 1e-2
    class_weights: str = "sqrt-inverse"
    augment: bool = True
    amp: bool = True
    eval_batch: int = 8

    def to_dict(self) -> dict:
        return asdict(self)


def resolve_device(device: str | None) -> torch.device:
    """'cpu', 'cuda', 'cuda:N' or None/'auto' (CUDA when available)."""
    if device in (None, "auto"):
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device}: PyTorch sees no CUDA device here (torch {torch.__version__})")
    return dev


class FrameBank:
    """Frames (points inside the ROI, labels, optionally instance ids) packed into device tensors.

    Args:
        frames: list of (N, 3) float32 points, (N,) int labels and, optionally, (N,) int instance ids.
    Attributes: points (P, 3), labels (P,), instances (P,) or None, offsets (F + 1,) on ``device``;
        ``kept``: share of the frames' labelled points inside the ROI.
    """

    def __init__(self, frames, cfg: ModelConfig, device):
        pts, labs, insts, offs, total, kept = [], [], [], [0], 0, 0
        for fr in frames:
            p, lab = fr[0], fr[1]
            m = in_roi(p, cfg)
            total += int(np.sum(lab > 0))
            kept += int(np.sum(lab[m] > 0))
            pts.append(p[m])
            labs.append(lab[m])
            if len(fr) > 2:
                insts.append(np.asarray(fr[2])[m])
            offs.append(offs[-1] + int(m.sum()))
        if insts and len(insts) != len(frames):
            raise ValueError("give instance ids for every frame of a bank or for none")
        self.points = torch.from_numpy(np.concatenate(pts).astype(np.float32)).to(device)
        self.labels = torch.from_numpy(np.concatenate(labs).astype(np.int64)).to(device)
        self.instances = torch.from_numpy(np.concatenate(insts).astype(np.int64)).to(device) if insts else None
        self.offsets = torch.tensor(offs, dtype=torch.long, device=device)
        self.n_frames = len(frames)
        self.kept = kept / total if total else float("nan")

    def _index(self, frames):
        idx, which = [], []
        for j, f in enumerate(frames):
            a, b = int(self.offsets[f]), int(self.offsets[f + 1])
            idx.append(torch.arange(a, b, device=self.points.device))
            which.append(torch.full((b - a,), j, dtype=torch.long, device=self.points.device))
        return torch.cat(idx), torch.cat(which)

    def batch(self, frames):
        """(points, labels, frame index per point) of the frames ``frames`` (a list of ints)."""
        idx, which = self._index(frames)
        return self.points[idx], self.labels[idx], which

    def batch_instances(self, frames):
        """The instance ids of ``batch(frames)``'s points."""
        if self.instances is None:
            raise ValueError("this FrameBank was made without instance ids")
        return self.instances[self._index(frames)[0]]


def class_weights(labels: torch.Tensor, n_classes: int, mode: str = "sqrt-inverse") -> torch.Tensor:
    """(C,) loss weights: 1 / sqrt(frequency), normalised to mean 1 over the classes present; 0 for class 0
    and absent classes ("none": 1 everywhere but class 0)."""
    w = torch.zeros(n_classes, dtype=torch.float32, device=labels.device)
    if mode == "none":
        w[1:] = 1.0
        return w
    if mode != "sqrt-inverse":
        raise ValueError(f"class_weights must be 'sqrt-inverse' or 'none', got {mode!r}")
    counts = torch.bincount(labels, minlength=n_classes).float()
    counts[0] = 0
    present = counts > 0
    w[present] = 1.0 / torch.sqrt(counts[present] / counts.sum())
    w[present] /= w[present].mean()
    return w


def _augment(points, batch, n_frames: int, gen: torch.Generator):
    flip = (torch.rand(n_frames, generator=gen) < 0.5).to(points.device)
    scale = (0.95 + 0.1 * torch.rand(n_frames, generator=gen)).to(points.device)
    p = points * scale[batch][:, None]
    p[:, 1] = torch.where(flip[batch], -p[:, 1], p[:, 1])
    return p


def lr_factor(step: int, steps: int, warmup: float = 0.1) -> float:
    """Learning-rate factor at ``step`` of ``steps``: linear warm-up over the first ``warmup`` share, then a
    cosine decay to 0 at the last step."""
    w = max(1, int(round(warmup * steps)))
    if step < w:
        return (step + 1) / w
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, (step - w) / max(1, steps - w))))


def _autocast(device, amp: bool):
    if amp and device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def train_step(model, opt, points, labels, batch, batch_size: int, weights, amp: bool = False) -> float:
    """One optimiser step on one batch; returns the loss before the step."""
    model.train()
    with _autocast(points.device, amp):
        logits = model(points, batch, batch_size)
    loss = torch.nn.functional.cross_entropy(logits.float(), labels, weight=weights, ignore_index=0)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


@contextlib.contextmanager
def _deterministic(device):
    if device.type == "cuda":
        # cuBLAS reads this when its handle is made; set before the first CUDA matmul of the process
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    before = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    bench = torch.backends.cudnn.benchmark
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark = False
    try:
        import warnings

        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*does not have a deterministic implementation.*")
            yield
    finally:
        torch.use_deterministic_algorithms(before[0], warn_only=before[1])
        torch.backends.cudnn.benchmark = bench


def train_model(bank: FrameBank, model_cfg: ModelConfig, cfg: TrainConfig, seed: int, device,
                progress: bool = False, desc: str = "train"):
    """A model trained for ``cfg.steps`` steps on ``bank``. Returns (model, {"losses", "seconds",
    "parameters"})."""
    device = torch.device(device)
    with _deterministic(device):
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        model = build_model(model_cfg).to(device)
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, cfg.steps))
        weights = class_weights(bank.labels, model_cfg.n_classes, cfg.class_weights)
        bs = min(cfg.batch_size, bank.n_frames)
        losses = []
        steps = range(cfg.steps)
        if progress:
            from tqdm import tqdm

            steps = tqdm(steps, desc=desc, unit="step", leave=False)
        t0 = time.perf_counter()
        for _ in steps:
            frames = torch.randperm(bank.n_frames, generator=gen)[:bs].tolist()
            p, lab, b = bank.batch(frames)
            if cfg.augment:
                p = _augment(p, b, bs, gen)
            losses.append(train_step(model, opt, p, lab, b, bs, weights, cfg.amp))
            sched.step()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        secs = time.perf_counter() - t0
    n_par = int(sum(p.numel() for p in model.parameters()))
    return model, {"losses": losses, "seconds": secs, "parameters": n_par}


@torch.no_grad()
def evaluate(model, banks, n_classes: int, batch_frames: int = 8, amp: bool = False, objects=None):
    """(D, C, C) int64 confusion matrices, one per drive (``banks``: one ``FrameBank`` per drive); class 0
    is left out of the ground truth.

    Args:
        objects: classes whose instances are counted too (the banks need instance ids). Then returns
            (the matrices, per drive a (K, 5) int64 array): one row per (frame, instance) of those classes
            with a point in the ROI: frame, instance id, class, points, points predicted as that class.
    """
    model.eval()
    out = np.zeros((len(banks), n_classes, n_classes), np.int64)
    tables = []
    for d, bank in enumerate(banks):
        conf = torch.zeros(n_classes * n_classes, dtype=torch.long, device=bank.points.device)
        rows = []
        for a in range(0, bank.n_frames, batch_frames):
            frames = list(range(a, min(a + batch_frames, bank.n_frames)))
            p, lab, b = bank.batch(frames)
            if len(p) == 0:
                continue
            with _autocast(p.device, amp):
                pred = model(p, b, len(frames)).argmax(dim=1)
            keep = lab > 0
            conf += torch.bincount(lab[keep] * n_classes + pred[keep], minlength=n_classes * n_classes)
            if objects is not None:
                rows.append(_instance_rows(bank.batch_instances(frames), lab, pred, b + a, objects))
        out[d] = conf.view(n_classes, n_classes).cpu().numpy()
        if objects is not None:
            tables.append(np.concatenate(rows) if rows else np.zeros((0, 5), np.int64))
    return (out, tables) if objects is not None else out


def _instance_rows(inst, lab, pred, frame, objects) -> np.ndarray:
    """(K, 5) rows frame, instance, class, points, points predicted as the class, for the points of
    instances (id > 0) of the classes ``objects``."""
    sel = (inst > 0) & torch.isin(lab, torch.as_tensor(list(objects), device=lab.device))
    if not bool(sel.any()):
        return np.zeros((0, 5), np.int64)
    key = frame[sel] * (1 << 16) + inst[sel]             # instance ids are 16 bits (the .label layout)
    uniq, inv = torch.unique(key, return_inverse=True)
    points = torch.bincount(inv, minlength=len(uniq))
    hits = torch.bincount(inv[pred[sel] == lab[sel]], minlength=len(uniq))
    cls = torch.zeros(len(uniq), dtype=torch.long, device=lab.device).scatter_(0, inv, lab[sel])
    return torch.stack([uniq >> 16, uniq & 0xFFFF, cls, points, hits], 1).cpu().numpy().astype(np.int64)


def steps_per_epoch(n_frames: int, batch_size: int) -> float:
    return n_frames / max(batch_size, 1) if n_frames else math.nan
