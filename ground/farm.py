"""One farm report from a batch's flights (issue 73), in ``DIR/farm/``: every block's rows and trees in one place.

Each block's map is its one finished flight's, or, where several flights of a block finished (its two sides, or a
plan's batteries), their combination (``ground combine``, ground.orchard.combine: each face of each tree from the
flight that saw it best) in ``DIR/farm/blocks/<block>/``, calibrated by the block's hand counts where the flights file
gives them (``ground load``). Then:
- ``rows.csv`` and ``trees.csv``: every block's rows and trees, with a ``block`` column, numbered by each block's
  layout (its map's own numbering where a block has none);
- ``farm.parquet``: the same as GeoParquet (WKB geometry, WGS84): a line per row, a point per tree, ``kind`` saying
  which, for a GIS;
- ``blocks.csv``: per block its flights, apples, load with its 90 % interval, kilograms and coverage;
- ``farm.png``: the farm at a glance, each tree coloured by its load (or its count where no hand counts were given).
"""

from __future__ import annotations

import csv
import json
import logging
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

ROW_FIELDS = ["block", "row", "count", "length_m", "coverage", "load", "load_lo", "load_hi", "diameter_mm", "kg",
              "kg_lo", "kg_hi", "start_lat", "start_lon", "end_lat", "end_lon"]
TREE_FIELDS = ["block", "row", "tree", "lat", "lon", "count", "coverage", "sides_seen", "load", "load_lo", "load_hi"]
BLOCK_FIELDS = ["block", "flights", "map", "apples", "load", "load_lo", "load_hi", "kg", "kg_lo", "kg_hi", "coverage",
                "trees", "trees_seen"]


def _num(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def block_map(block: str, folders: list[Path], counts: str | None, out: Path) -> Path:
    """The block's one map: its flight's folder, or its flights' combination in ``out/blocks/<block>``; calibrated by
    ``counts`` (the hand counts) where given and the map is a combination (a flight's own replay took them)."""
    if len(folders) == 1:
        return folders[0]
    from ground.orchard.combine import write_combined

    dest = out / "blocks" / block
    write_combined(folders, dest)
    if counts:
        r = subprocess.run([sys.executable, "-m", "ground", "load", str(dest), "--sample-counts", counts],
                           capture_output=True, text=True)
        if r.returncode:
            log.warning("block %s: its load could not be calibrated: %s", block,
                        (r.stderr.strip().splitlines() or ["?"])[-1])
    return dest


def _wkb_point(lon: float, lat: float) -> bytes:
    return struct.pack("<BIdd", 1, 1, lon, lat)


def _wkb_line(points: list[tuple[float, float]]) -> bytes:
    return struct.pack("<BII", 1, 2, len(points)) + b"".join(struct.pack("<dd", *p) for p in points)


def write_geoparquet(path: Path, rows: list[dict], trees: list[dict]) -> None:
    """Rows (lines) and trees (points) as one GeoParquet file (version 1.1.0: WKB, WGS84 longitude/latitude)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    feats = ([("row", r, _wkb_line([(_num(r["start_lon"]), _num(r["start_lat"])),
                                    (_num(r["end_lon"]), _num(r["end_lat"]))])) for r in rows]
             + [("tree", t, _wkb_point(_num(t["lon"]), _num(t["lat"]))) for t in trees])

    def col(key, kind=float):
        return [None if key not in f or not np.isfinite(_num(f[key])) else kind(_num(f[key])) for _, f, _ in feats]

    table = pa.table({"kind": [k for k, _, _ in feats], "block": [str(f["block"]) for _, f, _ in feats],
                      "row": col("row", int), "tree": col("tree", int), "count": col("count", int),
                      "coverage": col("coverage"), "load": col("load"), "load_lo": col("load_lo"),
                      "load_hi": col("load_hi"), "kg": col("kg"), "geometry": [g for _, _, g in feats]})
    lon = [_num(t["lon"]) for t in trees] + [_num(r[k]) for r in rows for k in ("start_lon", "end_lon")]
    lat = [_num(t["lat"]) for t in trees] + [_num(r[k]) for r in rows for k in ("start_lat", "end_lat")]
    ok = np.isfinite(lon) & np.isfinite(lat)
    bbox = [float(np.min(np.array(lon)[ok])), float(np.min(np.array(lat)[ok])), float(np.max(np.array(lon)[ok])),
            float(np.max(np.array(lat)[ok]))] if ok.any() else None
    geo = {"version": "1.1.0", "primary_column": "geometry",
           "columns": {"geometry": {"encoding": "WKB", "geometry_types": ["LineString", "Point"],
                                    "crs": _WGS84, **({"bbox": bbox} if bbox else {})}}}
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), b"geo": json.dumps(geo).encode()})
    pq.write_table(table, path)


#: OGC:CRS84 (WGS84, longitude first) as PROJJSON's identifier: GeoParquet's default CRS, written out.
_WGS84 = {"id": {"authority": "OGC", "code": "CRS84"}}


def farm_picture(rows: list[dict], trees: list[dict]) -> np.ndarray | None:
    """The farm (BGR), north up: rows in grey, each tree a dot coloured by its load (or count), a colour bar, a scale
    bar and each block's name. None without OpenCV or trees."""
    try:
        import cv2
    except ImportError:
        return None
    from pomar.plan_picture import _viridis

    pts = [(t, _num(t["lat"]), _num(t["lon"])) for t in trees]
    pts = [p for p in pts if np.isfinite(p[1]) and np.isfinite(p[2])]
    if not pts:
        return None
    from pomar.geo import Origin

    origin = Origin(float(np.mean([p[1] for p in pts])), float(np.mean([p[2] for p in pts])), 0.0)

    def enu(lat, lon):
        return origin.to_enu(lat, lon, 0.0)[:2]

    P = np.array([enu(la, lo) for _, la, lo in pts])
    lo_, hi_ = P.min(0) - 5.0, P.max(0) + 5.0
    size, margin = 1400, 70
    scale = (size - 2 * margin) / max(hi_ - lo_)
    w, h = (np.ceil((hi_ - lo_) * scale) + 2 * margin).astype(int)
    img = np.full((h + 60, w + 120, 3), 255, np.uint8)

    def px(xy):
        return int(margin + (xy[0] - lo_[0]) * scale), int(h - margin - (xy[1] - lo_[1]) * scale)

    for r in rows:
        a, b = enu(_num(r["start_lat"]), _num(r["start_lon"])), enu(_num(r["end_lat"]), _num(r["end_lon"]))
        if np.isfinite(a).all() and np.isfinite(b).all():
            cv2.line(img, px(a), px(b), (210, 210, 210), max(2, int(0.6 * scale)), cv2.LINE_AA)
    has_load = any(np.isfinite(_num(t.get("load"))) for t, _, _ in pts)
    key = "load" if has_load else "count"
    v = np.array([_num(t.get(key)) for t, _, _ in pts])
    top = float(np.nanpercentile(v, 95)) if np.isfinite(v).any() else 1.0
    top = top if top > 0 else 1.0
    if not has_load:  # a count says nothing of a tree the camera never saw: grey, as unknown
        v = np.where([_num(t.get("coverage")) > 0 for t, _, _ in pts], v, np.nan)
    for (t, la, lo), x in zip(pts, v):
        colour = (190, 190, 190) if not np.isfinite(x) else _viridis(x / top)
        cv2.circle(img, px(enu(la, lo)), max(3, int(0.35 * scale)), colour, -1, cv2.LINE_AA)
    blocks: dict[str, list] = {}
    for (t, la, lo) in pts:
        blocks.setdefault(str(t["block"]), []).append(enu(la, lo))
    for name, xy in blocks.items():
        xy = np.array(xy)
        cv2.putText(img, name, px((xy[:, 0].min(), xy[:, 1].max() + 3.0)), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0),
                    2, cv2.LINE_AA)
    x0 = w + 20  # the colour bar: 0 at the bottom, the 95th percentile at the top
    for i in range(200):
        cv2.line(img, (x0, margin + 200 - i), (x0 + 20, margin + 200 - i), _viridis(i / 199), 1)
    cv2.putText(img, f"{top:.0f}", (x0 + 24, margin + 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "0", (x0 + 24, margin + 200), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"apples a tree ({'load' if has_load else 'counted'})", (x0 - 160, margin - 12),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.circle(img, (x0 + 10, margin + 225), 6, (190, 190, 190), -1, cv2.LINE_AA)
    cv2.putText(img, "no figure" if has_load else "not seen", (x0 + 24, margin + 230), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    bar = 10.0 if (hi_ - lo_).max() < 150 else 50.0 if (hi_ - lo_).max() < 800 else 200.0
    cv2.line(img, (margin, h + 20), (int(margin + bar * scale), h + 20), (0, 0, 0), 3)
    cv2.putText(img, f"{bar:.0f} m", (margin, h + 45), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.arrowedLine(img, (w - 30, h + 45), (w - 30, h + 5), (0, 0, 0), 2, tipLength=0.3)
    cv2.putText(img, "N", (w - 55, h + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 2, cv2.LINE_AA)
    return img


def farm_report(out: Path, blocks: dict[str, dict]) -> dict:
    """The farm report in ``out/farm`` from ``blocks``: name -> {"folders": the block's finished flights' output
    folders, "flights": how many it had, "counts": its hand counts or None}; its summary (per block)."""
    from ground.outputs.tables import records_csv, write_atomic, write_json

    farm = Path(out) / "farm"
    farm.mkdir(parents=True, exist_ok=True)
    rows, trees, summary = [], [], []
    for name, b in sorted(blocks.items()):
        if not b["folders"]:
            summary.append({"block": name, "flights": b["flights"], "map": None})
            continue
        folder = block_map(name, b["folders"], b.get("counts"), farm)
        brows = [{**r, "block": name} for r in _read(folder / "rows.csv")]
        btrees = [{**t, "block": name} for t in _read(folder / "trees.csv")]
        rows += brows
        trees += btrees
        cov = [_num(t.get("coverage")) for t in btrees]
        cov = [c for c in cov if np.isfinite(c)]

        def total(key):
            v = [_num(r.get(key)) for r in brows]
            return float(np.sum(v)) if v and np.isfinite(v).all() else float("nan")

        summary.append({"block": name, "flights": b["flights"], "map": str(folder),
                        "apples": int(sum(_num(r["count"]) for r in brows)), "load": total("load"),
                        "load_lo": total("load_lo"), "load_hi": total("load_hi"), "kg": total("kg"),
                        "kg_lo": total("kg_lo"), "kg_hi": total("kg_hi"),
                        "coverage": float(np.mean(cov)) if cov else float("nan"), "trees": len(btrees),
                        "trees_seen": sum(c > 0 for c in cov)})
    fmt = {k: ".1f" for k in ("load", "load_lo", "load_hi", "kg", "kg_lo", "kg_hi")} | {"coverage": ".3f"}
    write_atomic(farm / "rows.csv", records_csv(rows, ROW_FIELDS, {}))
    write_atomic(farm / "trees.csv", records_csv(trees, TREE_FIELDS, {}))
    write_atomic(farm / "blocks.csv", records_csv(summary, BLOCK_FIELDS, fmt))
    if rows or trees:
        write_geoparquet(farm / "farm.parquet", rows, trees)
        img = farm_picture(rows, trees)
        if img is not None:
            import cv2

            cv2.imwrite(str(farm / "farm.png"), img)
    write_json(farm / "farm.json", {"blocks": summary})
    return {"blocks": summary, "folder": str(farm)}
