"""``place3d study CONFIG.toml``: M-SOG (seg, det) over a grid of placements x conditions x scenes.

The config (``place3d_kernels/configs/study/example.toml``)::

    [study]
    name = "example"
    lidar = "place3d_16ch"          # the rig's LiDAR model
    occlusion = "sog"
    voxel_size = 0.2                 # optional; default grid otherwise
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
(``<settings>``: hash of ``study_settings``: LiDAR, occlusion, grid, k, collection LiDAR). A rerun
submits only cells whose file is missing, so rerunning a finished study does no work; a rerun with other
settings is refused (``manifest.json``) unless ``--overwrite``. The table
(``study.csv``, ``study.json``) is always rebuilt from the cell files.
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
import time
from pathlib import Path

__all__ = ["add_arguments", "run", "run_study", "load_config"]


def add_arguments(p) -> None:
    from place3d_kernels.distributed import add_executor_arguments

    p.add_argument("config", help="study TOML (see place3d_kernels/configs/study/example.toml)")
    p.add_argument("--output", default=None, help="output folder (default: study-<name>/)")
    p.add_argument("--backend", default=None, help="backend of the tasks (default: $PLACE3D_BACKEND or auto)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--overwrite", action="store_true",
                   help="discard the cells of an earlier study in --output made with other settings")
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
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def _psog_task(spec) -> str:
    spec.load()                                   # builds the cache file if it is absent
    return spec.scene.label


def _cell_task(t) -> dict:
    """Score one placement on one (scene, condition) P-SOG, both tasks; write the cell file atomically."""
    psog_spec, placement, lidar, occlusion, backend, path, meta = t
    from place3d_kernels.spec import resolve_lidar
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import Placement

    psog = psog_spec.load()
    pl = Placement.load(placement)
    L = resolve_lidar(lidar)
    row = dict(meta)
    for task in ("seg", "det"):
        row[f"msog_{task}"] = float(msog_batch(psog, L, pl.poses[None], occlusion, task, backend)[0])
    _atomic_text(Path(path), json.dumps(row, indent=1))
    return row


def study_settings(cfg: dict) -> dict:
    """The settings every cell depends on besides its own scene, condition and placement (the study
    folder's manifest; the backend is left out: the three backends agree bit for bit)."""
    from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET

    return {"lidar": cfg.get("lidar", "place3d_16ch"), "occlusion": cfg.get("occlusion", "sog"),
            "voxel_size": cfg.get("voxel_size"), "frames_per_subset": cfg.get("frames_per_subset")
            or DEFAULT_FRAMES_PER_SUBSET, "collection_lidar": cfg.get("collection_lidar", "collection_64ch")}


def _check_entries(cfg: dict) -> None:
    """Every placement, scene and condition of the study loads (before any file is written)."""
    from place3d_kernels.placement import Placement
    from place3d_kernels.spec import ConditionSpec, SceneSpec, resolve_lidar

    for p in cfg["placements"]:
        Placement.load(p)
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
    from place3d_kernels.distributed import LocalExecutor
    from place3d_kernels.spec import ConditionSpec, PSOGSpec, RoiSpec, SceneSpec, backend_name

    t0 = time.perf_counter()
    cfg = config if isinstance(config, dict) else load_config(config)
    executor = executor or LocalExecutor()
    out = Path(output or f"study-{_safe(cfg['name'])}")
    if out.exists() and not out.is_dir():
        raise ValueError(f"study output {out} is a file; give a folder (--output DIR)")
    _check_entries(cfg)
    settings = study_settings(cfg)
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
            pspec = PSOGSpec(sspec, bname, RoiSpec(cfg.get("voxel_size")), cspec,
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
                    groups.setdefault(pspec, []).append((pspec, str(p), lidar, occlusion, bname, str(path), meta))
    todo = [t for g in groups.values() for t in g]
    if progress:
        print(f"study {cfg['name']}: {len(cells)} cells, {len(cells) - len(todo)} done, {len(todo)} to run "
              f"on {executor.kind} ({len(groups)} P-SOGs)", file=sys.stderr)
    if groups:
        executor.map(_psog_task, list(groups))     # one P-SOG per (scene, condition), so cells never race
    if todo:
        executor.map(_cell_task, todo)
    rows = [json.loads(p.read_text()) for p in cells]
    fields = ["scene", "scene_seed", "frames", "condition", "severity", "condition_label", "placement",
              "msog_seg", "msog_det"]
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
               "seconds": time.perf_counter() - t0}
    # provenance: the time and command line change per run, so a finished study's table stays comparable
    # by its rows and settings, not byte for byte
    _atomic_text(out / "study.json", json.dumps({**{k: v for k, v in summary.items() if k != "seconds"},
                                                 "provenance": provenance()}, indent=2, default=str))
    summary["csv"], summary["json"] = str(out / "study.csv"), str(out / "study.json")
    return summary


def run(args) -> int:
    from place3d_kernels.distributed import executor_from_args

    ex = executor_from_args(args)
    try:
        res = run_study(args.config, args.output, ex, args.backend, progress=not args.quiet,
                        overwrite=args.overwrite)
    finally:
        ex.shutdown()
    print(f"{'scene':22s} {'condition':24s} {'placement':14s} {'M-SOG seg':>11s} {'M-SOG det':>11s}")
    for r in res["rows"]:
        print(f"{r['scene'] + '-s' + str(r['scene_seed']):22s} {r['condition_label']:24s} {r['placement']:14s} "
              f"{r['msog_seg']:11.6f} {r['msog_det']:11.6f}")
    print(f"{res['cells']} cells ({res['executed']} tasks run) in {res['seconds']:.1f} s on {res['executor']}; "
          f"wrote {res['csv']} and {res['json']}")
    return 0
