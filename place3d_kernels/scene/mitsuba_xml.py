"""Mitsuba 3 XML scenes as labelled meshes, parsed with ``xml.etree`` (Mitsuba itself is not needed).

Read from a ``<scene>``:

* ``<shape type="ply">`` and ``<shape type="obj">``: the file named by ``<string name="filename">``
  (relative to the XML file, then to ``<path value=...>`` folders) is read through
  :func:`place3d_kernels.scene.loaders.load_mesh`;
* built-in primitives as Mitsuba defines them: ``rectangle`` ([-1, 1]^2 at z = 0), ``cube`` ([-1, 1]^3),
  ``disk`` (unit disk at z = 0, ``segments`` triangles), ``sphere`` (``center``, ``radius``; an icosphere
  with ``sphere_subdivisions``), ``cylinder`` (open tube from ``p0`` to ``p1`` with ``radius``);
* ``shapegroup`` / ``instance`` (the group's shapes under the instance's ``to_world``), ``include``;
* ``<transform name="to_world">`` with ``translate``, ``rotate``, ``scale``, ``matrix`` and ``lookat`` in
  document order, each left-multiplying the ones before it (as Mitsuba composes them); a ``rotate``
  axis is used as given, as Mitsuba 3 does (a non-unit axis also scales; a warning says so);
* ``<default name=... value=...>`` and ``$name`` substitution in every attribute (``variables`` overrides
  the defaults, like keyword arguments of ``mitsuba.load_file``);
* ``flip_normals`` (reverses the triangle winding).

Other shape types (``serialized``, ``bsplinecurve``, ...) are skipped with a warning naming them.
Vertices are float64 in the scene's units (metres, z up expected).

Labels (the conventions of ``load_mesh``): ``labels`` is a mapping (a dict or a TOML path) from names to
Place3D classes (ids or names, ``"*"`` the fallback), or one class for the whole scene. For every shape
the names looked up are, in order, the shape ``id``, the ids of its BSDFs (referenced with ``<ref>`` or
inline, nested BSDFs included), and for file shapes the filename stem. The first mapped name labels
the whole shape; otherwise a file shape's own labels apply (node names in the map, a PLY per-face
``label`` property, class-named objects), then a shape / BSDF id / stem that is a class name
(``road``, ``road.001``, ``traffic_sign_3``), then ``"*"``, then ``default``.
"""

from __future__ import annotations

import math
import re
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.base import Scene
from place3d_kernels.scene.labels import class_from_name, load_label_map, resolve_class
from place3d_kernels.scene.loaders import combine, load_mesh
from place3d_kernels.scene.primitives import box, icosphere

__all__ = ["load_mitsuba_xml", "load_mitsuba_scene", "parse_transform"]

_VAR = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
_FILE_SHAPES = ("ply", "obj")
_PRIMITIVES = ("rectangle", "cube", "sphere", "disk", "cylinder")


# --------------------------------------------------------------------------------------------- transforms
def _floats(text: str, n: int | tuple[int, ...], where: str) -> np.ndarray:
    parts = [p for p in re.split(r"[,\s]+", (text or "").strip()) if p]
    try:
        vals = np.array([float(p) for p in parts], np.float64)
    except ValueError:
        raise ValueError(f"{where}: {text!r} is not a list of numbers") from None
    ns = (n,) if isinstance(n, int) else n
    if len(vals) not in ns:
        raise ValueError(f"{where}: expected {' or '.join(map(str, ns))} numbers, got {len(vals)} in {text!r}")
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{where}: non-finite number in {text!r}")
    return vals


def _float(text, where: str) -> float:
    return float(_floats(text, 1, where)[0])


def _vec3(el: ET.Element, where: str, default: float, names=("x", "y", "z")) -> np.ndarray:
    """A 3-vector from ``value="a b c"`` (or one number, broadcast) or x / y / z attributes."""
    if "value" in el.attrib:
        v = _floats(el.get("value"), (1, 3), where)
        return np.repeat(v, 3) if len(v) == 1 else v
    return np.array([_float(el.get(k), f"{where} attribute {k!r}") if k in el.attrib else default
                     for k in names], np.float64)


def _translate(t) -> np.ndarray:
    M = np.eye(4)
    M[:3, 3] = t
    return M


def _scale(s) -> np.ndarray:
    return np.diag([*np.broadcast_to(np.asarray(s, np.float64), (3,)), 1.0])


def _rotate(axis, angle_deg: float) -> np.ndarray:
    """Mitsuba 3's ``Transform4f.rotate``: c I + (1 - c) a a^T + s [a]x with the axis taken as given
    (Mitsuba 3 does not normalise it, so a non-unit axis also scales and shears)."""
    a = np.asarray(axis, np.float64)
    th = math.radians(angle_deg)
    c, s = math.cos(th), math.sin(th)
    x, y, z = a
    K = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    M = np.eye(4)
    M[:3, :3] = c * np.eye(3) + s * K + (1 - c) * np.outer(a, a)
    return M


def _coordinate_system(n):
    """Mitsuba's ``coordinate_system`` (Duff et al. 2017): two unit vectors orthogonal to ``n``."""
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    return (np.array([1 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]]),
            np.array([b, sign + n[1] * n[1] * a, -n[1]]))


def _look_at(origin, target, up) -> np.ndarray:
    d = np.asarray(target, float) - np.asarray(origin, float)
    if np.linalg.norm(d) == 0:
        raise ValueError("lookat origin and target coincide")
    d = d / np.linalg.norm(d)
    if up is None:
        up = _coordinate_system(d)[0]
    left = np.cross(up, d)
    if np.linalg.norm(left) == 0:
        raise ValueError("lookat up is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = left, new_up, d, origin
    return M


def parse_transform(el: ET.Element, where: str = "transform") -> np.ndarray:
    """The 4x4 matrix of a ``<transform>`` element: children applied in document order (each one
    left-multiplies the product of those before it)."""
    M = np.eye(4)
    for ch in el:
        tag, w = ch.tag, f"{where}: <{ch.tag}>"
        if tag == "translate":
            T = _translate(_vec3(ch, w, 0.0))
        elif tag == "scale":
            T = _scale(_vec3(ch, w, 1.0))
        elif tag == "rotate":
            if "angle" not in ch.attrib:
                raise ValueError(f"{w} needs an 'angle' (degrees)")
            if "axis" in ch.attrib:
                axis = _floats(ch.get("axis"), 3, f"{w} axis")
            else:
                axis = _vec3(ch, w, 0.0)
            if not np.any(axis):
                raise ValueError(f"{w} has no rotation axis (give value='x y z', axis='x y z' or x/y/z)")
            if abs(np.linalg.norm(axis) - 1) > 1e-6:
                warnings.warn(f"{w}: rotation axis {axis.tolist()} is not unit length; used as given, as Mitsuba 3 "
                              "does (the result is not a pure rotation; normalise the axis in the file for one)",
                              stacklevel=2)
            T = _rotate(axis, _float(ch.get("angle"), f"{w} angle"))
        elif tag == "matrix":
            T = _floats(ch.get("value"), (9, 16), f"{w} value")
            if len(T) == 9:
                T = np.block([[T.reshape(3, 3), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
            else:
                T = T.reshape(4, 4)
        elif tag == "lookat":
            for k in ("origin", "target"):
                if k not in ch.attrib:
                    raise ValueError(f"{w} needs an {k!r}")
            up = _floats(ch.get("up"), 3, f"{w} up") if "up" in ch.attrib else None
            try:
                T = _look_at(_floats(ch.get("origin"), 3, f"{w} origin"), _floats(ch.get("target"), 3, f"{w} target"),
                             up)
            except ValueError as e:
                if str(e).startswith(where):
                    raise
                raise ValueError(f"{w}: {e}") from None
        else:
            raise ValueError(f"{where}: unknown transform <{tag}> "
                             "(expected translate, rotate, scale, matrix or lookat)")
        M = T @ M
    return M


def _apply(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    return v @ M[:3, :3].T + M[:3, 3]


# --------------------------------------------------------------------------------------------- primitives
def _rectangle():
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.int64)


def _disk(n: int):
    a = 2 * np.pi * np.arange(n) / n
    v = np.concatenate([[[0.0, 0.0, 0.0]], np.c_[np.cos(a), np.sin(a), np.zeros(n)]])
    i = np.arange(n)
    return v, np.stack([np.zeros(n, np.int64), 1 + i, 1 + (i + 1) % n], 1)


def _tube(n: int):
    a = 2 * np.pi * np.arange(n) / n
    ring = np.c_[np.cos(a), np.sin(a)]
    v = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.ones(n)]])
    i = np.arange(n)
    j = (i + 1) % n
    return v, np.concatenate([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)]).astype(np.int64)


# --------------------------------------------------------------------------------------------- parser
class _Parser:
    def __init__(self, path: Path, labels, default, variables, sphere_subdivisions, segments):
        self.path = path
        self.explicit_default = default is not None
        self.default = resolve_class(0 if default is None else default, f"{path}: default ")
        self.whole = None
        self.mapping: dict[str, int] = {}
        if isinstance(labels, (int, np.integer, str)) and not (isinstance(labels, str) and labels.endswith(".toml")):
            self.whole = resolve_class(labels, f"{path}: ")
        elif labels is not None:
            self.mapping = load_label_map(labels)
        self.given = {str(k): str(v) for k, v in (variables or {}).items()}
        self.sphere_subdivisions = int(sphere_subdivisions)
        self.segments = int(segments)
        if self.segments < 3:
            raise ValueError(f"segments must be at least 3, got {segments}")
        self.ids: dict[str, ET.Element] = {}
        self.search: list[Path] = []
        self.pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.skipped: list[str] = []
        self.n_shapes = 0
        self.unlabelled: list[str] = []     # shapes no rule labelled, left to an implicit default

    # -- reading files ----------------------------------------------------------------------------------
    def read(self, path: Path, depth: int = 0, inherited: dict | None = None) -> list[ET.Element]:
        """The children of the ``<scene>`` of ``path`` with variables substituted, includes expanded."""
        if depth > 16:
            raise ValueError(f"{path}: <include> nested more than 16 deep (a cycle?)")
        if not path.is_file():
            raise ValueError(f"{path}: no such Mitsuba XML file")
        try:
            root = ET.parse(path).getroot()
        except ET.ParseError as e:
            raise ValueError(f"{path}: malformed XML ({e})") from None
        if root.tag != "scene":
            raise ValueError(f"{path}: the root element is <{root.tag}>, expected <scene>")
        env = dict(self.given if inherited is None else inherited)
        for d in root.findall("default"):
            if "name" not in d.attrib or "value" not in d.attrib:
                raise ValueError(f"{path}: <default> needs 'name' and 'value'")
            env.setdefault(d.get("name"), d.get("value"))
        for el in root.iter():
            for k, val in el.attrib.items():
                if "$" in val:
                    el.set(k, self._subst(val, env, path, el))
        out = []
        for el in root:
            if el.tag == "include":
                fn = el.get("filename")
                if not fn:
                    raise ValueError(f"{path}: <include> needs a 'filename'")
                out.extend(self.read(self._resolve(fn, path.parent, path, "include"), depth + 1, env))
            elif el.tag == "path":
                p = Path(el.get("value", ""))
                self.search.append(p if p.is_absolute() else path.parent / p)
            else:
                out.append(el)
        return out

    @staticmethod
    def _subst(val: str, env: dict, path: Path, el: ET.Element) -> str:
        def rep(m):
            if m.group(1) not in env:
                raise ValueError(f"{path}: <{el.tag}> uses ${m.group(1)}, which has no <default> and was not given")
            return env[m.group(1)]
        return _VAR.sub(rep, val)

    def _resolve(self, fn: str, base: Path, xml: Path, what: str) -> Path:
        p = Path(fn)
        cands = [p] if p.is_absolute() else [base / p] + [s / p for s in self.search]
        for c in cands:
            if c.is_file():
                return c
        raise ValueError(f"{xml}: {what} file {fn!r} not found (looked in {', '.join(str(c.parent) for c in cands)})")

    # -- elements -----------------------------------------------------------------------------------------
    def props(self, el: ET.Element) -> dict[str, ET.Element]:
        return {ch.get("name"): ch for ch in el if ch.get("name") is not None}

    def to_world(self, el: ET.Element, where: str) -> np.ndarray:
        M = np.eye(4)
        for ch in el:
            if ch.tag == "transform" and ch.get("name") in ("to_world", "toWorld"):
                M = parse_transform(ch, f"{self.path}: {where} <transform name='to_world'>")
        return M

    def bsdf_ids(self, el: ET.Element) -> list[str]:
        out: list[str] = []

        def walk(b: ET.Element, depth: int = 0):
            if depth > 32:
                return
            if b.get("id"):
                out.append(b.get("id"))
            for ch in b:
                if ch.tag == "bsdf":
                    walk(ch, depth + 1)
                elif ch.tag == "ref" and ch.get("id") in self.ids and self.ids[ch.get("id")].tag == "bsdf":
                    walk(self.ids[ch.get("id")], depth + 1)

        for ch in el:
            if ch.tag == "bsdf":
                walk(ch)
            elif ch.tag == "ref":
                rid = ch.get("id")
                if rid not in self.ids:
                    raise ValueError(f"{self.path}: <ref id={rid!r}> in shape {el.get('id') or el.get('type')!r} "
                                     "names no element with that id")
                if self.ids[rid].tag == "bsdf":
                    walk(self.ids[rid])
        return out

    def _from_default(self, names: list[str]) -> bool:
        """Whether the fallback of ``label_of(names)`` is the default class (no class name, no "*")."""
        return (self.whole is None and "*" not in self.mapping
                and all(class_from_name(n) is None for n in names))

    def label_of(self, names: list[str]):
        """(class from the mapping or None, fallback class)."""
        if self.whole is not None:
            return self.whole, self.whole
        hit = next((self.mapping[n] for n in names if n in self.mapping), None)
        fb = next((c for c in map(class_from_name, names) if c is not None), None)
        if fb is None:
            fb = self.mapping.get("*", self.default)
        return hit, fb

    def shape(self, el: ET.Element, parent: np.ndarray, xml_dir: Path):
        kind = el.get("type", "")
        sid = el.get("id") or ""
        where = f"shape {sid!r} (type {kind!r})" if sid else f"shape of type {kind!r}"
        if kind == "shapegroup":
            return  # drawn only through <shape type="instance">
        M = parent @ self.to_world(el, where)
        if kind == "instance":
            ref = next((ch for ch in el if ch.tag == "ref"), None)
            grp = self.ids.get(ref.get("id")) if ref is not None else None
            if grp is None or grp.tag != "shape" or grp.get("type") != "shapegroup":
                raise ValueError(f"{self.path}: {where} must <ref> the id of a <shape type='shapegroup'>")
            for ch in grp:
                if ch.tag == "shape":
                    self.shape(ch, M, xml_dir)
            return
        p = self.props(el)
        names = [n for n in [sid, *self.bsdf_ids(el)] if n]
        flip = p.get("flip_normals") is not None and p["flip_normals"].get("value", "false").strip().lower() == "true"
        if kind in _FILE_SHAPES:
            fe = p.get("filename")
            if fe is None or not fe.get("value"):
                raise ValueError(f"{self.path}: {where} has no <string name='filename'>")
            f = self._resolve(fe.get("value"), xml_dir, self.path, f"{where}:")
            names.append(f.stem)
            hit, fb = self.label_of(names)
            if hit is not None:
                m = load_mesh(f, labels=hit)
            else:
                sub = {k: v for k, v in self.mapping.items() if k != "*"}
                m = load_mesh(f, labels=sub or None, default=fb)
            v, fc, lab = m.vertices, m.faces.astype(np.int64), m.labels
            # the file's own labels (node names, PLY labels, class-named objects) labelled none of it
            unlabelled = hit is None and self._from_default(names) and bool(np.all(lab == fb))
        elif kind in _PRIMITIVES:
            hit, fb = self.label_of(names)
            if kind == "rectangle":
                v, fc = _rectangle()
            elif kind == "cube":
                v, fc = box((-1, -1, -1), (1, 1, 1))
            elif kind == "disk":
                v, fc = _disk(self.segments)
            elif kind == "sphere":
                v, fc = icosphere(self.sphere_subdivisions)
                c = _vec3(p["center"], f"{self.path}: {where} center", 0.0) if "center" in p else np.zeros(3)
                r = _float(p["radius"].get("value"), f"{self.path}: {where} radius") if "radius" in p else 1.0
                v = v * r + c
            else:  # cylinder: open tube along p0 -> p1
                p0 = _vec3(p["p0"], f"{self.path}: {where} p0", 0.0) if "p0" in p else np.zeros(3)
                p1 = _vec3(p["p1"], f"{self.path}: {where} p1", 0.0) if "p1" in p else np.array([0.0, 0, 1])
                r = _float(p["radius"].get("value"), f"{self.path}: {where} radius") if "radius" in p else 1.0
                d = p1 - p0
                length = np.linalg.norm(d)
                if length == 0:
                    raise ValueError(f"{self.path}: {where} has p0 == p1")
                s, t = _coordinate_system(d / length)
                F = np.eye(4)
                F[:3, 0], F[:3, 1], F[:3, 2], F[:3, 3] = s, t, d / length, p0
                v, fc = _tube(self.segments)
                v = _apply(F @ _scale((r, r, length)), v)
            lab = np.full(len(fc), fb if hit is None else hit)
            unlabelled = hit is None and self._from_default(names)
        else:
            self.skipped.append(f"{sid or '(no id)'} (type {kind!r})")
            return
        self.n_shapes += 1
        if unlabelled and not self.explicit_default:
            self.unlabelled.append(names[0] if names else f"({kind}, no id)")
        v = _apply(M, v)
        if flip:
            fc = fc[:, ::-1]
        self.pieces.append((v, np.asarray(fc, np.int64), np.asarray(lab)))

    def run(self) -> Mesh:
        els = self.read(self.path)
        for el in els:
            for e in [el, *el.iter()]:
                if e.get("id") and e.tag != "ref":
                    self.ids.setdefault(e.get("id"), e)
        for el in els:
            if el.tag == "shape":
                self.shape(el, np.eye(4), self.path.parent)
        if self.skipped:
            warnings.warn(f"{self.path}: skipped unsupported shapes: {', '.join(self.skipped)}", stacklevel=3)
        if self.unlabelled:
            names = sorted(set(self.unlabelled))
            listed = ", ".join(names[:8]) + (f" and {len(names) - 8} more names" if len(names) > 8 else "")
            warnings.warn(f"{self.path}: {len(self.unlabelled)} of {self.n_shapes} shapes match no label rule and "
                          f"become class 0 (unlabeled): {listed}; map their ids, BSDF ids or file names to classes "
                          f"in a TOML label map (place3d --labels FILE.toml, or labels= here; '*' for the rest), "
                          f"or pass default=", UserWarning, stacklevel=3)
        if not self.pieces:
            raise ValueError(f"{self.path}: holds no supported shapes (ply, obj, {', '.join(_PRIMITIVES)})")
        verts, faces, labs, n = [], [], [], 0
        for v, f, lab in self.pieces:
            verts.append(v)
            faces.append(f + n)
            labs.append(lab)
            n += len(v)
        try:
            return Mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(labs))
        except ValueError as e:
            raise ValueError(f"{self.path}: {e}") from None


def load_mitsuba_xml(path, labels=None, default=None, variables: dict | None = None, sphere_subdivisions: int = 3,
                     segments: int = 64) -> Mesh:
    """Read a Mitsuba XML scene into one labelled :class:`Mesh` (see the module docstring).

    Args:
        path: the XML file; shape filenames are resolved relative to it.
        labels: a name -> class mapping (dict or TOML path), or one class id / name for everything.
        default: the class of shapes that nothing labels. None (the default) means 0 (unlabeled) with a
            warning naming how many shapes that was and how to label them (as ``load_mesh`` warns for mesh
            files); an explicit class is used silently.
        variables: values for ``$name`` references, overriding the file's ``<default>`` elements.
        sphere_subdivisions: icosphere level for spheres (20 * 4**n triangles).
        segments: triangles around disks and cylinders.

    Raises:
        ValueError: malformed XML, a missing XML or shape file, an unknown transform, an undefined
            ``$variable``, a dangling ``<ref>``, bad numbers, unknown class names, no supported shapes.
    """
    return _Parser(Path(path), labels, default, variables, sphere_subdivisions, segments).run()


def load_mitsuba_scene(path, labels=None, ego_poses=None, **kw) -> Scene:
    """A static Scene from a Mitsuba XML file (``ego_poses`` default: one frame at the origin)."""
    m = load_mitsuba_xml(path, labels=labels, **kw)
    return combine([m], name=f"mitsuba-{Path(path).stem}", ego_poses=ego_poses)
