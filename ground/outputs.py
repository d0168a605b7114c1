"""The apple map's files, written atomically (write to a temporary name, then rename).

- ``apples.csv``: id, x, y, z (ENU m), lat, lon, alt (WGS84), row, observations, reprojection error,
  first and last frame;
- ``apples.geojson``: a FeatureCollection of WGS84 points (lon, lat, alt) with the same properties;
- ``apples.ply``: ASCII point cloud in ENU, coloured by row;
- ``rows.csv``: row, count, length (m, along the row direction);
- ``poses.csv``: every mapped frame's camera (centre in ENU and WGS84, rotation, pose source);
- ``report.json``: counts, settings, timings (written by the caller through :func:`write_json`).
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np

APPLE_COLUMNS = ["id", "x", "y", "z", "lat", "lon", "alt", "row", "observations", "reprojection_error_px",
                 "first_frame", "last_frame"]
ROW_COLUMNS = ["row", "count", "length_m"]

#: Row colours (RGB), cycled; also used by the rerun log.
PALETTE = np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48], [145, 30, 180],
                    [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128], [170, 110, 40]],
                   np.uint8)


def row_colours(rows: np.ndarray) -> np.ndarray:
    return PALETTE[np.asarray(rows, int) % len(PALETTE)]


def write_atomic(path: Path, data: str | bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def write_json(path: Path, obj) -> None:
    write_atomic(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


FORMATS = {"x": ".4f", "y": ".4f", "z": ".4f", "lat": ".9f", "lon": ".9f", "alt": ".4f", "reprojection_error_px": ".3f"}


def apples_csv(table: dict) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(APPLE_COLUMNS)
    n = len(table["id"])
    for i in range(n):
        w.writerow([format(table[c][i], FORMATS.get(c, "")) for c in APPLE_COLUMNS])
    return buf.getvalue()


def apples_geojson(table: dict) -> str:
    feats = []
    for i in range(len(table["id"])):
        if not np.isfinite([table["lat"][i], table["lon"][i]]).all():
            continue
        feats.append({"type": "Feature",
                      "geometry": {"type": "Point", "coordinates": [round(float(table["lon"][i]), 9),
                                                                    round(float(table["lat"][i]), 9),
                                                                    round(float(table["alt"][i]), 4)]},
                      "properties": {"id": int(table["id"][i]), "row": int(table["row"][i]),
                                     "observations": int(table["observations"][i]),
                                     "reprojection_error_px": round(float(table["reprojection_error_px"][i]), 3)}})
    return json.dumps({"type": "FeatureCollection", "features": feats})


def apples_ply(table: dict) -> str:
    n = len(table["id"])
    col = row_colours(table["row"]) if n else np.zeros((0, 3), np.uint8)
    head = ["ply", "format ascii 1.0", "comment pomar apple map, ENU metres", f"element vertex {n}",
            "property float x", "property float y", "property float z",
            "property uchar red", "property uchar green", "property uchar blue", "property int row", "end_header"]
    lines = [f"{table['x'][i]:.4f} {table['y'][i]:.4f} {table['z'][i]:.4f} {col[i, 0]} {col[i, 1]} {col[i, 2]} "
             f"{int(table['row'][i])}" for i in range(n)]
    return "\n".join(head + lines) + "\n"


def rows_summary(table: dict, direction: float) -> list[dict]:
    out = []
    if not len(table["id"]):
        return out
    along = np.stack([table["x"], table["y"]], 1) @ np.array([np.cos(direction), np.sin(direction)])
    for r in np.unique(table["row"]):
        sel = table["row"] == r
        out.append({"row": int(r), "count": int(sel.sum()), "length_m": float(np.ptp(along[sel]))})
    return out


def rows_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(ROW_COLUMNS)
    for r in rows:
        w.writerow([r["row"], r["count"], f"{r['length_m']:.2f}"])
    return buf.getvalue()


POSE_COLUMNS = ["frame", "t_unix", "source", "x", "y", "z", "lat", "lon", "alt", "qw", "qx", "qy", "qz", "sigma_m"]


def poses_csv(poses: dict) -> str:
    """Each mapped frame's camera: centre in ENU and WGS84, ENU-to-camera rotation (wxyz), source, 1-sigma (m)."""
    fmt = {**FORMATS, "t_unix": ".6f", "qw": ".9f", "qx": ".9f", "qy": ".9f", "qz": ".9f", "sigma_m": ".3f"}
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(POSE_COLUMNS)
    for i in range(len(poses["frame"])):
        w.writerow([format(poses[c][i], fmt.get(c, "")) for c in POSE_COLUMNS])
    return buf.getvalue()


def write_map(out_dir: Path, table: dict, direction: float) -> list[dict]:
    """apples.csv, apples.geojson, apples.ply and rows.csv; returns the rows summary."""
    out = Path(out_dir)
    rows = rows_summary(table, direction)
    write_atomic(out / "apples.csv", apples_csv(table))
    write_atomic(out / "apples.geojson", apples_geojson(table))
    write_atomic(out / "apples.ply", apples_ply(table))
    write_atomic(out / "rows.csv", rows_csv(rows))
    return rows


def read_harvest(path: Path) -> dict[int, float]:
    """A harvest file: CSV with columns ``row`` and ``kg``."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rd = csv.DictReader(f)
            if not rd.fieldnames or not {"row", "kg"} <= set(rd.fieldnames):
                raise ValueError(f"{path}: a harvest file needs columns row,kg (got {rd.fieldnames})")
            return {int(r["row"]): float(r["kg"]) for r in rd}
    except OSError as e:
        raise ValueError(f"{path}: {e}") from None


def harvest_correlation(rows: list[dict], harvest: dict[int, float]) -> dict:
    """Pearson r (and r²) of per-row counts with per-row yield, as the paper reports."""
    common = [r for r in rows if r["row"] in harvest]
    if len(common) < 3:
        return {"rows": len(common), "r": None, "r2": None, "note": "fewer than 3 rows in common"}
    c = np.array([r["count"] for r in common], float)
    kg = np.array([harvest[r["row"]] for r in common], float)
    r = float(np.corrcoef(c, kg)[0, 1])
    return {"rows": len(common), "r": r, "r2": r * r}
