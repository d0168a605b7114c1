"""What each tree's canopy showed the camera (issue 59), from the geometry the ground has (and, before a flight, what
a flight plan's cameras will show it: pomar.plan, issue 72): the cameras' poses, the
rows' lines, the trees' positions and the apples' heights, with no threshold fitted to flights.

A row is a hedge: its canopy's two faces stand ``half_depth`` either side of the row's line, from the bottom to the top
of its apples (their 5th and 95th height percentiles; its half-depth the 75th percentile of their distances from the
line). Each tree's share of the two faces is sampled at SURFACE_POINTS points a side. A point is seen in a frame where
- it lies in front of the camera and inside its image;
- its face turns towards the camera (a face shows nothing from behind);
- no other row's canopy stands in the way (the ray from the camera crosses another row's line below its top);
- an apple there reaches the detector at least as large as it finds apples reliably (the drone's
  ``min_apple_radius_px``, at the frame's detector scale; no limit where the drone does not say).
A tree's coverage is the share of its points seen in at least one frame: 1 where both sides were seen whole, 0.5 for
one side, 0 for a tree never seen. Beside it: the sides seen, the frames that saw it, and the median range, angle
(from the face's normal) and apple radius at the detector over those frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Points sampled on each side of a tree: ALONG across its share of the row, by HEIGHTS up the canopy.
ALONG, HEIGHTS = 3, 3
SURFACE_POINTS = ALONG * HEIGHTS
#: The frames looked at: at most this many, evenly spread (neighbouring frames see nearly the same).
MAX_FRAMES = 400
#: Columns added to trees.csv (and, averaged over a row's trees, coverage to rows.csv).
#: ``cover_left``, ``cover_right``: the share seen of each face, on the row line's left and right looking from its start
#: to its end (``coverage`` is their mean): where two flights of one orchard are combined, each side's apples come from
#: the flight that saw that side best.
COVERAGE_COLUMNS = ["coverage", "cover_left", "cover_right", "sides_seen", "frames_seen", "range_m", "angle_deg",
                    "apple_px"]
#: An apple's radius (m) where the map has none measured: the middle of the 60-90 mm of dessert apples.
DEFAULT_APPLE_RADIUS_M = 0.0375


@dataclass
class Sight:
    """How the drone saw: its camera, and what its detector finds (pomar.camera.Camera; the detector's smallest
    reliable apple radius in its own pixels, 0 when not said; each frame's detector scale)."""
    camera: object
    min_px: float = 0.0
    scales: dict = field(default_factory=dict)


#: A hedge where no apple measures one (a flight plan's, before any flight): the faces 0.5 m either side of the line
#: (tall-spindle and super-spindle canopies stand 0.6-1.2 m wide), from 0.8 m to 3.0 m (pomar.apple_scale's
#: trellised trees).
DEFAULT_HEDGE = {"half_depth": 0.5, "bottom": 0.8, "top": 3.0}


def _canopies(apples: dict, rows: list[dict], default: dict | None = None) -> list[dict | None]:
    """Each row's hedge (line, faces' half-depth, bottom, top) from its own apples; a row with fewer than 5 takes the
    median hedge of the rows that have them (its canopy is the orchard's, its apples unseen); where no row has 5,
    ``default`` (a hedge's half_depth, bottom and top) or None for every row."""
    xy_all = np.stack([apples["x"], apples["y"]], 1) if len(apples["id"]) else np.zeros((0, 2))
    row_of = np.asarray(apples["row"]) if len(apples["id"]) else np.zeros(0)
    z_all = np.asarray(apples["z"], float) if len(apples["id"]) else np.zeros(0)
    out = []
    for r in rows:
        a, b = np.array([r["start_x"], r["start_y"]]), np.array([r["end_x"], r["end_y"]])
        length = float(np.linalg.norm(b - a))
        if length <= 0:
            out.append(None)
            continue
        u = (b - a) / length
        c = {"a": a, "u": u, "n": np.array([-u[1], u[0]]), "length": length}
        sel = row_of == r["row"]
        if sel.sum() >= 5:
            across = np.abs((xy_all[sel] - a) @ c["n"])
            c.update(half_depth=float(np.percentile(across, 75)), bottom=float(np.percentile(z_all[sel], 5)),
                     top=float(np.percentile(z_all[sel], 95)))
        out.append(c)
    known = [c for c in out if c is not None and "top" in c]
    if not known and default is None:
        return [None] * len(rows)
    pooled = ({k: float(np.median([c[k] for c in known])) for k in ("half_depth", "bottom", "top")} if known
              else dict(default))
    return [None if c is None else {**pooled, **c} for c in out]


def _surface(trees: list[dict], rows: list[dict], canopy: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, 2, SURFACE_POINTS, 3) points on each tree's two faces, (T, 2, 2) the faces' outward normals (horizontal),
    (T,) each tree's row index (-1: no canopy known)."""
    index = {r["row"]: i for i, r in enumerate(rows)}
    T = len(trees)
    X = np.full((T, 2, SURFACE_POINTS, 3), np.nan)
    N = np.zeros((T, 2, 2))
    row_of = np.full(T, -1)
    for k, t in enumerate(trees):
        i = index.get(t["row"])
        c = canopy[i] if i is not None else None
        if c is None:
            continue
        row_of[k] = i
        spacing = (trees[k + 1]["along_m"] - t["along_m"] if k + 1 < T and trees[k + 1]["row"] == t["row"]
                   else t["along_m"] - trees[k - 1]["along_m"] if k > 0 and trees[k - 1]["row"] == t["row"] else 1.0)
        centre = np.array([t["x"], t["y"]])
        along = (np.arange(ALONG) + 0.5) / ALONG - 0.5  # the tree's share of the row, -1/2..1/2 of a spacing
        height = c["bottom"] + (np.arange(HEIGHTS) + 0.5) / HEIGHTS * (c["top"] - c["bottom"])
        g_along, g_height = (g.ravel() for g in np.meshgrid(along * spacing, height, indexing="ij"))
        for s, sign in enumerate((1.0, -1.0)):
            xy = centre + sign * c["half_depth"] * c["n"] + g_along[:, None] * c["u"]
            X[k, s] = np.column_stack([xy, g_height])
            N[k, s] = sign * c["n"]
    return X, N, row_of


def _blocked(C: np.ndarray, X: np.ndarray, own: np.ndarray, canopy: list) -> np.ndarray:
    """(K,) whether each ray from a camera centre (C: K x 3) to a point (X: K x 3, of row index ``own``) crosses another
    row's line below that row's canopy top."""
    out = np.zeros(len(C), bool)
    for i, c in enumerate(canopy):
        if c is None:
            continue
        dC = (C[:, :2] - c["a"]) @ c["n"]  # signed distances to row i's line
        dX = (X[:, :2] - c["a"]) @ c["n"]
        crosses = (np.sign(dC) != np.sign(dX)) & (own != i)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(crosses, dC / (dC - dX), 0.0)
        Q = C + t[:, None] * (X - C)
        along = (Q[:, :2] - c["a"]) @ c["u"]
        out |= crosses & (along >= 0) & (along <= c["length"]) & (Q[:, 2] < c["top"])
    return out


def tree_coverage(trees: list[dict], rows: list[dict], apples: dict, cams: dict, sight: Sight,
                  default_hedge: dict | None = None) -> list[dict]:
    """COVERAGE_COLUMNS for each tree of ``trees`` (trees.csv's records) on ``rows`` (rows.csv's), with the map's
    ``apples`` (apples.csv's columns, ENU) and cameras (``cams``: poses.csv's columns, ENU-to-camera quaternions).
    The range, angle and apple radius are medians over every (frame, point) seen. ``default_hedge``: the canopy where
    no row has apples enough to measure it (a plan's: DEFAULT_HEDGE)."""
    from scipy.spatial.transform import Rotation

    none = {"coverage": float("nan"), "cover_left": float("nan"), "cover_right": float("nan"), "sides_seen": 0, "frames_seen": 0, "range_m": float("nan"),
            "angle_deg": float("nan"), "apple_px": float("nan")}
    canopy = _canopies(apples, rows, default_hedge)
    if not trees or not len(cams["frame"]) or all(c is None for c in canopy):
        return [dict(none) for _ in trees]
    X, N, row_of = _surface(trees, rows, canopy)
    T = len(trees)
    radius = np.asarray(apples.get("radius_m", []), float)
    radius_m = float(np.nanmedian(radius)) if np.isfinite(radius).any() else DEFAULT_APPLE_RADIUS_M
    step = max(1, int(np.ceil(len(cams["frame"]) / MAX_FRAMES)))
    pick = np.arange(0, len(cams["frame"]), step)
    frames = np.asarray(cams["frame"])[pick]
    C = np.column_stack([cams["x"], cams["y"], cams["z"]])[pick]
    R = Rotation.from_quat(np.column_stack([cams["qx"], cams["qy"], cams["qz"], cams["qw"]])[pick]).as_matrix()
    scale = np.array([sight.scales.get(int(f), 1.0) for f in frames], float)
    cam = sight.camera
    P = X.reshape(-1, 3)  # (M, 3), M = T * 2 * SURFACE_POINTS
    normal = np.repeat(N.reshape(-1, 2), SURFACE_POINTS, axis=0)
    own = np.repeat(row_of, 2 * SURFACE_POINTS)
    valid = np.isfinite(P).all(1)
    pairs = []  # (frame index, point, range, cos of the angle, apple px) of every point seen
    for lo in range(0, len(C), 50):
        Cf, Rf, sf = C[lo:lo + 50], R[lo:lo + 50], scale[lo:lo + 50]
        d = P[None] - Cf[:, None]  # (F, M, 3) camera to point, ENU
        xc = np.einsum("fij,fmj->fmi", Rf, d)
        z = xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * xc[..., 0] / z + cam.cx
            v = cam.fy * xc[..., 1] / z + cam.cy
            px = cam.fx * radius_m / z * sf[:, None]
        facing = np.einsum("fmk,mk->fm", -d[..., :2], normal)
        ok = valid[None] & (z > 0) & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height) & (facing > 0)
        if sight.min_px > 0:
            ok &= px >= sight.min_px
        f, m = np.nonzero(ok)
        keep = ~_blocked(Cf[f], P[m], own[m], canopy)  # the costly test only for what the others let through
        f, m = f[keep], m[keep]
        dist = np.linalg.norm(d[f, m], axis=1)
        pairs.append(np.column_stack([f + lo, m, dist, facing[f, m] / dist, px[f, m]]))
    seen_at = np.concatenate(pairs) if pairs else np.zeros((0, 5))
    tree = (seen_at[:, 1] // (2 * SURFACE_POINTS)).astype(int)
    seen = np.zeros(len(P), bool)
    seen[seen_at[:, 1].astype(int)] = True
    seen = seen.reshape(T, 2, SURFACE_POINTS)
    order = np.argsort(tree, kind="stable")
    bounds = np.searchsorted(tree[order], np.arange(T + 1))
    out = []
    for k in range(T):
        if row_of[k] < 0:
            out.append(dict(none))
            continue
        mine = seen_at[order[bounds[k]:bounds[k + 1]]]
        med = np.median(mine[:, 2:], 0) if len(mine) else np.full(3, np.nan)
        out.append({"coverage": float(seen[k].mean()), "cover_left": float(seen[k, 0].mean()),
                    "cover_right": float(seen[k, 1].mean()), "sides_seen": int(seen[k].any(1).sum()),
                    "frames_seen": int(len(np.unique(mine[:, 0])) * step), "range_m": float(med[0]),
                    "angle_deg": float(np.degrees(np.arccos(np.clip(med[1], -1, 1)))), "apple_px": float(med[2])})
    return out


def flight_coverage(trees: list[dict]) -> dict | None:
    """The flight's coverage (report.json's ``orchard.coverage``): its trees' mean, how many were seen at all and on
    both sides; None before any is known."""
    c = np.array([t.get("coverage", np.nan) for t in trees], float)
    if not np.isfinite(c).any():
        return None
    known = c[np.isfinite(c)]
    return {"mean": float(known.mean()), "trees": int(len(known)), "trees_seen": int((known > 0).sum()),
            "trees_both_sides": int(sum(t.get("sides_seen", 0) == 2 for t in trees))}


def row_coverage(rows: list[dict], trees: list[dict]) -> None:
    """Each row's coverage (into its record): the mean of its trees' (NaN where none is known)."""
    for r in rows:
        c = [t["coverage"] for t in trees if t["row"] == r["row"] and np.isfinite(t["coverage"])]
        r["coverage"] = float(np.mean(c)) if c else float("nan")
