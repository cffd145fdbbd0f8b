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
import sys
from pathlib import Path

__all__ = ["spec_hash", "write_manifest", "read_manifest", "verify_manifest", "first_difference", "provenance",
           "set_command_line", "MANIFEST_NAME", "content_hash", "verified_bytes", "ContentMismatch", "StaleCacheWarning",
           "cache_warning", "plain", "field_value"]

MANIFEST_NAME = "manifest.json"

#: the command line recorded in provenance blocks (``main(argv)`` sets it; otherwise ``sys.argv``)
_command_line: list | None = None


def set_command_line(argv) -> None:
    """Record ``argv`` (a list, or None for ``sys.argv``) as the command line of this run's outputs."""
    global _command_line
    _command_line = None if argv is None else [str(a) for a in argv]


def _canonical(d) -> str:
    return json.dumps(d, sort_keys=True, separators=(",", ":"), default=str)


def plain(d):
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


def content_hash(data: bytes) -> str:
    """sha256 (hex) of a file's bytes, as manifests record it (``content_sha256``)."""
    return hashlib.sha256(data).hexdigest()


def write_manifest(where, spec: dict, content_sha256: str | None = None) -> Path:
    """Write ``{"spec", "sha256", "version", "provenance"}`` atomically to ``where`` (a folder: its
    ``manifest.json``; a ``.json`` path: that file); with ``content_sha256``, the sha256 of the file the
    manifest describes too (``verified_bytes`` checks it)."""
    from place3d_kernels.atomic import atomic_write_text

    path = _path(where)
    spec = plain(spec)
    body = {"spec": spec, "sha256": spec_hash(spec), "version": _version(), "provenance": provenance()}
    if content_sha256 is not None:
        body["content_sha256"] = content_sha256
    atomic_write_text(path, json.dumps(body, indent=2, sort_keys=True))
    return path


class StaleCacheWarning(RuntimeWarning):
    """A cache file that is not used (damaged, rewritten, without its manifest, of other inputs): rebuilt."""


def cache_warning(path, cause) -> None:
    """Warn, in one line naming ``path`` and ``cause``, that a cache file is ignored and rebuilt."""
    import warnings

    why = " ".join(str(cause).split()) or type(cause).__name__
    if str(path) not in why:
        why = f"{path}: {why}"
    warnings.warn(f"cache file ignored and rebuilt: {why}", StaleCacheWarning, stacklevel=3)


class ContentMismatch(ValueError):
    """A file whose bytes are not those its manifest recorded (or which has no manifest to say)."""


def verified_bytes(path, manifest, spec: dict, what: str) -> bytes:
    """The bytes of ``path``, checked against the manifest at ``manifest``: written for ``spec`` and with
    the sha256 of exactly these bytes.

    Raises:
        ContentMismatch: no manifest, one without a content hash (an earlier version's), or other bytes;
            the message is one line naming the file and the cause.
        ValueError: the manifest was written for other settings (``verify_manifest``).
    """
    path = Path(path)
    if not verify_manifest(manifest, spec, what, "it is rebuilt"):
        raise ContentMismatch(f"{path}: {what} without its manifest ({Path(manifest).name}), so its content "
                              f"cannot be checked")
    want = read_manifest(manifest).get("content_sha256")
    if not want:
        raise ContentMismatch(f"{path}: the manifest of this {what} records no content hash (written by an "
                              f"earlier version)")
    data = path.read_bytes()
    if content_hash(data) != want:
        raise ContentMismatch(f"{path}: content differs from the sha256 its manifest recorded (damaged or "
                              f"rewritten)")
    return data


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


def field_value(d, dotted):
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
    current = plain(spec)
    stored = m.get("spec")
    if m.get("sha256") == spec_hash(current) and stored == current:
        return True
    field = first_difference(stored, current) or "sha256"
    raise ValueError(f"{_path(where)}: this {what} was made with different settings ({field}: "
                     f"{field_value(stored, field)!r} there, {field_value(current, field)!r} now); {fix}")
