"""Small helpers to read TOML configs with errors that name the file and the problem."""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

__all__ = ["read_toml", "resolve_config", "config_dir"]


def config_dir(kind: str) -> Path:
    """Folder of shipped configs of one kind (``lidars``, ``placements``, ...)."""
    return Path(str(resources.files("place3d_kernels.configs"))) / kind


def resolve_config(path_or_name, kind: str) -> Path:
    """A path as given, or the name of a shipped config (``"pyramid"`` -> place3d_kernels/configs/placements/pyramid.toml)."""
    p = Path(path_or_name)
    if p.exists():
        return p
    # a shipped name may name a subfolder ("carla_public/center"); never fall back to its bare stem
    rel = p if p.suffix == ".toml" else p.with_name(p.name + ".toml")
    shipped = config_dir(kind) / rel
    if not p.is_absolute() and ".." not in p.parts and shipped.exists():
        return shipped
    root = config_dir(kind)
    names = sorted(q.relative_to(root).with_suffix("").as_posix() for q in root.rglob("*.toml"))
    raise FileNotFoundError(f"No {kind[:-1]} config {str(path_or_name)!r}: not a file, and not one of the "
                            f"shipped names {names}")


def read_toml(path) -> dict:
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{p}: malformed TOML: {e}") from None


def require(d: dict, key: str, path, kind=(int, float)):
    if key not in d:
        raise ValueError(f"{path}: missing key {key!r}")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, kind):
        raise ValueError(f"{path}: key {key!r} must be {getattr(kind, '__name__', kind)}, got {v!r}")
    return v
