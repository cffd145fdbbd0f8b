"""Label resolution shared by the mesh-file and Mitsuba XML loaders: class ids from ints, names and maps."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from place3d_kernels.classes import CLASS_ID, CLASSES

__all__ = ["resolve_class", "class_from_name", "load_label_map"]

_SUFFIX = re.compile(r"^(.*?)(?:[._\- ]\d+)?$")


def resolve_class(value, where: str = "") -> int:
    """A class id from an int or a class name ("traffic sign", "traffic_sign", "Road")."""
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{where}label {value!r} is not a class id or name")
    if isinstance(value, (int, np.integer)):
        v = int(value)
        if not 0 <= v < len(CLASSES):
            raise ValueError(f"{where}class id {v} is outside 0..{len(CLASSES) - 1}")
        return v
    if isinstance(value, str):
        key = value.strip().lower().replace("_", " ").replace("-", " ")
        if key.isdigit():
            return resolve_class(int(key), where)
        if key in CLASS_ID:
            return CLASS_ID[key]
        raise ValueError(f"{where}unknown class name {value!r}; known: {', '.join(CLASSES)}")
    raise ValueError(f"{where}label {value!r} is not a class id or name")


def class_from_name(name: str | None) -> int | None:
    """The class named by a mesh or node name with an optional numeric suffix ("road.001",
    "traffic_sign_3"); None for no name or a name that is not a class."""
    if not name:
        return None
    base = _SUFFIX.match(name.strip()).group(1).lower().replace("_", " ").replace("-", " ")
    return CLASS_ID.get(base)


def load_label_map(source) -> dict[str, int]:
    """A name -> class mapping from a dict or a TOML file (top-level keys or a ``[labels]`` table)."""
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"{path}: no such label map file")
        import tomllib

        try:
            data = tomllib.loads(path.read_text())
        except Exception as e:  # noqa: BLE001 - any parse error becomes a ValueError naming the file
            raise ValueError(f"{path}: not a valid TOML label map ({e})") from None
        if isinstance(data.get("labels"), dict):
            data = data["labels"]
        where = f"{path}: "
    elif isinstance(source, dict):
        data, where = source, ""
    else:
        raise ValueError(f"labels must be a dict, a TOML path, a class id or a class name, got {type(source).__name__}")
    return {str(k): resolve_class(v, f"{where}label map entry {k!r}: ") for k, v in data.items()}
