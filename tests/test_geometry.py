"""The backend-neutral geometry module: one watertight ray/triangle test shared by the reference backend,
the OpenCL backend's host fallback and the vehicle body's inside test, and no module reaching into the
reference backend's internals (issue 32, boundary leaks)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import trimesh

from place3d_kernels.backends.geometry import brute_force_raycast, watertight_intersect
from place3d_kernels.backends.reference import ReferenceBackend

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = "place3d_kernels.backends.reference"


def _imported_modules(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def test_only_the_reference_backend_imports_its_internals():
    # the registry names the module as a string and imports it by name; tests may compare against it
    bad = []
    for pkg in ("place3d_kernels", "place3d_client"):
        for p in sorted((ROOT / pkg).rglob("*.py")):
            rel = p.relative_to(ROOT).as_posix()
            if rel.startswith("place3d_kernels/backends/reference/"):
                continue
            if any(m == REFERENCE or m.startswith(REFERENCE + ".") for m in _imported_modules(p)):
                bad.append(rel)
    assert not bad, f"modules importing the reference backend's internals: {bad}"


def test_brute_force_is_the_reference_raycast_bit_for_bit():
    rng = np.random.default_rng(3)
    m = trimesh.creation.icosphere(subdivisions=1)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    o = rng.normal(0, 3, (200, 3))
    d = v[rng.integers(0, len(v), 200)] - o          # aimed at shared vertices: ties between faces
    d /= np.linalg.norm(d, axis=1)[:, None]
    tm = np.where(np.arange(200) % 5 == 0, 2.0, np.inf)
    ref = ReferenceBackend()
    want_t, want_f = ref.raycast(ref.upload_mesh(v, f), o, d, tm)
    got_t, got_f = brute_force_raycast(v, f, o, d, tm)
    assert np.array_equal(got_t, want_t) and np.array_equal(got_f, want_f) and got_f.dtype == np.int32
    # the pairwise test: (rays, faces) distances, inf off the triangle and beyond t_max
    tri = np.array([[[2.0, -1.0, -1.0]], [[2.0, 1.0, -1.0]], [[2.0, 0.0, 1.0]]])
    t = watertight_intersect(np.zeros((3, 3)), np.array([[1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0]]), *tri,
                             np.array([np.inf, np.inf, 1.5]))
    assert t.shape == (3, 1) and t[0, 0] == 2.0 and np.isinf(t[1:, 0]).all()
