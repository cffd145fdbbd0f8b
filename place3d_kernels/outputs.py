"""Output folders that hold another run's results are refused unless ``--overwrite``.

A command writing into a folder first compares what the folder's earlier results were made with (the
setup its ``result.json`` or ``study.json`` records, or a manifest beside a checkpoint) with what this run
would make them with. Equal: the run continues (a rerun, or a resume). Different: ``ValueError`` naming the
first differing field and the way out, before anything is written. With ``--overwrite`` the earlier run's
files (those the command itself writes, by name) are removed first, so no file of the old run (the TOML of
another ``--task``, a checkpoint) is left beside the new ones.
"""

from __future__ import annotations

import json
from pathlib import Path

from place3d_kernels.manifest import field_value, first_difference, plain

__all__ = ["refuse_other_run", "stored_setup", "remove_owned"]

FIX = "use --overwrite to replace them or choose a fresh folder"


def stored_setup(path, key: str):
    """``json[key]`` of the JSON file at ``path``, or None when the file is absent; a file that is not
    readable JSON counts as another run's (an empty dict)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return d.get(key, {}) if isinstance(d, dict) else {}


def refuse_other_run(where, stored, current: dict, what: str, fix: str = FIX) -> None:
    """Raise ``ValueError`` when ``stored`` (the setup of the results at ``where``; None: none there) is not
    ``current``; the message is one line naming ``where``, the first differing field and ``fix``."""
    if stored is None:
        return
    stored, current = plain(stored), plain(current)
    field = first_difference(stored, current)
    if field is None:
        return
    raise ValueError(f"{where} holds the {what} of another run ({field}: {field_value(stored, field)!r} there, "
                     f"{field_value(current, field)!r} now); {fix}")


def remove_owned(folder, patterns) -> list:
    """Remove the files in ``folder`` matching ``patterns`` (globs of the names a command writes); returns
    them. Folders and other files are left alone."""
    folder = Path(folder)
    gone = []
    if not folder.is_dir():
        return gone
    for pat in patterns:
        for p in folder.glob(pat):
            if p.is_file() or p.is_symlink():
                p.unlink()
                gone.append(p)
    return gone


#: the files ``place3d optimize --output DIR`` writes into DIR (removed by ``--overwrite``)
OPTIMIZE_OUTPUTS = ("result.json", "history.csv", "optimized-*.toml", "convergence.png", "rig.png", "coverage.png",
                    "checkpoint.ckpt", "checkpoint.ckpt.manifest.json", "checkpoint.pkl",
                    "checkpoint.pkl.manifest.json")


def claim_optimize_folder(output, checkpoint, setup: dict, overwrite: bool, resume: bool) -> None:
    """The checks of ``place3d optimize`` on its output folder and checkpoint, before anything is built.

    Refused (``ValueError``): ``--overwrite`` with ``--resume``; an earlier version's pickle checkpoint
    where this run would resume; results (``result.json``) or, without ``--resume``, a checkpoint of a run
    with another setup, unless ``overwrite``, which removes that run's files (``OPTIMIZE_OUTPUTS``) first.
    """
    from place3d_kernels.optimize.checkpoint import LEGACY_NAME, refuse_legacy

    if overwrite and resume:
        raise ValueError("--overwrite starts afresh and --resume continues the earlier run; give one of them")
    out = Path(output) if output else None
    if resume:
        refuse_legacy(checkpoint, None if out is None else out / LEGACY_NAME)
    if overwrite:
        if out is not None:
            remove_owned(out, OPTIMIZE_OUTPUTS)
        if checkpoint is not None:
            remove_owned(Path(checkpoint).parent, (Path(checkpoint).name, Path(checkpoint).name + ".manifest.json"))
        return
    if out is not None:
        refuse_other_run(out / "result.json", stored_setup(out / "result.json", "setup"), setup, "results")
    if checkpoint is not None and not resume:
        man = Path(str(checkpoint) + ".manifest.json")
        refuse_other_run(checkpoint, stored_setup(man, "spec"), setup, "checkpoint",
                         "resume it with its settings (--resume), use --overwrite to discard it, or choose a "
                         "fresh folder")


def _placement_label(p) -> str:
    return Path(p).stem if str(p).endswith(".toml") else str(p)


def study_entries(cfg: dict) -> dict:
    """What a study's table (``study.csv``, ``study.json``) lists: its scenes, conditions and placements."""
    return {"scenes": cfg["scenes"], "conditions": cfg["conditions"],
            "placements": [_placement_label(p) for p in cfg["placements"]]}


def stored_study_entries(path):
    """``study_entries`` of the table at ``path`` (``study.json``), None when there is none; tables of
    earlier versions name their placements in their rows only."""
    d = stored_setup(path, "scenes")
    if d is None:
        return None
    try:
        j = json.loads(Path(path).read_text())
        placements = j.get("placements") or list(dict.fromkeys(r["placement"] for r in j.get("rows", [])))
        return {"scenes": j.get("scenes"), "conditions": j.get("conditions"), "placements": placements}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return {}


def claim_study_folder(out, cfg: dict, overwrite: bool) -> None:
    """Refuse (``ValueError``) a study folder whose table lists other scenes, conditions or placements than
    ``cfg``, unless ``overwrite``: rerunning replaces ``study.csv`` and ``study.json`` with a table of this
    study's entries only (the cells of other placements stay in ``cells/``, unlisted)."""
    if overwrite:
        return
    refuse_other_run(Path(out) / "study.json", stored_study_entries(Path(out) / "study.json"), study_entries(cfg),
                     "study table")
