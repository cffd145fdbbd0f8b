"""``place3d study CONFIG.toml``: M-SOG (seg, det) over a grid of placements x conditions x scenes.

The config (``place3d_kernels/configs/study/example.toml``)::

    [study]
    name = "example"
    lidar = "place3d_16ch"          # the rig's LiDAR model
    occlusion = "sog"
    voxel_size = 0.2                 # optional; default grid (0.1 m) otherwise
    roi = [80, 80, 5]                # optional ROI box: 3 sizes or 6 corners, metres (or --roi)
    frames_per_subset = 4            # optional
    placements = ["center", "line", "pyramid"]     # names or TOML paths

    [[scenes]]                       # one table per scene
    name = "town"                    # or "opendrive:PATH"
    seed = 0
    frames = 40

    [[conditions]]                   # "clean" = no condition
    name = "clean"
    [[conditions]]
    name = "fog"
    severity = "moderate"            # optional; seed (default 0) and other keys are condition params

Work is split into tasks on the chosen executor: first one P-SOG per (scene, condition) that still has
unfinished cells (cached on disk by its inputs), then one task per cell (placement, condition, scene)
that scores seg and det and writes ``cells/<scene>__<condition>__<placement>__<settings>.json`` atomically
(``<settings>``: hash of ``study_settings``: LiDAR, occlusion, grid, k, collection LiDAR, bootstrap
resamples and seed). A rerun
submits only cells whose file is missing, so rerunning a finished study does no work; a rerun with other
settings is refused (``manifest.json``) unless ``--overwrite``. The table
(``study.csv``, ``study.json``) is always rebuilt from the cell files.

Uncertainty: each cell also gets a 95 % percentile interval (``ci_lo_seg``, ``ci_hi_seg``, ``ci_lo_det``,
``ci_hi_det``) from a bootstrap over the subsets of its (scene, condition) drive (``[study] resamples``,
default 200, or ``--resamples``; 0 switches it off; ``resample_seed``, default 0). Every cell of a drive
draws the same resamples (same seed, same subsets), so the cells' resampled scores are paired and
``study.json`` lists, per (scene, condition), the placement pairs whose order holds in < 95 % of them.
"""

from __future__ import annotations

import csv
import io
import json
import sys
import time
from pathlib import Path

__all__ = ["add_arguments", "run", "run_study", "load_config"]


def add_arguments(p) -> None:
    from place3d_app.executors import add_executor_arguments

    p.add_argument("config", help="study TOML (see place3d_kernels/configs/study/example.toml)")
    p.add_argument("--output", default=None, help="output folder (default: study-<name>/)")
    p.add_argument("--backend", default=None, help="backend of the tasks (default: $PLACE3D_BACKEND or auto)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    from place3d_app.commands.common import add_roi_argument

    add_roi_argument(p)                 # overrides [study] roi
    p.add_argument("--resamples", type=int, default=None,
                   help="bootstrap resamples per cell over its drive's subsets (default: [study] resamples or 200; "
                        "0: no intervals)")
    p.add_argument("--overwrite", action="store_true",
                   help="discard the cells of an earlier study in --output made with other settings, and its "
                        "table when it lists other scenes, conditions or placements")
    add_executor_arguments(p)


def load_config(path) -> dict:
    from place3d_kernels._toml import read_toml

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"study config {path} not found")
    cfg = read_toml(path)
    st = dict(cfg.get("study", {}))
    if not st.get("placements"):
        raise ValueError(f"{path}: [study] placements = [...] is required")
    if not cfg.get("scenes"):
        raise ValueError(f"{path}: at least one [[scenes]] table is required")
    st.setdefault("name", path.stem)
    st["scenes"] = cfg["scenes"]
    st["conditions"] = cfg.get("conditions") or [{"name": "clean"}]
    return st


def _safe(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(s))


def _atomic_text(path: Path, text: str) -> None:
    from place3d_kernels.atomic import atomic_write_text

    atomic_write_text(path, text)


def _psog_task(t) -> str:
    spec, resamples, *shown = t
    if shown and shown[0]:
        # in this process, with a bar of its frames (the simulation is most of a study's time); the cache it
        # writes is what load() reads next
        spec.build(cache=spec.cache if spec.cache else True, progress=True)
    spec.load()                                   # builds the cache file if it is absent
    if resamples:
        from place3d_kernels.subset_records import spec_subset_records

        spec_subset_records(spec)                 # per-subset records for the cells' bootstrap, cached too
    return spec.scene.label


def _cell_task(t) -> dict:
    """Score one placement on one (scene, condition) P-SOG, both tasks; write the cell file atomically."""
    psog_spec, placement, lidar, occlusion, backend, path, meta, boot = t
    from place3d_kernels.spec import resolve_lidar
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import Placement

    psog = psog_spec.load()
    pl = Placement.load(placement)
    L = resolve_lidar(lidar)
    row = dict(meta)
    for task in ("seg", "det"):
        row[f"msog_{task}"] = float(msog_batch(psog, L, pl.poses[None], occlusion, task, backend)[0])
    if boot["resamples"]:
        from place3d_kernels.subset_records import spec_subset_records
        from place3d_kernels.uncertainty import bootstrap_records

        recs = spec_subset_records(psog_spec)
        bs = bootstrap_records(recs, psog_spec.grid.grid(), L, {meta["placement"]: pl}, ("seg", "det"), occlusion,
                               boot["resamples"], boot["seed"], backend,
                               point={t: [row[f"msog_{t}"]] for t in ("seg", "det")})
        for task, b in bs.items():
            row[f"ci_lo_{task}"], row[f"ci_hi_{task}"] = (float(v) for v in b.ci[0])
            row[f"samples_{task}"] = b.samples[:, 0].tolist()
    _atomic_text(Path(path), json.dumps(row, indent=1))
    return row


def few_subsets(cfg: dict, k: int) -> str | None:
    """Why the study's cells get no interval over their drive's subsets (a scene too short for
    ``intervals.MIN_SUBSETS`` subsets of ``k`` frames), or None."""
    from place3d_kernels.sog import subset_groups
    from place3d_kernels.spec import SceneSpec
    from place3d_kernels.uncertainty import MIN_SUBSETS, too_few_subsets

    for sc in cfg["scenes"]:
        frames = SceneSpec.from_dict(sc).frames
        reason = too_few_subsets(len(subset_groups(list(range(frames)), int(k))))
        if reason:
            return (f"scene {sc.get('name', 'town')} seed {sc.get('seed', 0)}: {reason} ({frames} frames, k = {k}); "
                    f"give every scene at least {MIN_SUBSETS * int(k)} frames")
    return None


def study_settings(cfg: dict) -> dict:
    """The settings every cell depends on besides its own scene, condition and placement (the study
    folder's manifest; the backend is left out: the three backends agree bit for bit)."""
    from place3d_kernels.grid import DEFAULT_GRID
    from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET

    # the default's size, not None: a study made when the default was 0.2 m must not match a 0.1 m one
    voxel = cfg.get("voxel_size")
    return {"lidar": cfg.get("lidar", "place3d_16ch"), "occlusion": cfg.get("occlusion", "sog"),
            "voxel_size": DEFAULT_GRID.voxel_size if voxel is None else voxel,
            "frames_per_subset": cfg.get("frames_per_subset") or DEFAULT_FRAMES_PER_SUBSET,
            "collection_lidar": cfg.get("collection_lidar", "collection_64ch"),
            "resamples": int(cfg.get("resamples", DEFAULT_RESAMPLES)),
            "resample_seed": int(cfg.get("resample_seed", 0)),
            # only when chosen, so the cells and manifests of studies made before ROIs could be chosen still match
            **({"roi": [float(x) for x in cfg["roi"]]} if cfg.get("roi") is not None else {})}


#: Bootstrap resamples per cell unless the config or --resamples says otherwise.
DEFAULT_RESAMPLES = 200


def _check_entries(cfg: dict) -> None:
    """Every placement, scene and condition of the study loads (before any file is written)."""
    from place3d_kernels.placement import Placement
    from place3d_kernels.spec import ConditionSpec, SceneSpec, resolve_lidar

    from place3d_kernels.grid import check_inside, check_roi

    from place3d_kernels.simulate import DEFAULT_MOUNT

    grid = check_roi(cfg.get("roi"), cfg.get("voxel_size"))
    check_inside(grid, DEFAULT_MOUNT[:3], "the collection LiDAR")
    for p in cfg["placements"]:
        check_inside(grid, Placement.load(p).poses[:, :3], f"a LiDAR of {p!r}")
    resolve_lidar(cfg.get("lidar", "place3d_16ch"))
    if cfg.get("occlusion", "sog") not in ("sog", "none"):
        raise ValueError(f"study occlusion must be 'sog' or 'none', got {cfg.get('occlusion')!r}")
    for s in cfg["scenes"]:
        SceneSpec.from_dict(s).validate()
    for c in cfg["conditions"]:
        cs = ConditionSpec.from_dict(c)
        if cs is not None:
            cs.condition(None)


def run_study(config, output=None, executor=None, backend=None, progress: bool = False,
              overwrite: bool = False) -> dict:
    """Run (or finish) a study; returns {rows, executed, cells, psogs, seconds, csv, json}.

    The output folder's ``manifest.json`` records the settings the cells were computed with
    (``study_settings``); a rerun with other settings raises ``ValueError`` naming the field, unless
    ``overwrite`` (which deletes the old cells first).
    """
    import shutil

    from place3d_kernels.manifest import provenance, spec_hash, verify_manifest, write_manifest
    from place3d_app.executors import LocalExecutor
    from place3d_kernels.spec import ConditionSpec, PSOGSpec, RoiSpec, SceneSpec, backend_name

    t0 = time.perf_counter()
    cfg = config if isinstance(config, dict) else load_config(config)
    executor = executor or LocalExecutor()
    out = Path(output or f"study-{_safe(cfg['name'])}")
    if out.exists() and not out.is_dir():
        raise ValueError(f"study output {out} is a file; give a folder (--output DIR)")
    _check_entries(cfg)
    from place3d_kernels.outputs import claim_study_folder, study_entries

    claim_study_folder(out, cfg, overwrite)          # a table of other entries is not replaced silently
    settings = study_settings(cfg)
    if settings["resamples"] < 0:
        raise ValueError(f"study resamples must be >= 0 (0: no intervals), got {settings['resamples']}")
    short = few_subsets(cfg, settings["frames_per_subset"])
    if settings["resamples"] and short:
        # an interval over 1-2 subsets has zero width (intervals.MIN_SUBSETS): none, said once, not per cell
        print(f"place3d: warning: no intervals: {short}", file=sys.stderr)
        settings["resamples"] = 0
    boot = {"resamples": settings["resamples"], "seed": settings["resample_seed"]}
    if overwrite and (out / "cells").exists():
        shutil.rmtree(out / "cells")
    elif (out / "cells").exists() and any((out / "cells").iterdir()) and not verify_manifest(out, settings, "study"):
        raise ValueError(f"{out} holds study cells without a manifest (made by an older version); use "
                         f"--overwrite to recompute them or choose a fresh folder")
    (out / "cells").mkdir(parents=True, exist_ok=True)
    write_manifest(out, settings)
    tag = spec_hash(settings)[:8]
    bname = backend_name(backend if backend is not None else cfg.get("backend"))
    lidar = cfg.get("lidar", "place3d_16ch")
    occlusion = cfg.get("occlusion", "sog")
    before = executor.submitted

    cells, groups = [], {}
    for s in cfg["scenes"]:
        sspec = SceneSpec.from_dict(s)
        for c in cfg["conditions"]:
            cspec = ConditionSpec.from_dict(c)
            pspec = PSOGSpec(sspec, bname, RoiSpec(cfg.get("voxel_size"), cfg.get("roi")), cspec,
                             cfg.get("collection_lidar", "collection_64ch"), cfg.get("frames_per_subset")).resolved()
            clabel = "clean" if cspec is None else cspec.label
            for p in cfg["placements"]:
                plabel = Path(p).stem if str(p).endswith(".toml") else str(p)
                path = out / "cells" / f"{_safe(sspec.label)}__{_safe(clabel)}__{_safe(plabel)}__{tag}.json"
                meta = {"scene": sspec.name, "scene_seed": sspec.seed, "frames": sspec.frames,
                        "condition": "clean" if cspec is None else cspec.name,
                        "severity": None if cspec is None else cspec.severity,
                        "condition_label": clabel, "placement": plabel, "settings": tag}
                cells.append(path)
                if not path.exists():
                    groups.setdefault(pspec, []).append((pspec, str(p), lidar, occlusion, bname, str(path), meta,
                                                         boot))
    todo = [t for g in groups.values() for t in g]
    if progress:
        print(f"study {cfg['name']}: {len(cells)} cells, {len(cells) - len(todo)} done, {len(todo)} to run "
              f"on {executor.kind} ({len(groups)} P-SOGs)", file=sys.stderr)
    # a bar per stage where the tasks run in this process; Ray runs them elsewhere, all at once
    bars = progress and executor.kind == "local"
    if progress and not bars and (groups or todo):
        print(f"study {cfg['name']}: waiting for {len(groups)} P-SOGs, then {len(todo)} cells, on {executor.kind} "
              f"(per-cell progress shows with --executor local)", file=sys.stderr)
    if groups:
        # one P-SOG per (scene, condition), so cells never race
        executor.map(*_ticking(_psog_task, [(g, boot["resamples"], bars) for g in groups], bars, "study: P-SOGs",
                               "P-SOG"))
    if todo:
        executor.map(*_ticking(_cell_task, todo, bars, "study: cells", "cell"))
    rows = [json.loads(p.read_text()) for p in cells]
    noise = _within_noise(rows, settings["resamples"])
    rows = [{k: v for k, v in r.items() if not k.startswith("samples_")} for r in rows]
    fields = ["scene", "scene_seed", "frames", "condition", "severity", "condition_label", "placement",
              "msog_seg", "msog_det", "ci_lo_seg", "ci_hi_seg", "ci_lo_det", "ci_hi_det"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    _atomic_text(out / "study.csv", buf.getvalue())
    executed = executor.submitted - before
    summary = {"name": cfg["name"], "rows": rows, "cells": len(cells), "executed": executed,
               "psogs_built_or_loaded": len(groups), "backend": bname, "executor": executor.kind,
               "lidar": lidar if isinstance(lidar, str) else lidar.name, "occlusion": occlusion,
               "settings": settings, "settings_sha256": spec_hash(settings),
               "scenes": cfg["scenes"], "conditions": cfg["conditions"],
               "placements": study_entries(cfg)["placements"], "within_noise": noise,
               "seconds": time.perf_counter() - t0}
    # provenance: the time and command line change per run, so a finished study's table stays comparable
    # by its rows and settings, not byte for byte
    _atomic_text(out / "study.json", json.dumps({**{k: v for k, v in summary.items() if k != "seconds"},
                                                 "provenance": provenance()}, indent=2, default=str))
    summary["csv"], summary["json"] = str(out / "study.csv"), str(out / "study.json")
    return summary


class _Tick:
    """``fn`` that advances a progress bar after each task (tasks run in this process: the local executor)."""

    def __init__(self, fn, bar):
        self.fn, self.bar = fn, bar

    def __call__(self, task):
        try:
            out = self.fn(task)
        except BaseException:
            self.bar.close()          # the error's message follows on a line of its own
            raise
        self.bar.update(1)
        if self.bar.n >= self.bar.total:
            self.bar.close()
        return out


def _ticking(fn, tasks: list, bar: bool, desc: str, unit: str) -> tuple:
    """(fn, tasks) for ``executor.map``: with ``bar``, ``fn`` advances a tqdm bar of ``len(tasks)`` on stderr."""
    if not bar:
        return fn, tasks
    from tqdm import tqdm

    return _Tick(fn, tqdm(total=len(tasks), desc=desc, unit=unit, file=sys.stderr)), tasks


def _within_noise(rows: list, resamples: int) -> dict:
    """{"<scene>-s<seed>/<condition>": {task: [[A, B, P(A > B)], ...]}}: the placement pairs of each drive
    whose order holds in < 95 % of the (paired) resamples; {} without a bootstrap."""
    import numpy as np

    from place3d_kernels.uncertainty import Bootstrap

    if not resamples:
        return {}
    groups: dict = {}
    for r in rows:
        groups.setdefault(f"{r['scene']}-s{r['scene_seed']}/{r['condition_label']}", []).append(r)
    out = {}
    for key, rs in groups.items():
        out[key] = {}
        for task in ("seg", "det"):
            b = Bootstrap([r["placement"] for r in rs], np.array([r[f"msog_{task}"] for r in rs]),
                          np.array([r[f"samples_{task}"] for r in rs]).T, unit="subsets")
            out[key][task] = [list(p) for p in b.within_noise()]
    return out


def run(args) -> int:
    from place3d_app.executors import executor_from_args

    cfg = load_config(args.config)
    if args.resamples is not None:
        cfg["resamples"] = args.resamples
    if args.roi is not None:
        cfg["roi"] = args.roi
    ex = executor_from_args(args)
    try:
        res = run_study(cfg, args.output, ex, args.backend, progress=not args.quiet,
                        overwrite=args.overwrite)
    finally:
        ex.shutdown()
    ci = res["settings"]["resamples"] > 0
    head = f"{'scene':22s} {'condition':24s} {'placement':14s} {'M-SOG seg':>11s} {'M-SOG det':>11s}"
    print(head + (f"  {'95 % interval seg':>24s} {'95 % interval det':>24s}" if ci else ""))
    for r in res["rows"]:
        line = (f"{r['scene'] + '-s' + str(r['scene_seed']):22s} {r['condition_label']:24s} {r['placement']:14s} "
                f"{r['msog_seg']:11.6f} {r['msog_det']:11.6f}")
        if ci:
            line += (f"  [{r['ci_lo_seg']:10.6f}, {r['ci_hi_seg']:10.6f}] "
                     f"[{r['ci_lo_det']:10.6f}, {r['ci_hi_det']:10.6f}]")
        print(line)
    for key, tasks in res["within_noise"].items():
        for task, pairs in tasks.items():
            if pairs:
                shown = ", ".join(f"{a} > {b} ({p:.2f})" for a, b, p in pairs[:6])
                more = f", and {len(pairs) - 6} more (study.json)" if len(pairs) > 6 else ""
                print(f"within noise ({key}, {task}): {shown}{more}")
    print(f"{res['cells']} cells ({res['executed']} tasks run) in {res['seconds']:.1f} s on {res['executor']}; "
          f"wrote {res['csv']} and {res['json']}")
    return 0
