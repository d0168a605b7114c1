"""Procedural orchard: rows of trees whose canopies are clouds of leaf splats, apples, and a ground texture.

Everything is built from the config and a seed, so the same config gives the same orchard.
Geometry is generated in the *orchard frame* (x across the rows, y along them, z up, metres,
rows centred on 0) and rotated into ENU by the row azimuth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pomar.fruit import apple_mass_kg
from sim.config import SimConfig

LEAF, APPLE, TRUNK = 0, 1, 2

# RGB base colours (0..1) of each variety: Gala reddish, Fuji greener-yellow with a blush.
VARIETY_COLOURS = {
    "gala": ((0.78, 0.16, 0.10), (0.90, 0.38, 0.16)),
    "fuji": ((0.62, 0.62, 0.26), (0.80, 0.42, 0.28)),
}


@dataclass
class Scene:
    """Render primitives (spherical splats) in ENU plus the ground texture (orchard frame)."""

    pos: np.ndarray  # (N, 3) float32, ENU
    radius: np.ndarray  # (N,) float32, metres
    colour: np.ndarray  # (N, 3) float32, RGB 0..1, leaves already lit
    kind: np.ndarray  # (N,) int8: LEAF, APPLE, TRUNK
    apple_index: np.ndarray  # (N,) int32: row of `apples` for APPLE primitives, else -1
    apples: dict  # apple_id, row, tree, variety, xyz (ENU), radius_m, mass_kg
    ground: np.ndarray  # (H, W, 3) uint8 RGB texture, row 0 at y_max
    ground_extent: tuple[float, float, float, float]  # x_min, x_max, y_min, y_max (orchard frame)
    ground_res: float
    orchard_to_enu: np.ndarray  # (2, 2) rotation of horizontal coordinates
    sun_enu: np.ndarray  # unit vector towards the sun
    row_x: np.ndarray  # across-row position of each row (orchard frame)
    #: Every tree: row and tree (1.. from the row's start, the orchard's -y end), its canopy centre (ENU), and its full
    #: load (the apples it carries, after the overlapping ones are taken out) and their mass.
    trees: dict | None = None


#: The simulator's mass of an apple: a sphere of its diameter at a whole apple's density (its flesh holds a fifth or so
#: of air; 0.70-0.85 g/cm3, so it floats). A truth for scoring, not a cultivar's mass-diameter relation.


def orchard_to_enu_matrix(azimuth_deg: float) -> np.ndarray:
    a = np.radians(azimuth_deg)
    # columns: across-row unit vector, along-row unit vector, in (east, north)
    return np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])


def sun_vector(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])


def _unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _hsv_to_rgb(h, s, v):
    hsv = np.stack([h * 179.0, s * 255.0, v * 255.0], axis=-1).astype(np.uint8)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0].astype(np.float32) / 255.0


def _noise(rng, shape, cell_px):
    """Smooth value noise of zero mean, unit-ish amplitude, with features about cell_px wide."""
    h, w = shape
    small = rng.normal(size=(max(2, int(h / cell_px) + 2), max(2, int(w / cell_px) + 2))).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _ground_texture(cfg: SimConfig, rng, row_x, sun_enu, to_enu):
    o = cfg.orchard
    res = cfg.render.ground_resolution_m
    x_min, x_max = row_x.min() - 14.0, row_x.max() + 14.0
    y_min, y_max = -o.row_length_m / 2 - 16.0, o.row_length_m / 2 + 16.0
    w, h = int(np.ceil((x_max - x_min) / res)), int(np.ceil((y_max - y_min) / res))
    xs = x_min + (np.arange(w) + 0.5) * res
    # grass: multi-octave noise in hue and value
    n = sum(_noise(rng, (h, w), c / res) * a for c, a in ((3.0, 0.5), (0.6, 0.3), (0.12, 0.25), (0.04, 0.2)))
    blades = _noise(rng, (h, w), 0.015 / res) * 0.25
    grass_h = np.clip(0.24 + 0.03 * n, 0.15, 0.33)  # hue in [0, 1): greens / yellows
    grass_s = np.clip(0.55 + 0.12 * n, 0.2, 0.9)
    grass_v = np.clip(0.42 + 0.10 * n + blades, 0.1, 0.9)
    soil_n = sum(_noise(rng, (h, w), c / res) * a for c, a in ((1.0, 0.5), (0.1, 0.35), (0.03, 0.3)))
    soil_h = np.full((h, w), 0.07, np.float32)
    soil_s = np.clip(0.45 + 0.08 * soil_n, 0.2, 0.8)
    soil_v = np.clip(0.38 + 0.12 * soil_n, 0.1, 0.8)
    # soil strip under each row (herbicide strip), edges broken by noise
    dist = np.min(np.abs(xs[None, :] - row_x[:, None]), axis=0)[None, :]
    strip = np.clip((0.75 + 0.25 * _noise(rng, (h, w), 0.5 / res) - dist) / 0.15, 0, 1)
    hh = grass_h * (1 - strip) + soil_h * strip
    ss = grass_s * (1 - strip) + soil_s * strip
    vv = grass_v * (1 - strip) + soil_v * strip
    # canopy shadows: a band beside each row, away from the sun
    sun_orch = to_enu.T @ sun_enu[:2]
    shift = -sun_orch[0] * 1.9 / max(np.tan(np.radians(cfg.render.sun_elevation_deg)), 0.2)
    sdist = np.min(np.abs(xs[None, :] - (row_x[:, None] + shift)), axis=0)[None, :]
    shadow = np.clip((o.canopy_width_m / 2 + 0.15 * _noise(rng, (h, w), 0.3 / res) - sdist) / 0.2, 0, 1)
    vv = vv * (1 - 0.45 * shadow)
    hsv = np.stack([hh * 179, ss * 255, vv * 255], axis=-1).clip(0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    return rgb, (x_min, x_max, y_min, y_max)


def _without_interpenetration(xyz: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Mask of the apples to keep: of two apples whose spheres overlap, the later one goes.

    Real apples do not pass through each other; two drawn that way would be one blob in
    the image but two apples in the truth.
    """
    keep = np.ones(len(xyz), bool)
    if len(xyz) < 2:
        return keep
    pairs = cKDTree(xyz).query_pairs(2.0 * float(radius.max()), output_type="ndarray")
    d = np.linalg.norm(xyz[pairs[:, 0]] - xyz[pairs[:, 1]], axis=1)
    pairs = pairs[d < radius[pairs[:, 0]] + radius[pairs[:, 1]]]
    for i, j in sorted(map(tuple, pairs)):  # i < j in every pair
        if keep[i]:
            keep[j] = False
    return keep


def build_scene(cfg: SimConfig) -> Scene:
    rng = np.random.default_rng(cfg.seed)
    o, a = cfg.orchard, cfg.apples
    to_enu = orchard_to_enu_matrix(o.row_azimuth_deg)
    sun = sun_vector(cfg.render.sun_elevation_deg, cfg.render.sun_azimuth_deg)
    sun_orch = np.concatenate([to_enu.T @ sun[:2], sun[2:]])
    row_x = (np.arange(o.rows) - (o.rows - 1) / 2.0) * o.row_spacing_m
    n_trees = max(1, int(round(o.row_length_m / o.tree_spacing_m)))
    tree_y = (np.arange(n_trees) - (n_trees - 1) / 2.0) * o.tree_spacing_m

    pos, rad, col, kind, aidx = [], [], [], [], []
    apples = {"apple_id": [], "row": [], "tree": [], "variety": [], "xyz": [], "radius_m": []}
    trees = {"row": [], "tree": [], "xyz": []}
    half_h = (o.canopy_height_m - o.canopy_base_m) / 2.0
    zc = o.canopy_base_m + half_h
    for r, x_r in enumerate(row_x):
        variety = o.varieties[r % len(o.varieties)]
        vcol = VARIETY_COLOURS.get(variety.lower(), VARIETY_COLOURS["gala"])
        row_hue = rng.uniform(-0.02, 0.02)
        for t_i, y_t in enumerate(tree_y):
            c = np.array([x_r + rng.normal(0, 0.05), y_t + rng.normal(0, 0.06), zc + rng.normal(0, 0.08)])
            trees["row"].append(r + 1)
            trees["tree"].append(t_i + 1)
            trees["xyz"].append(c)
            axes = np.array([o.canopy_width_m / 2, o.tree_spacing_m * 0.68, half_h]) * rng.uniform(0.85, 1.15, 3)
            k = rng.normal(size=(4, 3)) * 2.5
            ph = rng.uniform(0, 2 * np.pi, 4)

            def lump(d):
                return 1.0 + 0.07 * np.cos(d @ k.T + ph).sum(axis=1) / np.sqrt(2)

            # leaves, mostly on the canopy surface, some inside
            n = o.leaves_per_tree
            d = _unit_vectors(rng, n)
            s = np.clip(1.0 - np.abs(rng.normal(0, 0.10, n)), 0.3, 1.0)
            p = c + (s * lump(d))[:, None] * axes * d
            normal = d / axes
            normal = normal / np.linalg.norm(normal, axis=1, keepdims=True) + rng.normal(0, 0.5, (n, 3))
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            lit = cfg.render.ambient + (1 - cfg.render.ambient) * np.clip(normal @ sun_orch, 0, 1)
            lit *= 0.55 + 0.45 * s**3  # leaves deep in the canopy are in its shade
            hue = np.clip(0.27 + row_hue + rng.normal(0, 0.025, n), 0.15, 0.40)
            rgb = _hsv_to_rgb(hue, rng.uniform(0.45, 0.85, n), rng.uniform(0.35, 0.75, n)) * lit[:, None]
            pos.append(p)
            rad.append(o.leaf_radius_m * rng.uniform(0.7, 1.3, n))
            col.append(rgb)
            kind.append(np.full(n, LEAF, np.int8))
            aidx.append(np.full(n, -1, np.int32))
            # trunk
            tz = np.linspace(0.05, o.canopy_base_m + 0.2, 8)
            pos.append(np.stack([np.full(8, c[0]), np.full(8, c[1]), tz], axis=1))
            rad.append(np.full(8, 0.06))
            col.append(np.tile(np.array([[0.30, 0.22, 0.15]], np.float32), (8, 1)))
            kind.append(np.full(8, TRUNK, np.int8))
            aidx.append(np.full(8, -1, np.int32))
            # apples, mostly on the sides and lower half of the canopy
            mean = a.per_tree * (a.row_load[r % len(a.row_load)] if a.row_load else 1.0)
            if a.tree_vigour_cv > 0:  # a draw only when asked: an orchard without it is drawn as before
                k_shape = 1.0 / a.tree_vigour_cv ** 2
                mean *= rng.gamma(k_shape, 1.0 / k_shape)
            m = rng.poisson(mean)
            if m == 0:
                continue
            d = _unit_vectors(rng, 4 * m + 8)
            d = d[(d[:, 2] > -0.7) & (d[:, 2] < 0.6)][:m]
            m = len(d)
            s = rng.uniform(a.depth_min, a.depth_max, m)
            p = c + (s * lump(d))[:, None] * axes * d
            lo, hi = (a.row_diameter_m[r % len(a.row_diameter_m)] if a.row_diameter_m
                      else (a.diameter_min_m, a.diameter_max_m))
            radius = rng.uniform(lo, hi, m) / 2.0
            mix = rng.uniform(0, 1, (m, 1))
            base = np.array(vcol[0]) * (1 - mix) + np.array(vcol[1]) * mix
            base = base * rng.uniform(0.9, 1.1, (m, 1))
            first = len(apples["apple_id"])
            for j in range(m):
                apples["apple_id"].append(first + j)
                apples["row"].append(r + 1)
                apples["tree"].append(t_i + 1)
                apples["variety"].append(variety)
                apples["xyz"].append(p[j])
                apples["radius_m"].append(radius[j])
            pos.append(p)
            rad.append(radius)
            col.append(base.astype(np.float32))
            kind.append(np.full(m, APPLE, np.int8))
            aidx.append(np.arange(first, first + m, dtype=np.int32))

    pos_o = np.concatenate(pos)
    rad_a, col_a, kind_a, aidx_a = (np.concatenate(v) for v in (rad, col, kind, aidx))
    xyz_o = np.array(apples["xyz"]).reshape(-1, 3)
    r_apple = np.array(apples["radius_m"])
    keep_apple = _without_interpenetration(xyz_o, r_apple)
    # drop the primitives of removed apples and renumber the rest; no draw from rng here,
    # so the ground (drawn next) is the same as without the removal
    keep_prim = (kind_a != APPLE) | keep_apple[np.maximum(aidx_a, 0)]
    new_index = np.cumsum(keep_apple) - 1
    aidx_a = np.where(kind_a == APPLE, new_index[np.maximum(aidx_a, 0)], -1).astype(np.int32)
    pos_o, rad_a, col_a, kind_a, aidx_a = (v[keep_prim] for v in (pos_o, rad_a, col_a, kind_a, aidx_a))
    xyz_o = xyz_o[keep_apple]
    pos_enu = np.column_stack([pos_o[:, :2] @ to_enu.T, pos_o[:, 2]]).astype(np.float32)
    # each tree's full load: the apples kept on it (no draw from rng)
    a_row = np.array(apples["row"], np.int64)[keep_apple]
    a_tree = np.array(apples["tree"], np.int64)[keep_apple]
    variety = np.array(apples["variety"])[keep_apple]
    a_mass = np.zeros(len(variety))
    for v in np.unique(variety):  # the mass of each apple of its diameter and cultivar (pomar.fruit)
        a_mass[variety == v] = apple_mass_kg(2.0 * r_apple[keep_apple][variety == v], v)
    t_row, t_tree = np.array(trees["row"], np.int64), np.array(trees["tree"], np.int64)
    key = (a_row - 1) * n_trees + (a_tree - 1)
    t_key = (t_row - 1) * n_trees + (t_tree - 1)
    load = np.bincount(key, minlength=len(t_key))[t_key] if len(key) else np.zeros(len(t_key), int)
    mass = np.bincount(key, weights=a_mass, minlength=len(t_key))[t_key] if len(key) else np.zeros(len(t_key))
    t_xyz = np.array(trees["xyz"]).reshape(-1, 3)
    ground, extent = _ground_texture(cfg, rng, row_x, sun, to_enu)
    return Scene(
        pos=pos_enu,
        radius=rad_a.astype(np.float32),
        colour=col_a.astype(np.float32),
        kind=kind_a,
        apple_index=aidx_a,
        apples={
            "apple_id": np.arange(len(xyz_o), dtype=np.int64),
            "row": a_row,
            "tree": a_tree,
            "variety": np.array(apples["variety"], dtype=str)[keep_apple],
            "xyz": np.column_stack([xyz_o[:, :2] @ to_enu.T, xyz_o[:, 2]]),
            "radius_m": r_apple[keep_apple],
            "mass_kg": a_mass,
        },
        ground=ground,
        ground_extent=extent,
        ground_res=cfg.render.ground_resolution_m,
        orchard_to_enu=to_enu,
        sun_enu=sun,
        row_x=row_x,
        trees={"row": t_row, "tree": t_tree, "xyz": np.column_stack([t_xyz[:, :2] @ to_enu.T, t_xyz[:, 2]]),
               "apples": load, "mass_kg": mass},
    )
