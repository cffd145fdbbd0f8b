"""OpenDRIVE (1.4-style) parsing with ``xml.etree``: roads, lane sections, lanes and road marks."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path as _FsPath

import numpy as np

from place3d_kernels.scene.xodr_geometry import Cubic, Geometry, fnum

__all__ = ["parse_opendrive", "OpenDrive", "Road", "Lane", "Section"]


class Lane:
    def __init__(self, lid, ltype, widths, borders, marks):
        self.id, self.type = lid, ltype
        self.width = Cubic(widths) if widths else None
        self.border = Cubic(borders) if borders else None
        self.marks = sorted(marks)  # (sOffset, type, width)

    def mark_at(self, ds):
        m = None
        for rec in self.marks:
            if rec[0] <= ds + 1e-9:
                m = rec
        return m


class Section:
    def __init__(self, s, left, right, center):
        self.s = s
        self.left = sorted(left, key=lambda l: l.id)            # 1, 2, 3, ...
        self.right = sorted(right, key=lambda l: -l.id)         # -1, -2, -3, ...
        self.center = center
        self.s_end = None


class Road:
    """A parsed road: reference line, elevation, lane offset and lane sections."""

    def __init__(self, rid, name, length, junction, geoms, elevation, offset, sections):
        self.id, self.name, self.length, self.junction = rid, name, length, junction
        self.geoms, self.elevation, self.offset, self.sections = geoms, elevation, offset, sections
        self._gs = np.array([g.s for g in geoms])

    def reference(self, s):
        """x, y, heading of the reference line at s (array)."""
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self._gs, s, side="right") - 1, 0, len(self.geoms) - 1)
        x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        for k in np.unique(i):
            m = i == k
            g = self.geoms[k]
            x[m], y[m], h[m] = g.eval(np.clip(s[m] - g.s, 0.0, max(g.length, 0.0)))
        return x, y, h

    def samples(self, step: float) -> np.ndarray:
        """Sample positions along s: a uniform grid of ``step`` (finer on tight curves) plus every
        geometry and lane-section start and the road end."""
        pts = [np.arange(0.0, self.length, step), [self.length]]
        for g in self.geoms:
            pts.append([g.s])
            kmax = g.max_curvature()
            if kmax > 1e-9 and 0.15 / kmax < step:  # about 0.15 rad per step
                fine = max(0.15 / kmax, 0.1)
                pts.append(g.s + np.arange(0.0, g.length, fine))
        for sec in self.sections:
            pts.append([sec.s])
        s = np.unique(np.clip(np.concatenate([np.asarray(p, float) for p in pts]), 0.0, self.length))
        keep = np.r_[True, np.diff(s) > 1e-6]
        return s[keep]


class OpenDrive:
    """A parsed OpenDRIVE file: roads and the number of junctions."""

    def __init__(self, path, roads, n_junctions, header):
        self.path, self.roads, self.n_junctions, self.header = path, roads, n_junctions, header

    @property
    def road_length(self) -> float:
        return float(sum(r.length for r in self.roads))


def _lane(el, path, rid) -> Lane:
    try:
        lid = int(el.get("id"))
    except (TypeError, ValueError):
        raise ValueError(f"{path}: road {rid}: <lane> has no integer id (got {el.get('id')!r})") from None
    ltype = (el.get("type") or "none").strip()
    widths = [(fnum(w, "sOffset", path), fnum(w, "a", path, 0), fnum(w, "b", path, 0), fnum(w, "c", path, 0),
               fnum(w, "d", path, 0)) for w in el.findall("width")]
    borders = [(fnum(w, "sOffset", path), fnum(w, "a", path, 0), fnum(w, "b", path, 0), fnum(w, "c", path, 0),
                fnum(w, "d", path, 0)) for w in el.findall("border")]
    if lid != 0 and not widths and not borders:
        raise ValueError(f"{path}: road {rid}: lane {lid} has neither <width> nor <border>")
    marks = [(fnum(m, "sOffset", path, 0), (m.get("type") or "none").strip().lower(),
              fnum(m, "width", path, 0.0)) for m in el.findall("roadMark")]
    return Lane(lid, ltype, widths, borders, marks)


def parse_opendrive(path) -> OpenDrive:
    """Parse an OpenDRIVE (1.4-style) file: a path, or the name of a shipped CARLA map (``"Town01"``).

    Raises ValueError naming the file and the problem.
    """
    path = _FsPath(path)
    if not path.is_file():
        from place3d_kernels.data import CARLA_TOWNS, opendrive_path

        if path.name.removesuffix(".xodr") not in CARLA_TOWNS:
            raise ValueError(f"{path}: no such OpenDRIVE file (shipped maps by name: {list(CARLA_TOWNS)})")
        path = opendrive_path(path.name)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ValueError(f"{path}: not well-formed XML ({e})") from None
    if root.tag != "OpenDRIVE":
        raise ValueError(f"{path}: root element is <{root.tag}>, expected <OpenDRIVE>")
    road_els = root.findall("road")
    if not road_els:
        raise ValueError(f"{path}: no <road> elements")
    roads = []
    for r in road_els:
        rid = r.get("id", "?")
        length = fnum(r, "length", path)
        if length <= 0:
            raise ValueError(f"{path}: road {rid} has non-positive length {length}")
        pv = r.find("planView")
        if pv is None:
            raise ValueError(f"{path}: road {rid} has no <planView>")
        geoms = []
        for g in pv.findall("geometry"):
            kids = [k for k in g if k.tag in ("line", "arc", "spiral", "poly3", "paramPoly3")]
            if not kids:
                raise ValueError(f"{path}: road {rid}: <geometry s={g.get('s')}> has no line/arc/spiral/poly3/"
                                 f"paramPoly3 child")
            k = kids[0]
            if k.tag == "line":
                p = {}
            elif k.tag == "arc":
                p = {"curvature": fnum(k, "curvature", path)}
            elif k.tag == "spiral":
                p = {"curvStart": fnum(k, "curvStart", path), "curvEnd": fnum(k, "curvEnd", path)}
            elif k.tag == "poly3":
                p = {c: fnum(k, c, path) for c in "abcd"}
            else:
                p = {c: fnum(k, c, path) for c in ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV")}
                p["pRange"] = k.get("pRange", "arcLength")
            glen = fnum(g, "length", path)
            if glen < 0:
                raise ValueError(f"{path}: road {rid}: geometry with negative length {glen}")
            geoms.append(Geometry(fnum(g, "s", path), fnum(g, "x", path), fnum(g, "y", path), fnum(g, "hdg", path),
                                   glen, k.tag, p))
        if not geoms:
            raise ValueError(f"{path}: road {rid}: <planView> has no <geometry>")
        geoms.sort(key=lambda g: g.s)
        ep = r.find("elevationProfile")
        elevation = Cubic.parse(ep.findall("elevation") if ep is not None else [], path)
        lanes_el = r.find("lanes")
        if lanes_el is None:
            raise ValueError(f"{path}: road {rid} has no <lanes>")
        offset = Cubic.parse(lanes_el.findall("laneOffset"), path)
        sections = []
        for sec in lanes_el.findall("laneSection"):
            s0 = fnum(sec, "s", path)
            left = [_lane(l, path, rid) for side in sec.findall("left") for l in side.findall("lane")]
            right = [_lane(l, path, rid) for side in sec.findall("right") for l in side.findall("lane")]
            cen = [_lane(l, path, rid) for side in sec.findall("center") for l in side.findall("lane")]
            sections.append(Section(s0, left, right, cen[0] if cen else None))
        if not sections:
            raise ValueError(f"{path}: road {rid}: <lanes> has no <laneSection>")
        sections.sort(key=lambda x: x.s)
        for a, b in zip(sections[:-1], sections[1:]):
            a.s_end = b.s
        sections[-1].s_end = length
        roads.append(Road(rid, r.get("name", ""), length, r.get("junction", "-1"), geoms, elevation, offset,
                          sections))
    return OpenDrive(path, roads, len(root.findall("junction")), root.find("header"))
