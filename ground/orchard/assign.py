"""The apple map on the orchard's own rows and trees (issue 59): with an orchard layout (pomar.layout), each
apple belongs to the row whose strip it lies in and to that row's nearest tree, so ``rows.csv`` and ``trees.csv`` use
the grower's numbering, and the same tree keeps its ``row,tree`` from flight to flight.

A row's strip is its line from end to end (and half a tree spacing past its first and last trees, where they stand
that close to its ends; an apple's radius more, END_TOLERANCE_M), and half the way to the nearest other row on each
side (a lone row: any distance). An apple in no strip (past a row's ends, or in a part of the orchard the layout
leaves out) is outside: row 0 in apples.csv, in no row's count.
"""

from __future__ import annotations

import numpy as np

from pomar.layout import LayoutRow, row_ends_enu, tree_positions

#: The row number of an apple that lies in no row's strip.
OUTSIDE = 0
#: An apple whose centre lies this far past a strip's end (m) still belongs to it: about an apple's radius, an apple
#: that touches the row's end. A layout made from a map's rows (pomar.layout.layout_from_rows) ends each row at its
#: outermost apples, which would otherwise fall in or out by a rounding.
END_TOLERANCE_M = 0.04


def _lines(layout: list[LayoutRow], origin) -> list[dict]:
    """Each row's line in ENU (metres about ``origin``): start, unit direction, normal, length, its trees."""
    out = []
    for r in layout:
        a, b = row_ends_enu(r, origin)
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        trees = tree_positions(r, origin)
        along = (trees - a) @ u
        s = r.tree_spacing_m
        # where along the line its apples may lie: end to end, and half a spacing past its end trees
        span = (min(0.0, along[0] - s / 2), max(length, along[-1] + s / 2)) if len(along) else (0.0, length)
        out.append({"row": r, "a": a, "b": b, "u": u, "n": np.array([-u[1], u[0]]), "length": length,
                    "trees": trees, "along": along, "span": span})
    for i, L in enumerate(out):  # half the way to the nearest other row, measured from this row's middle
        mid = (L["a"] + L["b"]) / 2
        gaps = [abs((mid - M["a"]) @ M["n"]) for j, M in enumerate(out) if j != i]
        L["half_width"] = min(gaps) / 2 if gaps else np.inf
    return out


def _place(xy: np.ndarray, lines: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each apple's row number (OUTSIDE for none), its tree's index in that row (from 0) and its signed offset from
    the row's line (m, positive on the line's left, looking from its start to its end)."""
    n = len(xy)
    row_of = np.full(n, OUTSIDE, int)
    tree_of = np.zeros(n, int)
    signed = np.zeros(n)
    best = np.full(n, np.inf)  # |across| of the strip an apple was given to: the nearest line wins where strips meet
    for L in lines:
        s = L["row"].tree_spacing_m
        along, off = (xy - L["a"]) @ L["u"], (xy - L["a"]) @ L["n"]
        across = np.abs(off)
        inside = ((along >= L["span"][0] - END_TOLERANCE_M) & (along <= L["span"][1] + END_TOLERANCE_M)
                  & (across <= L["half_width"]) & (across < best))
        row_of[inside], best[inside], signed[inside] = L["row"].row, across[inside], off[inside]
        tree_of[inside] = np.clip(np.rint((along[inside] - L["along"][0]) / s), 0, len(L["along"]) - 1).astype(int)
    return row_of, tree_of, signed


#: An apple's side of its row, in apples.csv: on the row line's left or right, looking from its start to its end (the
#: face a camera on that side sees); empty outside every row, or without a layout.
LEFT, RIGHT = "left", "right"


def apple_places(table: dict, layout: list[LayoutRow], origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each apple of ``table`` (ENU) on the layout: its row number (OUTSIDE for none), its tree number (from 1; 0
    outside) and its side of the row (LEFT, RIGHT; "" outside): apples.csv's ``row``, ``tree`` and ``side``."""
    n = len(table["id"])
    xy = np.stack([table["x"], table["y"]], 1) if n else np.zeros((0, 2))
    row_of, tree_of, signed = _place(xy, _lines(layout, origin))
    inside = row_of != OUTSIDE
    side = np.where(~inside, "", np.where(signed >= 0, LEFT, RIGHT)).astype(object)
    return row_of, np.where(inside, tree_of + 1, 0), side


def orchard_rows(table: dict, layout: list[LayoutRow], origin) -> tuple[np.ndarray, list[dict], list[dict]]:
    """The apples of ``table`` (apple_table's columns, ENU) on the layout's rows and trees: (each apple's row number,
    OUTSIDE for none; the rows' records as rows_summary gives them, every row of the layout, in its order; the trees'
    records as trees_summary gives them, every tree)."""
    lines = _lines(layout, origin)
    n = len(table["id"])
    xy = np.stack([table["x"], table["y"]], 1) if n else np.zeros((0, 2))
    row_of, tree_of, _ = _place(xy, lines)
    z_all = float(np.median(table["z"])) if n else 0.0
    rows, trees = [], []
    for L in lines:
        r, sel = L["row"], row_of == L["row"].row
        z = float(np.median(table["z"][sel])) if sel.any() else z_all
        counts = np.bincount(tree_of[sel], minlength=len(L["along"]))
        rows.append({"row": r.row, "count": int(sel.sum()), "length_m": L["length"],
                     "apples_per_m": float(sel.sum() / L["length"]),
                     "start_x": float(L["a"][0]), "start_y": float(L["a"][1]), "end_x": float(L["b"][0]),
                     "end_y": float(L["b"][1]), "z": z, "start_lat": r.start[0], "start_lon": r.start[1],
                     "end_lat": r.end[0], "end_lon": r.end[1]})
        geo = np.asarray(origin.to_geodetic(np.column_stack([L["trees"], np.full(len(L["trees"]), z)])), float)
        trees += [{"row": r.row, "tree": i + 1, "along_m": float(L["along"][i]), "x": float(L["trees"][i, 0]),
                   "y": float(L["trees"][i, 1]), "lat": float(geo[i, 0]), "lon": float(geo[i, 1]),
                   "count": int(counts[i])} for i in range(len(L["along"]))]
    return row_of, rows, trees
