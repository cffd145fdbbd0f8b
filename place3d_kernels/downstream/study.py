"""The downstream study: rigs x scenes -> datasets -> trained models (several seeds) -> mIoU table with
intervals, M-SOG of the same rigs on the pooled P-SOG of the same training drives, Kendall tau between the
two with an interval, a plot, ``results.json``.

Steps (``run_study``):

1. Datasets (``dataset.build_datasets``): every (rig, drive) sequence, drive by drive (in worker processes
   with ``workers``); after a training drive's sequences, its P-SOG record (``pooled.drive_record``:
   collection LiDAR, cached on disk by its inputs) is built from the scene still in memory.
2. M-SOG of every rig on the pooled P-SOG of the training drives (the paper pools its training scenes,
   Sec. 4), for each normalisation (``metrics.NORMALISATIONS``).
3. Cells, one per (rig, model, seed): train for ``steps`` steps on the training drives, evaluate on the
   test drives (same towns, other routes) and the held-out drives (other towns) into one confusion matrix
   per drive. A cell is written as ``cells/<rig>/<model>-s<seed>-<hash>.npz`` with its spec in
   ``<same>.json`` (a manifest, written last); a rerun skips cells whose manifest matches (resume) and
   computes the others (new seeds, new rigs, other settings: a new hash).
4. The table, from the cell files: per model and split, each rig's mean mIoU over seeds with a bootstrap
   interval over seeds and test drives, on the classes every rig's test set holds; Kendall tau of each
   M-SOG normalisation against it with a bootstrap interval; the plot.
5. The detection proxy, from the same cells (no other training): the evaluation also counts, per object
   (instance) of ``OBJECT_CLASSES`` in each test frame, its points and those predicted as its class; the
   table gets each rig's object recall with an interval and Kendall tau against M-SOG beside mIoU's
   (``metrics.detection_counts``; what it measures: docs/downstream.md).

Outputs in ``output``: ``datasets/`` (unless ``data`` points elsewhere), ``cells/``, ``results.json``,
``table.csv``, ``msog_vs_miou.png``.
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from place3d_kernels.downstream.dataset import Rig, Splits, build_datasets, read_frames, route_overlap
from place3d_kernels.downstream import metrics as dm

__all__ = ["StudyConfig", "run_study", "summarise", "plot_results", "SPLITS", "OBJECT_CLASSES"]

SPLITS = ("test", "heldout")

#: classes whose objects the detection proxy counts: Place3D "vehicle" (cars, vans, trucks, buses; the
#: paper's detection class is the car) and "pedestrian"
OBJECT_CLASSES = ("vehicle", "pedestrian")


@dataclass(frozen=True)
class StudyConfig:
    """Everything a study depends on (see ``command`` for the options that set it).

    ``model_options``: ModelConfig fields other than ``name`` (e.g. smaller grids); ``train_options``:
    TrainConfig fields other than ``steps``.
    """

    rigs: tuple
    splits: Splits
    lidar: str = "place3d_16ch"
    models: tuple = ("bev",)
    seeds: tuple = (0, 1, 2)
    steps: int = 400
    model_options: dict = field(default_factory=dict)
    train_options: dict = field(default_factory=dict)
    normalisations: tuple = ("paper", "evidence", "uncertain")
    occlusion: str = "sog"
    voxel_size: float | None = None
    frames_per_subset: int | None = None
    resamples: int = 1000
    min_points: int = 1

    def model_config(self, name: str):
        from place3d_kernels.downstream.model import ModelConfig

        return ModelConfig(name=name, **self.model_options)

    def train_config(self):
        from place3d_kernels.downstream.train import TrainConfig

        return TrainConfig(steps=int(self.steps), **self.train_options)

    def load_rigs(self) -> list[Rig]:
        rigs = [Rig.load(r, self.lidar) for r in self.rigs]
        names = [r.name for r in rigs]
        if len(set(names)) != len(names):
            raise ValueError(f"rig names must be distinct, got {names}")
        return rigs


def _cell_spec(cfg: StudyConfig, rig: Rig, model: str, seed: int) -> dict:
    return {"rig": rig.to_dict(), "splits": cfg.splits.to_dict(), "model": cfg.model_config(model).to_dict(),
            "train": cfg.train_config().to_dict(), "seed": int(seed)}


def _cell_path(out: Path, spec: dict) -> Path:
    from place3d_kernels.manifest import spec_hash

    return out / "cells" / spec["rig"]["name"] / f"{spec['model']['name']}-s{spec['seed']}-{spec_hash(spec)[:10]}.npz"


def _run_cell(spec: dict, banks: dict, device, progress: bool) -> dict:
    from place3d_kernels.downstream.model import ModelConfig
    from place3d_kernels.downstream.train import TrainConfig, evaluate, train_model

    mc = ModelConfig.from_dict(spec["model"])
    tc = TrainConfig(**spec["train"])
    model, info = train_model(banks["train"], mc, tc, spec["seed"], device, progress,
                              desc=f"{spec['rig']['name']} {mc.name} s{spec['seed']}")
    t0 = time.perf_counter()
    confs, objects = {}, {}
    for s in SPLITS:
        if banks.get(s):
            confs[s], tables = evaluate(model, banks[s], mc.n_classes, tc.eval_batch, tc.amp, _object_ids())
            # one table for the split: the drive index first
            objects[s] = np.concatenate([np.c_[np.full(len(t), d, np.int64), t] for d, t in enumerate(tables)])
    return {"confs": confs, "objects": objects, "losses": np.asarray(info["losses"], np.float32),
            "train_seconds": info["seconds"], "eval_seconds": time.perf_counter() - t0,
            "parameters": info["parameters"]}


def _object_ids() -> tuple:
    from place3d_kernels.classes import CLASS_ID

    return tuple(CLASS_ID[c] for c in OBJECT_CLASSES)


def _banks(root, rig: Rig, splits: Splits, mc, device) -> dict:
    from place3d_kernels.downstream.train import FrameBank

    train = [f[:2] for d in read_frames(root, rig, splits.drives("train")) for f in d]
    out = {"train": FrameBank(train, mc, device)}
    for s in SPLITS:
        out[s] = [FrameBank(fr, mc, device) for fr in read_frames(root, rig, splits.drives(s), instances=True)]
    return out


def _cell_done(path: Path, spec: dict) -> bool:
    """A cell with a matching manifest and its object tables (cells written before the detection proxy
    have none: they are trained again, which gives the same confusion matrices on the CPU)."""
    from place3d_kernels.manifest import verify_manifest

    if not (path.exists() and verify_manifest(path.with_suffix(".json"), spec, "downstream cell")):
        return False
    with np.load(path) as z:
        return all(f"objects_{s}" in z.files for s in SPLITS if f"conf_{s}" in z.files)


def _msog(cfg: StudyConfig, rigs, pooled, backend) -> dict:
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch

    psog = pooled.psog()
    out = {}
    for n in cfg.normalisations:
        out[n] = [float(msog_batch(psog, LidarModel.load(r.lidar), r.pose_array[None], occlusion=cfg.occlusion,
                                   task="seg", backend=backend, normalisation=n)[0]) for r in rigs]
    return out


def run_study(cfg: StudyConfig, output, backend=None, device=None, progress: bool = False,
              overwrite: bool = False, data=None, workers: int = 0, executor=None) -> dict:
    """Run (or resume) the study; returns the results dict also written to ``results.json``
    (``workers`` or ``executor``: where the dataset tasks run, see ``dataset.build_datasets``)."""
    from place3d_kernels.downstream.train import resolve_device
    from place3d_kernels.manifest import provenance, write_manifest
    from place3d_kernels.pooled import PooledPSOG, PoolSettings, backend_name
    from place3d_kernels.sog import cache_dir

    t_start = time.perf_counter()
    out = Path(output)
    root = Path(data) if data else out / "datasets"
    rigs = cfg.load_rigs()
    dev = resolve_device(device)
    backend = backend_name(backend)
    settings = PoolSettings(cfg.voxel_size, frames_per_subset=cfg.frames_per_subset, backend=backend,
                            cache=str(cache_dir()))
    t0 = time.perf_counter()
    ds, records = build_datasets(root, rigs, cfg.splits, backend, overwrite, progress, settings, workers, executor)
    timing = {"datasets_wall_seconds": time.perf_counter() - t0, "dataset_seconds": ds["seconds"],
              "psog_seconds": ds["psog_seconds"]}
    pooled = PooledPSOG(settings.grid, records)
    t0 = time.perf_counter()
    msog = _msog(cfg, rigs, pooled, backend)
    timing["msog_seconds"] = time.perf_counter() - t0

    cells, ran, skipped = {}, 0, 0
    t0 = time.perf_counter()
    for rig in rigs:
        banks = None
        for model in cfg.models:
            for seed in cfg.seeds:
                spec = _cell_spec(cfg, rig, model, seed)
                path = _cell_path(out, spec)
                meta = path.with_suffix(".json")
                if not overwrite and _cell_done(path, spec):
                    skipped += 1
                else:
                    if banks is None:
                        banks = _banks(root, rig, cfg.splits, cfg.model_config(model), dev)
                    res = _run_cell(spec, banks, dev, progress)
                    path.parent.mkdir(parents=True, exist_ok=True)
                    arrays = {f"conf_{s}": c for s, c in res["confs"].items()}
                    arrays.update({f"objects_{s}": t for s, t in res["objects"].items()})
                    tmp = path.with_name(path.stem + ".tmp.npz")
                    np.savez_compressed(tmp, losses=res["losses"], **arrays)
                    os.replace(tmp, path)
                    write_manifest(meta, spec)       # last: a cell with a manifest is complete
                    info = {k: res[k] for k in ("train_seconds", "eval_seconds", "parameters")}
                    info["kept_train_share"] = banks["train"].kept
                    (path.with_suffix(".info.json")).write_text(json.dumps(info, indent=2))
                    ran += 1
                cells[(rig.name, model, seed)] = path
        del banks
    timing["cells_seconds"] = time.perf_counter() - t0
    res = summarise(cfg, rigs, cells, msog)
    res.update(settings={"config": _config_dict(cfg), "backend": backend, "device": str(dev),
                         "voxel_size": settings.grid.voxel_size},        # the M-SOG grid, the default resolved
               datasets={**ds, "root": str(root),
                         "executor": getattr(executor, "kind", "process" if workers else "local"),
                         "route_overlap_10m": {s: route_overlap(root, rigs[0], cfg.splits.drives("train"),
                                                                cfg.splits.drives(s)) for s in SPLITS
                                               if cfg.splits.drives(s)}},
               cells_run=ran, cells_skipped=skipped, pooled_drives=pooled.labels, pooled_subsets=pooled.n_subsets,
               timing={**timing, "total_seconds": time.perf_counter() - t_start}, machine=_machine(dev, backend),
               provenance=provenance())
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(res, indent=2, default=_jsonable))
    _write_csv(out / "table.csv", res)
    res["plot"] = str(plot_results(res, out / "msog_vs_miou.png"))
    return res


def summarise(cfg: StudyConfig, rigs, cells: dict, msog: dict) -> dict:
    """Table and taus from the cell files (``cells``: {(rig, model, seed): npz path})."""
    from place3d_kernels.classes import CLASSES

    table = {}
    for model in cfg.models:
        table[model] = {}
        for split in SPLITS:
            key = f"conf_{split}"
            loaded = [[np.load(cells[(r.name, model, s)]) for s in cfg.seeds] for r in rigs]
            if key not in loaded[0][0]:
                continue
            confs = np.stack([np.stack([z[key] for z in row]) for row in loaded])     # (R, S, D, C, C)
            classes = dm.present_classes(confs, cfg.min_points)
            boot = dm.bootstrap_miou(confs, classes, cfg.resamples)
            iou = np.nan_to_num(dm.per_class_iou(confs.sum(axis=2)), nan=0.0).mean(axis=1)   # (R, C)
            rows = [{"rig": r.name, "miou": float(boot["miou"][i]), "lo": float(boot["lo"][i]),
                     "hi": float(boot["hi"][i]), "per_seed": [float(v) for v in boot["per_seed"][i]],
                     "seeds": list(cfg.seeds),
                     "class_iou": {CLASSES[c]: float(iou[i, c]) for c in classes},
                     "msog": {n: msog[n][i] for n in msog}} for i, r in enumerate(rigs)]
            taus = {n: dm.bootstrap_tau(msog[n], confs, classes, cfg.resamples) for n in msog}
            table[model][split] = {"classes": [CLASSES[c] for c in classes], "rows": rows, "tau": taus,
                                   "drives": int(confs.shape[2])}
            okey = f"objects_{split}"
            if all(okey in z.files for row in loaded for z in row):
                tables = [[z[okey] for z in row] for row in loaded]
                table[model][split]["objects"] = _object_summary(cfg, rigs, tables, int(confs.shape[2]), msog)
            for row in loaded:
                for z in row:
                    z.close()
    return {"table": table}


def _object_summary(cfg: StudyConfig, rigs, tables, n_drives: int, msog: dict) -> dict:
    """Per object class: each rig's recall (mean over seeds, interval), the share of objects its points
    reach (``seen``), and Kendall tau of each M-SOG normalisation against the recall."""
    from place3d_kernels.classes import CLASS_ID

    out = {}
    for name in OBJECT_CLASSES:
        c = dm.detection_counts(tables, n_drives, CLASS_ID[name])
        total = int(c["objects"].sum())
        boot = dm.bootstrap_recall(c["found"], c["objects"], cfg.resamples)
        rows = [{"rig": r.name, "recall": float(boot["recall"][i]), "lo": float(boot["lo"][i]),
                 "hi": float(boot["hi"][i]), "per_seed": [float(v) for v in boot["per_seed"][i]],
                 "seen": float(c["seen"][i].sum() / total) if total else float("nan")}
                for i, r in enumerate(rigs)]
        taus = {n: dm.bootstrap_recall_tau(msog[n], c["found"], c["objects"], cfg.resamples) for n in msog}
        out[name] = {"objects": total, "objects_per_drive": c["objects"].tolist(), "rows": rows, "tau": taus,
                     "thresholds": {"object_min_points": dm.OBJECT_MIN_POINTS,
                                    "detect_min_points": dm.DETECT_MIN_POINTS,
                                    "detect_min_share": dm.DETECT_MIN_SHARE}}
    return out


def _config_dict(cfg: StudyConfig) -> dict:
    return {"rigs": list(cfg.rigs), "splits": cfg.splits.to_dict(), "lidar": cfg.lidar, "models": list(cfg.models),
            "seeds": list(cfg.seeds), "steps": cfg.steps, "model": cfg.model_config(cfg.models[0]).to_dict(),
            "train": cfg.train_config().to_dict(), "normalisations": list(cfg.normalisations),
            "occlusion": cfg.occlusion, "voxel_size": cfg.voxel_size, "frames_per_subset": cfg.frames_per_subset,
            "resamples": cfg.resamples, "min_points": cfg.min_points}


def _machine(dev, backend) -> dict:
    import platform

    import torch

    info = {"node": platform.node(), "platform": platform.platform(), "cpu_count": os.cpu_count(),
            "python": platform.python_version(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "device": str(dev), "backend": backend}
    if dev.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(dev)
    return info


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _write_csv(path: Path, res: dict) -> None:
    """One row per (model, split, rig): mIoU, its interval and seeds, M-SOG, then per object class the
    recall of the detection proxy, its interval and the share of objects the rig's points reach."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        norms = None
        for model, splits in res["table"].items():
            for split, t in splits.items():
                objects = t.get("objects", {})
                for i, r in enumerate(t["rows"]):
                    if norms is None:
                        norms = list(r["msog"])
                        w.writerow(["model", "split", "rig", "miou", "lo", "hi", "per_seed"] + [f"msog_{n}" for n in norms]
                                   + [f"{c}_{k}" for c in OBJECT_CLASSES for k in ("recall", "lo", "hi", "seen")])
                    obj = []
                    for c in OBJECT_CLASSES:
                        o = objects[c]["rows"][i] if c in objects else None
                        obj += ["" if o is None else f"{o[k]:.4f}" for k in ("recall", "lo", "hi", "seen")]
                    w.writerow([model, split, r["rig"], f"{r['miou']:.4f}", f"{r['lo']:.4f}", f"{r['hi']:.4f}",
                                " ".join(f"{v:.4f}" for v in r["per_seed"])] + [f"{r['msog'][n]:.6f}" for n in norms]
                               + obj)


def plot_results(res: dict, path) -> Path:
    """M-SOG (paper normalisation, else the first) against mIoU with its interval, one panel per
    (model, split), tau in each title; a second row against the vehicle recall of the detection proxy
    where the table has it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(m, s, t) for m, sp in res["table"].items() for s, t in sp.items()]
    recall = [(m, s, t["objects"][OBJECT_CLASSES[0]]) for m, s, t in panels if "objects" in t]
    n_rows = 2 if recall else 1
    fig, axes = plt.subplots(n_rows, max(len(panels), 1), figsize=(5.2 * max(len(panels), 1), 4.4 * n_rows),
                             squeeze=False)
    for ax, (model, split, t) in zip(axes[0], panels):
        _panel(ax, t["rows"], t["tau"], "miou", [r["msog"] for r in t["rows"]], f"{model}, {split}",
               "mIoU (%), mean over seeds, 95 % interval")
    for ax, (model, split, o) in zip(axes[-1] if recall else [], recall):
        _panel(ax, o["rows"], o["tau"], "recall", [r["msog"] for r in res["table"][model][split]["rows"]],
               f"{model}, {split}, {OBJECT_CLASSES[0]}s", f"{OBJECT_CLASSES[0]} recall (%), proxy, 95 % interval")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _panel(ax, rows, taus, key: str, msog, what: str, ylabel: str) -> None:
    norm = "paper" if "paper" in taus else next(iter(taus))
    x = np.array([m[norm] for m in msog])
    y = np.array([r[key] for r in rows]) * 100
    lo = np.array([r["lo"] for r in rows]) * 100
    hi = np.array([r["hi"] for r in rows]) * 100
    ax.errorbar(x, y, yerr=[np.maximum(y - lo, 0), np.maximum(hi - y, 0)], fmt="o", capsize=3)
    for xi, yi, r in zip(x, y, rows):
        ax.annotate(r["rig"], (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=8)
    tau = taus[norm]
    ax.set_title(f"{what}: tau {tau['tau']:+.2f} [{tau['lo']:+.2f}, {tau['hi']:+.2f}]", fontsize=10)
    ax.set_xlabel(f"M-SOG ({norm} normalisation; higher is better)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
