"""The map's own rows and trees, found from its apples where the grower gave no orchard layout: rows numbered 1..N
left to right looking along the rows (ground.apples.rows.direction_rows labels each apple), each row's line the span of
its apples, and trees cut every tree spacing from each row's start. A tree's number moves when the row's first apple
does: an orchard layout (ground.orchard.assign) numbers them for good."""

from __future__ import annotations

import numpy as np


def rows_summary(table: dict, direction: float, origin=None) -> list[dict]:
    """Per row: count, length along the row direction, apples per metre, and the row's line (ENU, and WGS84 when
    ``origin`` is given): its apples' span along the row (1st to 99th percentile when it has 20 or more, so that a
    stray estimate does not stretch it) at their median across-row offset and height."""
    out = []
    if not len(table["id"]):
        return out
    u = np.array([np.cos(direction), np.sin(direction)])
    n = np.array([-u[1], u[0]])
    xy = np.stack([table["x"], table["y"]], 1)
    along, across = xy @ u, xy @ n
    for r in np.unique(table["row"]):
        sel = table["row"] == r
        a = along[sel]
        lo, hi = np.percentile(a, [1, 99]) if sel.sum() >= 20 else (a.min(), a.max())
        c, z = np.median(across[sel]), np.median(table["z"][sel])
        ends = np.array([[*(lo * u + c * n), z], [*(hi * u + c * n), z]])
        geo = np.asarray(origin.to_geodetic(ends)) if origin is not None else np.full((2, 3), np.nan)
        length = float(np.ptp(a))
        out.append({"row": int(r), "count": int(sel.sum()), "length_m": length,
                    "apples_per_m": float(sel.sum() / length) if length > 0 else float("nan"),
                    "start_x": float(ends[0, 0]), "start_y": float(ends[0, 1]), "end_x": float(ends[1, 0]),
                    "end_y": float(ends[1, 1]), "z": float(z), "start_lat": float(geo[0, 0]),
                    "start_lon": float(geo[0, 1]), "end_lat": float(geo[1, 0]), "end_lon": float(geo[1, 1])})
    return out


def trees_summary(table: dict, rows: list[dict], direction: float, spacing_m: float, origin=None) -> list[dict]:
    """Per tree: each row's line (rows_summary) cut into segments ``spacing_m`` long from its start; an apple
    belongs to the segment its position along the row falls in (those beyond the line's ends to the end segments)."""
    if spacing_m <= 0:
        raise ValueError(f"tree spacing must be > 0 m, got {spacing_m}")
    out = []
    u = np.array([np.cos(direction), np.sin(direction)])
    xy = np.stack([table["x"], table["y"]], 1) if len(table["id"]) else np.zeros((0, 2))
    for r in rows:
        start = np.array([r["start_x"], r["start_y"]])
        n = max(1, int(np.ceil(r["length_m"] / spacing_m - 1e-9)))
        sel = np.asarray(table["row"]) == r["row"]
        k = np.clip(np.floor((xy[sel] - start) @ u / spacing_m), 0, n - 1).astype(int)
        counts = np.bincount(k, minlength=n)
        along = (np.arange(n) + 0.5) * spacing_m
        centres = start + along[:, None] * u
        geo = (np.asarray(origin.to_geodetic(np.column_stack([centres, np.full(n, r.get("z", 0.0))])))
               if origin is not None else np.full((n, 3), np.nan))
        out += [{"row": r["row"], "tree": i + 1, "along_m": float(along[i]), "x": float(centres[i, 0]),
                 "y": float(centres[i, 1]), "lat": float(geo[i, 0]), "lon": float(geo[i, 1]), "count": int(counts[i])}
                for i in range(n)]
    return out
