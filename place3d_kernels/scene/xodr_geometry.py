"""OpenDRIVE reference-line geometry: cubic profiles and planView records (line, arc, spiral, poly3, paramPoly3)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["fnum", "Cubic", "Geometry"]


def fnum(el, name, path, default=None):
    v = el.get(name)
    if v is None:
        if default is not None:
            return float(default)
        raise ValueError(f"{path}: <{el.tag}> is missing attribute {name!r}")
    try:
        x = float(v)
    except ValueError:
        raise ValueError(f"{path}: <{el.tag}> attribute {name}={v!r} is not a number") from None
    if not math.isfinite(x):
        raise ValueError(f"{path}: <{el.tag}> attribute {name}={v!r} is not finite")
    return x


class Cubic:
    """Piecewise cubic a + b ds + c ds^2 + d ds^3 over records starting at s (``elevation``, ``laneOffset``)."""

    def __init__(self, records):
        recs = sorted(records, key=lambda r: r[0])
        self.s = np.array([r[0] for r in recs], float) if recs else np.zeros(1)
        self.k = np.array([r[1:] for r in recs], float) if recs else np.zeros((1, 4))

    @classmethod
    def parse(cls, els, path, s_key="s"):
        return cls([(fnum(e, s_key, path), fnum(e, "a", path, 0), fnum(e, "b", path, 0), fnum(e, "c", path, 0),
                     fnum(e, "d", path, 0)) for e in els])

    def __call__(self, s):
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 1)
        ds = s - self.s[i]
        a, b, c, d = self.k[i].T
        return a + ds * (b + ds * (c + ds * d))

    def slope(self, s):
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 1)
        ds = s - self.s[i]
        _, b, c, d = self.k[i].T
        return b + ds * (2 * c + 3 * ds * d)


class Geometry:
    """One planView record: evaluates (x, y, heading) at offsets ds in [0, length]."""

    def __init__(self, s, x, y, hdg, length, kind, p):
        self.s, self.x, self.y, self.hdg, self.length, self.kind, self.p = s, x, y, hdg, length, kind, p
        self._table = None
        if kind in ("spiral", "poly3", "paramPoly3"):
            self._build_table()

    def max_curvature(self) -> float:
        if self.kind == "arc":
            return abs(self.p["curvature"])
        if self.kind == "spiral":
            return max(abs(self.p["curvStart"]), abs(self.p["curvEnd"]))
        if self._table is not None:
            h = np.unwrap(self._table[3])
            s = self._table[0]
            if len(s) > 2:
                return float(np.max(np.abs(np.diff(h) / np.maximum(np.diff(s), 1e-9))))
        return 0.0

    def _build_table(self):
        """Dense (s, x, y, hdg) table for curves without a closed form."""
        L = self.length
        n = int(max(64, math.ceil(L / 0.05)))
        n += n % 2  # even for Simpson
        if self.kind == "spiral":
            k0, k1 = self.p["curvStart"], self.p["curvEnd"]
            cd = (k1 - k0) / L if L > 0 else 0.0
            s = np.linspace(0.0, L, n + 1)
            th = self.hdg + k0 * s + 0.5 * cd * s * s
            # cumulative Simpson over pairs of intervals, trapezoid midpoint for the odd nodes
            hm = 0.5 * (s[1:] + s[:-1])
            thm = self.hdg + k0 * hm + 0.5 * cd * hm * hm
            ds = np.diff(s)
            dx = ds / 6 * (np.cos(th[:-1]) + 4 * np.cos(thm) + np.cos(th[1:]))
            dy = ds / 6 * (np.sin(th[:-1]) + 4 * np.sin(thm) + np.sin(th[1:]))
            x = self.x + np.r_[0.0, np.cumsum(dx)]
            y = self.y + np.r_[0.0, np.cumsum(dy)]
            self._table = np.stack([s, x, y, th])
            return
        if self.kind == "poly3":
            a, b, c, d = (self.p[k] for k in "abcd")
            # arc length along u >= u, so u(L) <= L; sample u on [0, L] (extended if the curve is short)
            umax = L
            coef_u = (0.0, 1.0, 0.0, 0.0)
            coef_v = (a, b, c, d)
            param = "u"
        else:
            coef_u = tuple(self.p[k] for k in ("aU", "bU", "cU", "dU"))
            coef_v = tuple(self.p[k] for k in ("aV", "bV", "cV", "dV"))
            normalized = self.p.get("pRange", "arcLength").lower() == "normalized"
            umax = 1.0 if normalized else L
            param = "p"
        for _ in range(8):
            u = np.linspace(0.0, umax, n + 1)
            pu = coef_u[0] + u * (coef_u[1] + u * (coef_u[2] + u * coef_u[3]))
            pv = coef_v[0] + u * (coef_v[1] + u * (coef_v[2] + u * coef_v[3]))
            du = coef_u[1] + u * (2 * coef_u[2] + 3 * u * coef_u[3])
            dv = coef_v[1] + u * (2 * coef_v[2] + 3 * u * coef_v[3])
            sp = np.hypot(du, dv)
            arc = np.r_[0.0, np.cumsum(0.5 * (sp[1:] + sp[:-1]) * np.diff(u))]
            if param == "p" or arc[-1] >= L - 1e-9 or umax > 1e6:
                break
            umax *= 1.5
        if param == "p" and self.p.get("pRange", "arcLength").lower() != "normalized":
            s = u  # arcLength: p is the arc length by definition
        elif param == "p":
            s = arc * (L / arc[-1]) if arc[-1] > 0 else u * L
        else:
            s = arc
        ch, sh = math.cos(self.hdg), math.sin(self.hdg)
        # local (u, v) rotated by hdg and shifted to (x, y); a non-zero a / aU / aV offsets the start as in the spec
        x = self.x + ch * pu - sh * pv
        y = self.y + sh * pu + ch * pv
        th = self.hdg + np.arctan2(dv, du)
        self._table = np.stack([s, x, y, np.unwrap(th)])

    def eval(self, ds):
        ds = np.asarray(ds, float)
        if self.kind == "line" or (self.kind == "arc" and abs(self.p["curvature"]) < 1e-12):
            c, s = math.cos(self.hdg), math.sin(self.hdg)
            return self.x + ds * c, self.y + ds * s, np.full_like(ds, self.hdg)
        if self.kind == "arc":
            k = self.p["curvature"]
            th = self.hdg + k * ds
            return (self.x + (np.sin(th) - math.sin(self.hdg)) / k,
                    self.y - (np.cos(th) - math.cos(self.hdg)) / k, th)
        t = self._table
        return np.interp(ds, t[0], t[1]), np.interp(ds, t[0], t[2]), np.interp(ds, t[0], t[3])
