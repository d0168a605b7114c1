"""The apple map's files, written atomically (write to a temporary name, then rename).

- ``apples.csv``: id, x, y, z (ENU m), lat, lon, alt (WGS84), row (1..N, or the orchard layout's number, 0 outside
  its rows: ground.orchard.assign), radius (m, the fruit's: its least hidden views' boxes times depth,
  ground.apples.counting), observations, reprojection error, first and last frame;
- ``apples.geojson``: a FeatureCollection of WGS84 points (lon, lat, alt) with the same properties;
  alt is empty (NaN in the CSVs, 2-D points in GeoJSON) where the drone's log gives no altitude above sea level;
- ``apples.ply``: ASCII point cloud in ENU, coloured by row;
- ``rows.csv``: row, count, length (m, along the row direction), apples per metre, and the row's line:
  start and end in ENU and WGS84 (the span of its apples along the row, at their median across-row offset);
- ``trees.csv``: row, tree (1.. from the row's start), position along the row (m, the segment's centre from the
  row's start), the segment's centre (ENU and WGS84), and its count: each row's line cut into segments one tree
  spacing long (with an orchard layout: its trees, where they stand, each apple to its row's nearest tree);
- ``candidates.csv`` (at the end): every apple the count was chosen from, counted or not: id, x, y, z (ENU m),
  lat, lon, alt, radius (m, its views' median box: what the size check compared), observations, strong views, expected views, first and last frame, and ``left_out``
  (empty when counted, else the check that left it out: ``small``, ``narrow`` or ``few_views``);
- ``poses.csv``: every mapped frame's camera (centre in ENU and WGS84, rotation, pose source);
- ``report.json``: counts, settings, timings (written by the caller through :func:`write_json`).
"""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from pomar.cli import InputError


def apples_enu(snap, A: list) -> np.ndarray:
    """(N, 3) ENU positions of these apples (ground.apples.association.Apple, in the map frame of the map
    ``snap``, a :class:`ground.outputs.snapshot.MapSnapshot`): the map's similarity, then the corrections of the map's
    bend and drift of the frames each apple was seen in, each moving it with its camera, and averaged (an apple seen
    again on a later pass takes both stretches' corrections)."""
    X = np.array([a.X for a in A]).reshape(-1, 3)
    if snap.to_enu is None or not len(X):
        return X
    S = snap.to_enu
    frames, off, rot = snap.corrections
    seen = [[snap.frame_of[o.frame] for o in a.observations] for a in A]
    k = np.searchsorted(frames, np.concatenate(seen))
    used = np.unique(k)  # the posed frames these apples were seen in
    centre = np.zeros((len(frames), 3))
    centre[used] = S.apply(np.array([snap.poses[f].centre for f in frames[used]], float).reshape(-1, 3))
    # every (apple, view) pair at once: the apple moved with that view's camera, then the mean over its views
    n_views = np.array([len(fs) for fs in seen])
    apple = np.repeat(np.arange(len(A)), n_views)
    X = S.apply(np.asarray(X, float).reshape(-1, 3))
    moved = centre[k] + off[k] + np.einsum("nij,nj->ni", rot[k], X[apple] - centre[k])
    out = np.zeros_like(X)
    np.add.at(out, apple, moved)
    return out / n_views[:, None]


def _geodetic(snap, enu: np.ndarray) -> np.ndarray:
    """(N, 3) lat, lon, alt of ENU points; NaN before the map is georeferenced. The altitude is NaN where the drone's
    log gives none above sea level (a DJI SRT's height above take-off): the map's heights stay in its ENU z."""
    if snap.to_enu is None or snap.origin is None or not len(enu):
        return np.full((len(enu), 3), np.nan)
    geo = np.asarray(snap.origin.to_geodetic(enu), float).reshape(-1, 3)
    if not snap.above_sea_level:
        geo[:, 2] = np.nan
    return geo


def apple_table(snap) -> tuple[dict[str, np.ndarray], float]:
    """The counted apples of the map ``snap`` (:class:`ground.outputs.snapshot.MapSnapshot`) as columns
    (APPLE_COLUMNS: ENU, WGS84, row 1..N left to right looking along the row direction, radius in metres ...), and the
    rows' direction (rad)."""
    from ground.apples.rows import direction_rows

    ids = snap.counted_ids
    A = [snap.apples[i] for i in ids]
    enu = apples_enu(snap, A)
    geo = _geodetic(snap, enu)
    rows, direction = direction_rows(enu[:, :2]) if len(A) >= 2 else (np.zeros(len(A), int), 0.0)
    return {"id": np.array(ids, int), "x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2],
            "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
            "row": np.asarray(rows, int) + 1,
            "tree": np.zeros(len(A), int), "side": np.full(len(A), "", dtype=object),  # on a layout (ground.orchard)
            "radius_m": np.array([snap.size.get(i, np.nan) for i in ids], float) * snap.metres_per_unit,
            "observations": np.array([a.n_observations for a in A], int),
            "reprojection_error_px": np.array([a.reprojection_error for a in A], float),
            "first_frame": np.array([snap.frame_of[a.first_frame] for a in A], int),
            "last_frame": np.array([snap.frame_of[a.last_frame] for a in A], int)}, direction


def candidate_table(snap) -> dict[str, np.ndarray]:
    """Every apple the count was chosen from (the counting's checks, with each apple's position, ENU and WGS84, its
    radius in metres and its first and last frame): candidates.csv's columns. ``snap`` made at the end (its
    ``checks``)."""
    c = dict(snap.checks)
    A = [snap.apples[i] for i in c["id"]]
    enu = apples_enu(snap, A)
    geo = _geodetic(snap, enu)
    radius = c.pop("radius") * snap.metres_per_unit
    return {**c, "radius_m": radius, "x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2],
            "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
            "first_frame": np.array([snap.frame_of[a.first_frame] for a in A], int),
            "last_frame": np.array([snap.frame_of[a.last_frame] for a in A], int)}


def pose_table(snap) -> dict[str, np.ndarray]:
    """Every mapped frame's camera: frame, capture time, source, centre (ENU and WGS84), ENU-to-camera quaternion."""
    from scipy.spatial.transform import Rotation

    frames = sorted(snap.poses)
    P = [snap.poses[f] for f in frames]
    if not P or snap.to_enu is None:
        return {k: np.zeros(0) for k in ("frame", "t_unix", "source", "x", "y", "z", "lat", "lon", "alt",
                                         "qw", "qx", "qy", "qz", "sigma_m")}
    S = snap.to_enu
    _, off, rot = snap.corrections
    C = S.apply(np.array([p.centre for p in P])) + off
    R = np.array([p.R for p in P]) @ S.R.T @ np.swapaxes(rot, 1, 2)  # ENU-to-camera, turned with the map's bend
    q = Rotation.from_matrix(R).as_quat()  # xyzw
    geo = _geodetic(snap, C)
    return {"frame": np.array(frames), "t_unix": np.array([snap.frame_times.get(f, np.nan) for f in frames]),
            "source": np.array([p.source for p in P], dtype=object), "x": C[:, 0], "y": C[:, 1], "z": C[:, 2],
            "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
            "qw": q[:, 3], "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2],
            "sigma_m": np.array([p.sigma_m for p in P])}


#: ``tree`` and ``side``: with an orchard layout, the apple's tree (numbered from 1 along its row; 0 outside) and its side
#: of the row (ground.orchard.assign.LEFT, RIGHT); without one, 0 and empty.
APPLE_COLUMNS = ["id", "x", "y", "z", "lat", "lon", "alt", "row", "tree", "side", "radius_m", "observations",
                 "reprojection_error_px", "first_frame", "last_frame"]
ROW_COLUMNS = ["row", "count", "length_m", "apples_per_m", "start_x", "start_y", "end_x", "end_y",
               "start_lat", "start_lon", "end_lat", "end_lon", "coverage", "load", "load_lo", "load_hi",
               "diameter_mm", "share_lt60", "share_60_70", "share_70_80", "share_gt80", "apple_kg", "kg", "kg_lo",
               "kg_hi", "diameter_mm_lo", "diameter_mm_hi"]

#: Row colours (RGB), cycled by row number; also used by the rerun log. Okabe & Ito's colour-blind-safe
#: palette without its black: blue, orange, bluish green, vermillion, sky blue, reddish purple, yellow.
PALETTE = np.array([[0, 114, 178], [230, 159, 0], [0, 158, 115], [213, 94, 0], [86, 180, 233], [204, 121, 167],
                    [240, 228, 66]], np.uint8)


def row_colours(rows: np.ndarray) -> np.ndarray:
    """Rows are numbered from 1: row 1 takes the palette's first colour."""
    return PALETTE[(np.asarray(rows, int) - 1) % len(PALETTE)]


def write_atomic(path: Path, data: str | bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # a full disk: the file before stays whole, and no half-written one is left
        raise


def rescue_folder(flight_id: str | None, pid: int) -> Path:
    """Where a ground process (``pid``) writes the map files its output folder refused at the flight's end."""
    return Path(tempfile.gettempdir()) / f"pomar-rescue-{flight_id or 'flight'}-{pid}"


def write_json(path: Path, obj) -> None:
    write_atomic(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


FORMATS = {"x": ".4f", "y": ".4f", "z": ".4f", "lat": ".9f", "lon": ".9f", "alt": ".4f", "reprojection_error_px": ".3f",
           "radius_m": ".4f"}


#: An apple's place on a layout where the table has none (a map without a layout): tree 0, no side.
NO_PLACE = {"tree": 0, "side": ""}


def apples_csv(table: dict) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(APPLE_COLUMNS)
    n = len(table["id"])
    for i in range(n):
        w.writerow([format(table[c][i] if c in table else NO_PLACE.get(c, ""), FORMATS.get(c, "")) for c in APPLE_COLUMNS])
    return buf.getvalue()


def apples_geojson(table: dict) -> str:
    feats = []
    for i in range(len(table["id"])):
        if not np.isfinite([table["lat"][i], table["lon"][i]]).all():
            continue
        feats.append({"type": "Feature",
                      # 2-D where the map has no altitude above sea level (_geodetic)
                      "geometry": {"type": "Point", "coordinates": [round(float(table["lon"][i]), 9),
                                                                    round(float(table["lat"][i]), 9)]
                                   + ([round(float(table["alt"][i]), 4)] if np.isfinite(table["alt"][i]) else [])},
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


ROW_FORMATS = {"length_m": ".2f", "apples_per_m": ".2f", "coverage": ".3f", "load": ".0f", "load_lo": ".0f",
               "load_hi": ".0f", "diameter_mm": ".1f", "share_lt60": ".3f", "share_60_70": ".3f", "share_70_80": ".3f",
               "share_gt80": ".3f", "apple_kg": ".4f", "kg": ".1f", "kg_lo": ".1f", "kg_hi": ".1f", "diameter_mm_lo": ".1f",
               "diameter_mm_hi": ".1f", "start_x": ".3f", "start_y": ".3f", "end_x": ".3f",
               "end_y": ".3f", "start_lat": ".9f", "start_lon": ".9f", "end_lat": ".9f", "end_lon": ".9f"}


def records_csv(records: list[dict], columns: list[str], formats: dict[str, str]) -> str:
    """CSV text of records (dicts), the given columns in order, each value formatted by ``formats`` where named."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in records:
        w.writerow([format(r.get(c, float("nan")), formats.get(c, "")) for c in columns])
    return buf.getvalue()


def rows_csv(rows: list[dict]) -> str:
    return records_csv(rows, ROW_COLUMNS, ROW_FORMATS)


#: With what each tree's canopy showed the camera (pomar.coverage.COVERAGE_COLUMNS): empty where not known.
#: And the load estimated from the hand counts (ground.orchard.calibration.LOAD_COLUMNS): empty without them.
TREE_COLUMNS = ["row", "tree", "along_m", "x", "y", "lat", "lon", "count", "coverage", "cover_left", "cover_right",
                "sides_seen", "frames_seen", "range_m", "angle_deg", "apple_px", "hand_count", "load", "load_lo",
                "load_hi"]


def trees_csv(trees: list[dict]) -> str:
    return records_csv(trees, TREE_COLUMNS, {"along_m": ".2f", "x": ".3f", "y": ".3f", "lat": ".9f", "lon": ".9f",
                                             "coverage": ".3f", "cover_left": ".3f", "cover_right": ".3f", "range_m": ".2f", "angle_deg": ".1f", "apple_px": ".2f",
                                             "load": ".1f", "load_lo": ".1f", "load_hi": ".1f"})


POSE_COLUMNS = ["frame", "t_unix", "source", "x", "y", "z", "lat", "lon", "alt", "qw", "qx", "qy", "qz", "sigma_m"]


CANDIDATE_COLUMNS = ["id", "x", "y", "z", "lat", "lon", "alt", "radius_m", "observations", "strong_views",
                     "expected_views", "first_frame", "last_frame", "left_out"]


def candidates_csv(c: dict) -> str:
    return records_csv([{k: c[k][i] for k in CANDIDATE_COLUMNS} for i in range(len(c["id"]))], CANDIDATE_COLUMNS,
                       {**FORMATS, "expected_views": ".0f"})


def poses_csv(poses: dict) -> str:
    """Each mapped frame's camera: centre in ENU and WGS84, ENU-to-camera rotation (wxyz), source, 1-sigma (m)."""
    fmt = {**FORMATS, "t_unix": ".6f", "qw": ".9f", "qx": ".9f", "qy": ".9f", "qz": ".9f", "sigma_m": ".3f"}
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(POSE_COLUMNS)
    for i in range(len(poses["frame"])):
        w.writerow([format(poses[c][i], fmt.get(c, "")) for c in POSE_COLUMNS])
    return buf.getvalue()


def write_map(out_dir: Path, table: dict, rows: list[dict], trees: list[dict]) -> None:
    """apples.csv, apples.geojson, apples.ply, rows.csv and trees.csv."""
    out = Path(out_dir)
    write_atomic(out / "trees.csv", trees_csv(trees))
    write_atomic(out / "apples.csv", apples_csv(table))
    write_atomic(out / "apples.geojson", apples_geojson(table))
    write_atomic(out / "apples.ply", apples_ply(table))
    write_atomic(out / "rows.csv", rows_csv(rows))


class HarvestFileError(InputError, ValueError):
    """A harvest file that does not read: the message names the file, its line and what is wrong."""


def read_harvest(path: Path) -> dict[int, float]:
    """A harvest file: CSV with columns ``row`` (numbered as in rows.csv) and ``kg``, one line a row. A row that is not
    a whole number, a yield that is not a number or is negative, a row given twice: HarvestFileError naming the line."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rd = csv.DictReader(f)
            if not rd.fieldnames or not {"row", "kg"} <= set(rd.fieldnames):
                raise HarvestFileError(f"{path}: a harvest file needs columns row,kg (got {rd.fieldnames})")
            out: dict[int, float] = {}
            for r in rd:
                line = rd.line_num
                try:
                    row = int(r["row"])
                except (TypeError, ValueError):
                    raise HarvestFileError(f"{path}:{line}: row {r['row']!r} is not a whole number") from None
                try:
                    kg = float(r["kg"])
                except (TypeError, ValueError):
                    raise HarvestFileError(f"{path}:{line}: kg {r['kg']!r} is not a number") from None
                if not np.isfinite(kg) or kg < 0:
                    raise HarvestFileError(f"{path}:{line}: kg {r['kg']} is not a yield (a number, 0 or more)")
                if row in out:
                    raise HarvestFileError(f"{path}:{line}: row {row} is given twice")
                out[row] = kg
            return out
    except OSError as e:
        raise HarvestFileError(f"{path}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise HarvestFileError(f"{path}: not a text (CSV) file") from None


def harvest_correlation(rows: list[dict], harvest: dict[int, float]) -> dict:
    """Pearson r (and r²) of per-row counts with per-row yield, as the paper reports."""
    common = [r for r in rows if r["row"] in harvest]
    if len(common) < 3:
        return {"rows": len(common), "r": None, "r2": None, "note": "fewer than 3 rows in common"}
    c = np.array([r["count"] for r in common], float)
    kg = np.array([harvest[r["row"]] for r in common], float)
    r = float(np.corrcoef(c, kg)[0, 1])
    return {"rows": len(common), "r": r, "r2": r * r}
