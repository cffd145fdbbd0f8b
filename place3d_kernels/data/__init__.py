"""Data shipped with the package: the four CARLA OpenDRIVE maps of the Place3D paper (CC-BY, "CARLA
Simulator"; see ``data/opendrive/README.md``).

>>> from place3d_kernels.data import opendrive_path, CARLA_TOWNS
>>> opendrive_path("Town01")      # a plain .xodr file, decompressed once into the cache folder
"""

from __future__ import annotations

import gzip
import os
import tempfile
from importlib import resources
from pathlib import Path

__all__ = ["CARLA_TOWNS", "opendrive_path", "resolve_opendrive"]

#: the towns the paper collected its data in (Place3D, Sec. 4 / appendix)
CARLA_TOWNS = ("Town01", "Town03", "Town04", "Town06")


def _cache() -> Path:
    return Path(os.environ.get("PLACE3D_CACHE", Path.home() / ".cache" / "place3d")) / "opendrive"


def opendrive_path(name: str) -> Path:
    """Path of a shipped CARLA map as a plain ``.xodr`` file (``"Town01"`` or ``"Town01.xodr"``).

    Raises:
        ValueError: not a shipped map (the message lists them).
    """
    stem = Path(name).name.removesuffix(".gz").removesuffix(".xodr")
    src = resources.files("place3d_kernels.data") / "opendrive" / f"{stem}.xodr.gz"
    if stem not in CARLA_TOWNS or not src.is_file():
        raise ValueError(f"no shipped OpenDRIVE map {name!r}; shipped: {list(CARLA_TOWNS)} (or give a path "
                         f"to an .xodr file)")
    data = gzip.decompress(src.read_bytes())
    out = _cache() / f"{stem}.xodr"
    if not (out.is_file() and out.stat().st_size == len(data)):
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=out.parent, suffix=".tmp")  # per-writer name: parallel workers
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, out)
    return out


def resolve_opendrive(path_or_name) -> Path:
    """An existing file as given; otherwise the shipped map of that name."""
    p = Path(path_or_name)
    if p.is_file():
        return p
    return opendrive_path(str(path_or_name))
