"""The orchard layout a grower of a simulated orchard would have (issue 59): one line a row, its ends and its trees'
spacing, fitted to the truth's trees (truth/trees.csv), numbered as the truth numbers them, so that a ground given it
(``--orchard``) writes trees.csv with the truth's ``row,tree`` and the sample counts of ``python -m sim counts`` match.

    python -m sim layout FLIGHT_DIR --out orchard.csv

Each row's line goes through its trees' canopy centres (their principal axis, from tree 1 to the last); the spacing is
the slope of their positions along it against their numbers, and the row's ends lie half a spacing beyond its first
and last trees (the planted line, whatever the canopies' jitter).
"""

from __future__ import annotations

import numpy as np

from pomar.layout import LayoutRow


def truth_layout(flight) -> list[LayoutRow]:
    """The layout of a flight directory (pomar.flight.FlightDir) from its trees' truth; rows with fewer than two trees
    have no line and are left out."""
    t = flight.truth_trees()
    a = flight.truth_apples()
    cultivar = {int(r): str(v) for r, v in zip(a["row"], a["variety"])}  # each row's one variety
    return _fit_rows(t, np.stack([t["x"], t["y"]], 1), cultivar, flight.origin())


def config_layout(cfg) -> list[LayoutRow]:
    """The layout of a simulator config's orchard (sim.config.SimConfig), before any flight: its scene's trees, as
    :func:`truth_layout` reads them from a rendered flight (the same seed gives the same orchard)."""
    from pomar.geo import Origin
    from sim.orchard import build_scene

    scene = build_scene(cfg)
    tr, a = scene.trees, scene.apples
    cultivar = {int(r): str(v) for r, v in zip(a["row"], a["variety"])}
    origin = Origin(cfg.origin.lat, cfg.origin.lon, cfg.origin.alt)
    return _fit_rows({"row": np.asarray(tr["row"]), "tree": np.asarray(tr["tree"])}, np.asarray(tr["xyz"])[:, :2],
                     cultivar, origin)


def _fit_rows(t: dict, xy: np.ndarray, cultivar: dict, origin) -> list[LayoutRow]:
    out = []
    for row in np.unique(t["row"].astype(int)):
        sel = t["row"].astype(int) == row
        number, p = t["tree"][sel].astype(int), xy[sel]
        if len(p) < 2:
            continue
        c = p.mean(0)
        u = np.linalg.svd(p - c)[2][0]
        if (p[np.argmax(number)] - p[np.argmin(number)]) @ u < 0:
            u = -u  # from tree 1 to the last
        spacing, a0 = np.polyfit(number - 1.0, (p - c) @ u, 1)  # along = a0 + spacing * (tree - 1)
        ends = np.array([c + (a0 - spacing / 2) * u, c + (a0 + (number.max() - 0.5) * spacing) * u])
        geo = np.asarray(origin.to_geodetic(np.column_stack([ends, np.zeros(2)])), float)
        out.append(LayoutRow(int(row), (geo[0, 0], geo[0, 1]), (geo[1, 0], geo[1, 1]), round(float(spacing), 4),
                             round(float(spacing) / 2, 4), cultivar=cultivar.get(int(row), "")))
    return out
