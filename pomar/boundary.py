"""Where a flight may go (issue 72's ``--boundary``): the polygon a grower draws around the block (the property's
edge, a neighbour's house, a power line left outside), read from GeoJSON or a CSV of vertices, and the part of a
straight line inside it.

- GeoJSON: a Polygon, or a Feature or FeatureCollection holding one (its outer ring; holes are not read), lon/lat.
- CSV: ``lat,lon`` columns, one vertex a line, in order round the polygon (closing it again is optional).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from pomar.cli import InputError
from pomar.geo import Origin


class BoundaryError(InputError, ValueError):
    """A boundary file that cannot be read as one polygon: its message names the file and what is wrong."""


def _geojson_ring(path: Path, doc) -> list:
    polys = []

    def walk(g):
        if not isinstance(g, dict):
            return
        kind = g.get("type")
        if kind == "FeatureCollection":
            for f in g.get("features") or []:
                walk(f)
        elif kind == "Feature":
            walk(g.get("geometry"))
        elif kind == "Polygon":
            polys.append(g.get("coordinates"))
        elif kind == "MultiPolygon":
            polys.extend(g.get("coordinates") or [])

    walk(doc)
    if len(polys) != 1:
        raise BoundaryError(f"{path}: {'no' if not polys else len(polys)} polygons: give the one the flight stays in")
    try:
        return [(float(p[1]), float(p[0])) for p in polys[0][0]]
    except (TypeError, IndexError, ValueError):
        raise BoundaryError(f"{path}: the polygon's outer ring is not a list of [lon, lat] positions") from None


def _csv_ring(path: Path, text: str) -> list:
    rows = list(csv.DictReader(text.splitlines()))
    if not rows or not {"lat", "lon"} <= set(rows[0]):
        raise BoundaryError(f"{path}: no lat and lon columns (a CSV boundary has a vertex a line)")
    out = []
    for k, r in enumerate(rows, start=2):
        try:
            out.append((float(r["lat"]), float(r["lon"])))
        except (TypeError, ValueError):
            raise BoundaryError(f"{path}:{k}: lat {r['lat']!r}, lon {r['lon']!r} is no position") from None
    return out


def read_boundary(path, origin: Origin) -> np.ndarray:
    """The boundary in ``path`` as an (N, 2) ENU polygon (m about ``origin``), not closed."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise BoundaryError(f"{path}: cannot be read ({exc.strerror if isinstance(exc, OSError) else 'not text'})") \
            from None
    if path.suffix.lower() in (".json", ".geojson"):
        try:
            ring = _geojson_ring(path, json.loads(text))
        except json.JSONDecodeError as exc:
            raise BoundaryError(f"{path}: not JSON (line {exc.lineno}: {exc.msg})") from None
    else:
        ring = _csv_ring(path, text)
    if len(ring) > 1 and ring[0] == ring[-1]:
        ring = ring[:-1]
    ll = np.array(ring, float).reshape(-1, 2)
    if len(ll) < 3 or not np.isfinite(ll).all() or (np.abs(ll[:, 0]) > 90).any() or (np.abs(ll[:, 1]) > 180).any():
        raise BoundaryError(f"{path}: a boundary needs 3 or more positions (latitude within 90, longitude within 180), "
                            f"got {len(ll)}")
    xy = np.asarray(origin.to_enu(ll[:, 0], ll[:, 1], np.full(len(ll), origin.alt)), float)[:, :2]
    x, y = xy[:, 0], xy[:, 1]
    if abs(0.5 * (x @ np.roll(y, -1) - y @ np.roll(x, -1))) < 1.0:
        raise BoundaryError(f"{path}: the polygon encloses less than 1 square metre")
    return xy


def inside(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Whether each of ``pts`` (M, 2) lies inside ``poly`` (N, 2), by the crossing rule."""
    pts = np.atleast_2d(pts)
    x, y = pts[:, 0:1], pts[:, 1:2]
    a, b = poly, np.roll(poly, -1, axis=0)
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        at = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (crosses & (x < at)).sum(axis=1) % 2 == 1


def clip_segment(poly: np.ndarray, p: np.ndarray, q: np.ndarray) -> tuple[float, float] | None:
    """The longest stretch of the segment p-q inside ``poly``, as fractions (t0, t1) of the way from p to q; None where
    none of it is inside."""
    d = q - p
    a, b = poly, np.roll(poly, -1, axis=0)
    e = b - a
    den = d[0] * e[:, 1] - d[1] * e[:, 0]
    ts = [0.0, 1.0]
    ok = np.abs(den) > 1e-12
    w = a[ok] - p
    t = (w[:, 0] * e[ok, 1] - w[:, 1] * e[ok, 0]) / den[ok]
    s = (w[:, 0] * d[1] - w[:, 1] * d[0]) / den[ok]
    ts += [float(v) for v, u in zip(t, s) if 0.0 < v < 1.0 and -1e-9 <= u <= 1.0 + 1e-9]
    ts = np.unique(ts)
    mids = (ts[:-1] + ts[1:]) / 2
    ins = inside(poly, p + mids[:, None] * d)
    best, span = None, 0.0
    k = 0
    while k < len(mids):  # runs of inside pieces, the longest kept
        if ins[k]:
            j = k
            while j + 1 < len(mids) and ins[j + 1]:
                j += 1
            if ts[j + 1] - ts[k] > span:
                best, span = (float(ts[k]), float(ts[j + 1])), ts[j + 1] - ts[k]
            k = j + 1
        else:
            k += 1
    return best


def distance_to_edge(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Each of ``pts``' (M, 2) distance (m) to the nearest edge of ``poly``."""
    pts = np.atleast_2d(pts)
    a, b = poly, np.roll(poly, -1, axis=0)
    e = b - a
    t = np.clip(((pts[:, None, :] - a) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(pts[:, None, :] - (a + t[..., None] * e), axis=-1).min(axis=1)


def outside_m(poly: np.ndarray, p: np.ndarray, q: np.ndarray, tol_m: float = 0.5, step_m: float = 0.1) -> float:
    """How many metres of the straight line p-q lie outside ``poly`` (sampled every ``step_m``); 0 where no part lies
    more than ``tol_m`` outside (a line along an edge, as a pass cut at the boundary and the hop from its end)."""
    length = float(np.linalg.norm(q - p))
    n = max(1, int(np.ceil(length / step_m)))
    pts = p + ((np.arange(n) + 0.5) / n)[:, None] * (q - p)
    out = ~inside(poly, pts)
    if not out.any() or distance_to_edge(poly, pts[out]).max() <= tol_m:
        return 0.0
    return length * float(out.mean())
