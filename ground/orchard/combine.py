"""Several flights of one orchard as one map (issue 72): the maps of a flight plan's split flights, or of a grower's
flights one per side of the rows, combined into one ``rows.csv``/``trees.csv`` by the layout's numbering.

Each map was replayed with the same ``--orchard`` layout, so each apple has its row, tree and side of the row
(apples.csv), and each tree the share of each face its flight saw (trees.csv's ``cover_left``, ``cover_right``,
pomar.coverage). A face seen by two flights shows the same apples twice, and their positions, each flight's GPS, lie
a metre apart: matching them one by one would count some twice. So each face of each tree takes its apples from one
flight, the one that saw that face best (the most of it; on a tie, the earlier map), and no apple is counted twice.
The tree's coverage is that of the union: each face's best share, their mean.

The combined folder holds apples.csv (the chosen apples, each on the layout: its own map shifted as it was for its
rows, in the first map's ENU frame), rows.csv, trees.csv and a report.json naming the maps and which faces each gave;
``ground choose-trees`` and ``ground load`` take it as they take one flight's map.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from ground.orchard.assign import LEFT, RIGHT
from pomar.cli import InputError
from pomar.coverage import flight_coverage, row_coverage

#: The columns a map needs to be combined: its apples on the layout's trees and sides, its trees' faces seen.
APPLE_NEEDS = ("id", "x", "y", "z", "lat", "lon", "alt", "row", "tree", "side", "radius_m")
TREE_NEEDS = ("row", "tree", "count", "coverage", "cover_left", "cover_right")


def _read_csv(path: Path, need) -> list[dict]:
    try:
        with open(path, newline="") as f:
            rd = csv.DictReader(f)
            rows = list(rd)
            fields = rd.fieldnames or []
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (give the folders of finished maps)") from None
    lacking = [c for c in need if c not in fields]
    if lacking:
        raise InputError(f"{path}: no column {', '.join(lacking)} (a map of an older version, or one replayed without "
                         "--orchard: replay it with the orchard's layout)")
    return rows


def read_map(folder: Path) -> dict:
    """One finished map, checked for what combining needs: its apples, trees, rows and report."""
    folder = Path(folder)
    report_path = folder / "report.json"
    try:
        report = json.loads(report_path.read_text())
    except FileNotFoundError:
        raise InputError(f"{report_path}: no such file (give the folders of finished maps)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{report_path}: not JSON ({e})") from None
    orchard = report.get("orchard") or {}
    if orchard.get("numbering") != "layout":
        raise InputError(f"{report_path}: this map's trees are not numbered by an orchard layout (replay it with "
                         "--orchard, the same layout for every flight)")
    origin = (report.get("map") or {}).get("origin")
    if not origin:
        raise InputError(f"{report_path}: the map has no origin (it was never georeferenced)")
    return {"folder": folder, "report": report, "origin": origin,
            "apples": _read_csv(folder / "apples.csv", APPLE_NEEDS),
            "trees": _read_csv(folder / "trees.csv", TREE_NEEDS),
            "rows": _read_csv(folder / "rows.csv", ("row", "length_m", "start_x", "start_y", "end_x", "end_y"))}


def _num(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _same_layout(maps: list[dict]) -> None:
    """Every map's trees, numbered the same and standing where the first map's do (within 0.1 m): one layout."""
    from pomar.geo import Origin

    first = {(int(t["row"]), int(t["tree"])): (_num(t.get("lat")), _num(t.get("lon"))) for t in maps[0]["trees"]}
    o = maps[0]["origin"]
    origin = Origin(o["lat"], o["lon"], o.get("alt") or 0.0)

    def enu(ll):
        return origin.to_enu(ll[0], ll[1], origin.alt)[:2]

    for m in maps[1:]:
        mine = {(int(t["row"]), int(t["tree"])): (_num(t.get("lat")), _num(t.get("lon"))) for t in m["trees"]}
        if set(mine) != set(first):
            raise InputError(f"{m['folder'] / 'trees.csv'}: its trees are not those of {maps[0]['folder']} (another "
                             "layout): replay every flight with the same --orchard file")
        far = [k for k in first if np.linalg.norm(enu(mine[k]) - enu(first[k])) > 0.1]
        if far:
            raise InputError(f"{m['folder'] / 'trees.csv'}: row {far[0][0]} tree {far[0][1]} stands elsewhere than in "
                             f"{maps[0]['folder']} (another layout): replay every flight with the same --orchard file")


def _to_first(m: dict, origin0: dict) -> np.ndarray:
    """The map's apples in the first map's ENU frame, shifted onto the layout as its rows were (report.json's
    ``orchard.layout_shift``)."""
    from pomar.geo import Origin

    a = m["apples"]
    if not a:
        return np.zeros((0, 3))
    lat = np.array([_num(r["lat"]) for r in a])
    lon = np.array([_num(r["lon"]) for r in a])
    o = m["origin"]
    # the map's own ENU frame about its origin, moved to the first's: origins a few metres apart, frames parallel
    offset = Origin(origin0["lat"], origin0["lon"], origin0.get("alt") or 0.0).to_enu(o["lat"], o["lon"],
                                                                                  o.get("alt") or 0.0)
    xyz = np.array([[_num(r["x"]), _num(r["y"]), _num(r["z"])] for r in a]) + offset
    shift = (m["report"].get("orchard") or {}).get("layout_shift") or {}
    xyz[:, :2] -= np.nan_to_num([_num(shift.get("east_m", 0.0)), _num(shift.get("north_m", 0.0))])
    bad = ~np.isfinite(lat) | ~np.isfinite(lon)
    xyz[bad] = np.nan
    return xyz


def combine_maps(folders: list[Path]) -> dict:
    """The maps in ``folders`` (at least two, one layout) as one: ``apples`` (records, APPLE columns), ``trees``,
    ``rows`` (records as their CSVs), ``sources`` (per map: its folder and the faces it gave) and ``cultivars``."""
    if len(folders) < 2:
        raise InputError("give at least two finished maps of one orchard to combine")
    maps = [read_map(f) for f in folders]
    _same_layout(maps)
    keys = [(int(t["row"]), int(t["tree"])) for t in maps[0]["trees"]]
    index = [{(int(t["row"]), int(t["tree"])): i for i, t in enumerate(m["trees"])} for m in maps]
    # (maps, trees) share of each face seen, the trees in the first map's order
    cover = {side: np.array([[_num(m["trees"][index[k][key]][f"cover_{side}"]) for key in keys]
                             for k, m in enumerate(maps)]) for side in (LEFT, RIGHT)}
    # each face's flight: the most of it seen (NaN: not known, as 0); the first on a tie
    best = {side: np.argmax(np.nan_to_num(c, nan=-1.0), axis=0) for side, c in cover.items()}
    chosen = {(key, side): int(best[side][j]) for j, key in enumerate(keys) for side in (LEFT, RIGHT)}
    origin0 = maps[0]["origin"]
    apples, gave = [], [{LEFT: 0, RIGHT: 0} for _ in maps]
    for k, m in enumerate(maps):
        xyz = _to_first(m, origin0)
        for a, p in zip(m["apples"], xyz):
            key, side = (int(a["row"]), int(a["tree"])), a["side"]
            if key[0] == 0 or side not in (LEFT, RIGHT) or chosen.get((key, side)) != k:
                continue
            apples.append({**a, "x": p[0], "y": p[1], "z": p[2], "flight": k + 1})
    for j, key in enumerate(keys):
        for side in (LEFT, RIGHT):
            if np.nan_to_num(cover[side][best[side][j], j]) > 0:
                gave[best[side][j]][side] += 1
    for i, a in enumerate(apples, start=1):
        a["id"] = i
    counts = {}
    for a in apples:
        counts[(int(a["row"]), int(a["tree"]))] = counts.get((int(a["row"]), int(a["tree"])), 0) + 1
    trees = []
    for j, (key, t0) in enumerate(zip(keys, maps[0]["trees"])):
        cl, cr = (float(cover[s][best[s][j], j]) for s in (LEFT, RIGHT))
        faces = [c for c in (cl, cr) if np.isfinite(c)]
        best_k = max(range(len(maps)), key=lambda k: np.nan_to_num(_num(maps[k]["trees"][index[k][key]]["coverage"]),
                                                                    nan=-1.0))
        tb = maps[best_k]["trees"][index[best_k][key]]
        trees.append({"row": key[0], "tree": key[1], "along_m": _num(t0.get("along_m")), "x": _num(t0.get("x")),
                      "y": _num(t0.get("y")), "lat": _num(t0.get("lat")), "lon": _num(t0.get("lon")),
                      "count": counts.get(key, 0), "coverage": float(np.mean(faces)) if faces else float("nan"),
                      "cover_left": cl, "cover_right": cr, "sides_seen": int(sum(c > 0 for c in faces)),
                      "frames_seen": int(sum(np.nan_to_num(_num(m["trees"][index[k][key]].get("frames_seen")))
                                             for k, m in enumerate(maps))),
                      **{c: _num(tb.get(c)) for c in ("range_m", "angle_deg", "apple_px")}})
    rows = []
    for r in maps[0]["rows"]:
        row = int(r["row"])
        mine = [t for t in trees if t["row"] == row]
        n = sum(t["count"] for t in mine)
        rows.append({**{k: _num(r.get(k)) for k in ("length_m", "start_x", "start_y", "end_x", "end_y", "start_lat",
                                                     "start_lon", "end_lat", "end_lon")},
                     "row": row, "count": n, "apples_per_m": n / _num(r["length_m"]) if _num(r["length_m"]) else 0.0})
    row_coverage(rows, trees)
    sources = [{"map": str(m["folder"]), "faces_given": gave[k], "apples_given": sum(a["flight"] == k + 1
                                                                                     for a in apples),
                "apples_in_map": len(m["apples"])} for k, m in enumerate(maps)]
    return {"apples": apples, "trees": trees, "rows": rows, "sources": sources, "maps": maps}


def write_combined(folders: list[Path], out: Path) -> dict:
    """Combine the maps in ``folders`` and write the combined map's files to ``out``; its report."""
    from ground.orchard.size import row_sizes
    from ground.outputs.tables import APPLE_COLUMNS, FORMATS, records_csv, rows_csv, trees_csv, write_atomic, write_json

    c = combine_maps(folders)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = {"id": np.array([a["id"] for a in c["apples"]], int),
             "row": np.array([int(a["row"]) for a in c["apples"]], int),
             "radius_m": np.array([_num(a["radius_m"]) for a in c["apples"]], float)}
    # every size carries the least certain of the maps' scales (ground.poses.scale)
    sigmas = [_num(((m["report"].get("registration") or {}).get("georeference_scale") or {}).get("sigma_pct"))
              for m in c["maps"]]
    sigma = max((s for s in sigmas if np.isfinite(s)), default=float("nan")) / 100.0
    layout_path = (c["maps"][0]["report"].get("orchard") or {}).get("layout")
    try:
        from pomar.layout import read_layout

        cultivars = {r.row: r.cultivar for r in read_layout(layout_path)} if layout_path else {}
    except (InputError, OSError):  # the layout moved since: the sizes take no cultivar
        cultivars = {}
    size = row_sizes(table, c["rows"], cultivars, sigma)
    columns = APPLE_COLUMNS + ["flight"]
    # the maps' own figures as they wrote them, but the positions, now in one frame
    write_atomic(out / "apples.csv", records_csv(c["apples"], columns, {k: FORMATS[k] for k in ("x", "y", "z")}))
    write_atomic(out / "trees.csv", trees_csv(c["trees"]))
    write_atomic(out / "rows.csv", rows_csv(c["rows"]))
    report = {"combined": {"maps": c["sources"],
                           "rule": "each face of each tree from the map that saw it best; no apple counted twice"},
              "apples": len(c["apples"]),
              "orchard": {"numbering": "layout", "layout": (c["maps"][0]["report"].get("orchard") or {}).get("layout"),
                          "coverage": flight_coverage(c["trees"]), "size": size},
              "map": c["maps"][0]["report"].get("map"),
              "registration": {"georeference_scale": {"sigma_pct": 100.0 * sigma if np.isfinite(sigma) else None}},
              "rows": [{k: r[k] for k in ("row", "count", "coverage")} for r in c["rows"]]}
    write_json(out / "report.json", report)
    return report
