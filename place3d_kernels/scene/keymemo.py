"""Remembered scene cache keys: a cached P-SOG is found without building its scene.

A P-SOG cache file is named by ``Scene.key``, a hash of the built scene's geometry, labels, route and
actors. Building the procedural town only to learn that hash was most of a warm ``place3d optimize`` start.
So the key of each generated scene is remembered on disk under an identity that covers everything the build
depends on: the scene spec (name, seed, frames), the source of every module of the scene builder
(``place3d_kernels/scene/*.py``, ``mesh.py`` and ``classes.py``, all it imports from the package), the
package, NumPy and SciPy versions, and for an OpenDRIVE map the bytes of the map file. Any change to one of
them is a new identity, so the scene is built again and the new key remembered: a stale key is never used.
Scenes read from user files (``mesh:``, ``mitsuba:``) are always built (their content is the scene).
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

__all__ = ["SceneRef", "identity", "recall", "remember"]

_PKG = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class SceneRef:
    """A scene known by its name and cache key, built by ``build()`` only when its geometry is needed
    (``scene_psog`` calls it on a cache miss)."""

    name: str
    key: str
    build: Callable


@functools.lru_cache(maxsize=1)
def _sources_digest() -> str:
    import numpy as np

    from place3d_kernels.version import VERSION

    try:                        # the OpenDRIVE builder uses SciPy (KD-trees, ndimage); read its version only
        from importlib.metadata import version

        scipy_version = version("scipy")
    except Exception:  # noqa: BLE001 - not installed: the OpenDRIVE builder would fail anyway
        scipy_version = "none"
    h = hashlib.sha256(f"{VERSION} numpy {np.__version__} scipy {scipy_version}".encode())
    files = sorted((_PKG / "scene").glob("*.py")) + [_PKG / "mesh.py", _PKG / "classes.py"]
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def identity(spec_dict: dict, kind: str, path: Path | None) -> str | None:
    """The identity a scene's key is remembered under, or None for scenes that are always built."""
    if kind not in ("town", "opendrive"):
        return None
    h = hashlib.sha256(json.dumps(spec_dict, sort_keys=True).encode())
    h.update(_sources_digest().encode())
    if kind == "opendrive":
        h.update(Path(path).read_bytes())
    return h.hexdigest()[:32]


def _file(folder: Path, ident: str) -> Path:
    return Path(folder) / "scene-keys" / f"{ident}.json"


def recall(folder: Path, ident: str | None) -> tuple[str, str] | None:
    """(scene name, key) remembered under ``ident`` in ``folder``, or None."""
    if ident is None:
        return None
    try:
        d = json.loads(_file(folder, ident).read_text())
        return str(d["name"]), str(d["key"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def remember(folder: Path, ident: str | None, name: str, key: str) -> None:
    """Write (name, key) under ``ident`` (atomically: concurrent writers write the same content)."""
    if ident is None:
        return
    path = _file(folder, ident)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(path, json.dumps({"name": name, "key": key}))
    except OSError:
        pass   # a read-only cache folder: the scene is simply built next time
