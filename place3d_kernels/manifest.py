"""Manifests and provenance: what an output was made from, so nothing stale is ever reused silently.

A *manifest* (``manifest.json`` in an output folder, or ``<file>.manifest.json`` beside a file) holds the
full spec dict an artefact was made from, the sha256 of its canonical JSON (sorted keys, no spaces) and
the package version. Before an artefact is reused, ``verify_manifest`` compares the stored spec with the
current one and raises ``ValueError`` naming the first field that differs; the way out is ``--overwrite``
or a fresh folder.

``provenance()`` is the block every output file carries: package version, command line, UTC time.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import sys
import threading
from pathlib import Path

__all__ = ["spec_hash", "write_manifest", "read_manifest", "verify_manifest", "first_difference", "provenance",
           "set_command_line", "MANIFEST_NAME"]

MANIFEST_NAME = "manifest.json"

#: the command line recorded in provenance blocks (``main(argv)`` sets it; otherwise ``sys.argv``)
_command_line: list | None = None


def set_command_line(argv) -> None:
    """Record ``argv`` (a list, or None for ``sys.argv``) as the command line of this run's outputs."""
    global _command_line
    _command_line = None if argv is None else [str(a) for a in argv]


def _canonical(d) -> str:
    return json.dumps(d, sort_keys=True, separators=(",", ":"), default=str)


def _plain(d):
    """``d`` as it reads back from JSON (tuples become lists), so stored and current specs compare equal."""
    return json.loads(_canonical(d))


def spec_hash(spec: dict) -> str:
    """sha256 (hex) of the canonical JSON of ``spec``."""
    return hashlib.sha256(_canonical(spec).encode()).hexdigest()


def _version() -> str:
    from place3d_kernels.version import VERSION  # a leaf module: importing the package root would be a cycle

    return VERSION


def provenance(**extra) -> dict:
    """Package version, command line (``sys.argv``) and UTC time (ISO 8601), plus ``extra`` fields."""
    argv = list(sys.argv) if _command_line is None else _command_line
    return {"package": "place3d-kernels", "version": _version(), "argv": argv,
            "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), **extra}


def _path(where) -> Path:
    where = Path(where)
    return where / MANIFEST_NAME if where.is_dir() or not where.suffix else where


def write_manifest(where, spec: dict) -> Path:
    """Write ``{"spec", "sha256", "version", "provenance"}`` atomically to ``where`` (a folder: its
    ``manifest.json``; a ``.json`` path: that file)."""
    path = _path(where)
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = _plain(spec)
    body = {"spec": spec, "sha256": spec_hash(spec), "version": _version(), "provenance": provenance()}
    tmp = path.with_name(path.name + f".tmp{os.getpid()}-{threading.get_ident()}")
    tmp.write_text(json.dumps(body, indent=2, sort_keys=True))
    os.replace(tmp, path)
    return path


def read_manifest(where) -> dict | None:
    """The manifest at ``where`` (folder or file), or None when there is none."""
    path = _path(where)
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except ValueError as e:
        raise ValueError(f"{path} is not a readable manifest ({e}); delete it or use --overwrite") from None


def first_difference(stored, current, prefix: str = "") -> str | None:
    """Dotted name of the first field where ``stored`` and ``current`` differ (keys sorted), or None."""
    if isinstance(stored, dict) and isinstance(current, dict):
        for k in sorted(set(stored) | set(current)):
            name = f"{prefix}.{k}" if prefix else str(k)
            if k not in stored or k not in current:
                return name
            d = first_difference(stored[k], current[k], name)
            if d is not None:
                return d
        return None
    return None if stored == current else (prefix or "<spec>")


def _get(d, dotted):
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return "<absent>"
        d = d[part]
    return d


def verify_manifest(where, spec: dict, what: str = "output",
                    fix: str = "use --overwrite to replace it or choose a fresh folder") -> bool:
    """Check that the manifest at ``where`` was written for ``spec``.

    Returns:
        True when a manifest exists and matches, False when there is none.

    Raises:
        ValueError: the stored spec differs; the message names the first differing field, both values,
            and ``fix``, the way out (default: ``--overwrite`` or a fresh folder).
    """
    m = read_manifest(where)
    if m is None:
        return False
    current = _plain(spec)
    stored = m.get("spec")
    if m.get("sha256") == spec_hash(current) and stored == current:
        return True
    field = first_difference(stored, current) or "sha256"
    raise ValueError(f"{_path(where)}: this {what} was made with different settings ({field}: "
                     f"{_get(stored, field)!r} there, {_get(current, field)!r} now); {fix}")
