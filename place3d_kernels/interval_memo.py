"""Interval scores of fixed rigs, remembered on disk beside a scene's subset records.

``place3d optimize`` prints an interval for the optimised rig and for each of the eleven paper baselines:
every rig is rescored on each leave-one-out (or resampled) P-SOG of the drive. The baselines' scores there
depend only on the scene's subset records, the rig, the LiDAR, the task, the occlusion mode, the
normalisation and the code, never on the search, yet they were most of the interval's scoring. So they are
remembered: one JSON file per subset-record file and code identity, one entry per rig (its point score and
its row of resampled scores).

A stale entry is never used. The file's name carries a digest of the package's source (every ``.py``
and ``.cl`` file under ``place3d_kernels/``), the package and NumPy versions, so any code change starts a
new file (older ones are removed when the new one is written). An entry's key hashes everything else the
scores depend on: the LiDAR model's full state, the rig's float64 poses, task, occlusion, normalisation,
the vehicle body and the resampling (method, count, seed). The backend is not in the key: backends agree
bit for bit (tests/test_cross_backend.py and the stress suites hold them to it). Floats are written with
``repr`` and read back exactly (NaN included).
"""

from __future__ import annotations

import functools
import hashlib
import json
import pickle
from pathlib import Path

import numpy as np

__all__ = ["IntervalMemo", "code_digest", "rig_key"]

_PKG = Path(__file__).resolve().parent


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """sha256 (hex, 16 chars) of the package version, NumPy's version and every source file of the package."""
    from place3d_kernels.version import VERSION

    h = hashlib.sha256(f"{VERSION} numpy {np.__version__}".encode())
    for f in sorted(_PKG.rglob("*")):
        if f.suffix in (".py", ".cl") and f.is_file():
            h.update(str(f.relative_to(_PKG)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def rig_key(lidar, poses, **setting) -> str:
    """A key for one rig's interval scores: the LiDAR's state, the (L, 6) float64 poses and ``setting``
    (task, occlusion, normalisation, body, method, resamples, seed: plain values)."""
    state = {k: (v.tobytes() if isinstance(v, np.ndarray) else repr(v)) for k, v in sorted(vars(lidar).items())}
    p = np.ascontiguousarray(poses, dtype=np.float64)
    blob = pickle.dumps((state, p.shape, p.tobytes(), sorted(setting.items())), protocol=4)
    return hashlib.sha256(blob).hexdigest()[:32]


class IntervalMemo:
    """Entries ``{rig key: (point, samples)}`` in ``<records stem>-intervals-<code digest>.json``.

    Args:
        records_path: the subset-record cache file these scores were computed from.
    """

    def __init__(self, records_path: Path):
        records_path = Path(records_path)
        self._prefix = records_path.stem + "-intervals-"
        self.path = records_path.with_name(f"{self._prefix}{code_digest()}.json")
        self._entries: dict = {}
        self._dirty = False
        try:
            self._entries = json.loads(self.path.read_text())["entries"]
        except (OSError, ValueError, KeyError, TypeError):
            self._entries = {}      # none yet, or unreadable: recomputed and rewritten

    def get(self, key: str):
        """(point, samples (R,) float64) or None."""
        e = self._entries.get(key)
        if e is None:
            return None
        return float(e["point"]), np.array([float(v) for v in e["samples"]], dtype=np.float64)

    def put(self, key: str, point: float, samples) -> None:
        self._entries[key] = {"point": repr(float(point)), "samples": [repr(float(v)) for v in samples]}
        self._dirty = True

    def save(self) -> None:
        """Write the entries atomically (if any changed) and remove this record file's older memos."""
        if not self._dirty:
            return
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(self.path, json.dumps({"code": code_digest(), "entries": self._entries}))
        self._dirty = False
        for old in self.path.parent.glob(f"{self._prefix}*.json"):
            if old != self.path:
                try:
                    old.unlink()
                except OSError:
                    pass
