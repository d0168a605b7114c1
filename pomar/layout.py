"""The orchard as the grower knows it: an orchard layout file (issue 59), one line a row.

    row,start_lat,start_lon,end_lat,end_lon,tree_spacing_m,first_tree_m,cultivar
    12,-28.5163188,-50.8811460,-28.5160002,-50.8811460,1.0,0.5,Gala

``row`` is the row's number as the grower uses it (any whole number, each once); ``start`` and ``end`` its two ends in
WGS84 (degrees); the trees stand along the line from start to end, the first ``first_tree_m`` from the start, then one
every ``tree_spacing_m`` up to the end: tree 1, 2, ... So the same tree has the same ``row,tree`` in every flight.
``cultivar`` (optional, may be empty) names the row's cultivar: its apples' mass from their size (pomar.fruit).

:func:`read_layout` reads and checks one (a line that does not parse, a row given twice, a row whose two ends are in one
place, trees that overlap: one line naming the line and what is wrong); :func:`layout_from_rows` writes one from a
finished map's ``rows.csv``, numbered as the map numbers them, for the grower to check and correct; :func:`write_layout`
writes it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pomar.cli import InputError
from pomar.user_csv import user_csv

COLUMNS = ["row", "start_lat", "start_lon", "end_lat", "end_lon", "tree_spacing_m", "first_tree_m"]
#: A row shorter than this has its two ends in one place (a GPS fix's spread).
MIN_ROW_M = 1.0
#: Two trees closer than this share of the smaller of their spacings overlap (two rows drawn on one another, or a
#: spacing mistyped).
OVERLAP_SHARE = 0.5


class LayoutError(InputError, ValueError):
    """An orchard layout file that does not read: the message names the file, its line and what is wrong."""


@dataclass(frozen=True)
class LayoutRow:
    row: int
    start: tuple[float, float]  # lat, lon (deg)
    end: tuple[float, float]
    tree_spacing_m: float
    first_tree_m: float
    line: int = 0  # its line in the file (0: not read from one)
    cultivar: str = ""  # the row's cultivar, where the grower says it (its apples' mass: pomar.fruit)


def row_ends_enu(r: LayoutRow, origin) -> tuple[np.ndarray, np.ndarray]:
    """A row's start and end, horizontal ENU (m) about ``origin`` (pomar.geo.Origin)."""
    a, b = (np.asarray(origin.to_enu(lat, lon, origin.alt), float)[:2] for lat, lon in (r.start, r.end))
    return a, b


def row_length_m(r: LayoutRow, origin) -> float:
    """The length (m) of a row, in the ENU frame of ``origin``."""
    a, b = row_ends_enu(r, origin)
    return float(np.linalg.norm(b - a))


def tree_positions(r: LayoutRow, origin) -> np.ndarray:
    """(n, 2) ENU positions (m, about ``origin``) of the row's trees, tree 1 first."""
    a, b = row_ends_enu(r, origin)
    length = float(np.linalg.norm(b - a))
    along = np.arange(r.first_tree_m, length + 1e-9, r.tree_spacing_m)
    return a + along[:, None] * (b - a) / max(length, 1e-12)


def layout_trees(rows: list[LayoutRow]) -> set[tuple[int, int]]:
    """Every (row, tree) number of a layout."""
    from pomar.geo import Origin

    if not rows:
        return set()
    origin = Origin(rows[0].start[0], rows[0].start[1], 0.0)
    return {(r.row, k + 1) for r in rows for k in range(len(tree_positions(r, origin)))}


def read_layout(path) -> list[LayoutRow]:
    """The rows of an orchard layout file, checked (module docstring); LayoutError naming the line otherwise."""
    from pomar.geo import Origin

    path = Path(path)
    rows = [_row(path, line, d) for line, d in user_csv(path, COLUMNS, LayoutError, "an orchard layout")]
    if not rows:
        raise LayoutError(f"{path}: no rows")
    seen: dict[int, int] = {}
    for r in rows:
        if r.row in seen:
            raise LayoutError(f"{path}:{r.line}: row {r.row} is given twice (first on line {seen[r.row]})")
        seen[r.row] = r.line
    origin = Origin(rows[0].start[0], rows[0].start[1], 0.0)
    for r in rows:
        length = row_length_m(r, origin)
        if length < MIN_ROW_M:
            raise LayoutError(f"{path}:{r.line}: row {r.row}'s two ends are in one place ({length:.2f} m apart)")
        if r.first_tree_m > length:
            raise LayoutError(f"{path}:{r.line}: row {r.row}'s first tree ({r.first_tree_m:g} m) lies past its end "
                              f"({length:.1f} m)")
    _check_overlaps(path, rows, origin)
    return rows


def _row(path: Path, line: int, d: dict) -> LayoutRow:
    def number(key: str, lo: float, hi: float) -> float:
        try:
            v = float(d[key])
        except (TypeError, ValueError):
            raise LayoutError(f"{path}:{line}: {key} {d[key]!r} is not a number") from None
        if not (np.isfinite(v) and lo <= v <= hi):
            raise LayoutError(f"{path}:{line}: {key} {d[key]} is not in [{lo:g}, {hi:g}]")
        return v

    try:
        row = int(d["row"])
    except (TypeError, ValueError):
        raise LayoutError(f"{path}:{line}: row {d['row']!r} is not a whole number") from None
    spacing = number("tree_spacing_m", 0.0, 100.0)
    if spacing <= 0:
        raise LayoutError(f"{path}:{line}: tree_spacing_m must be more than 0 m, got {d['tree_spacing_m']}")
    return LayoutRow(row, (number("start_lat", -90, 90), number("start_lon", -180, 180)),
                     (number("end_lat", -90, 90), number("end_lon", -180, 180)), spacing,
                     number("first_tree_m", 0.0, 10_000.0), line, (d.get("cultivar") or "").strip())


def _check_overlaps(path: Path, rows: list[LayoutRow], origin) -> None:
    """Trees of two rows (or of one) closer than OVERLAP_SHARE of the smaller spacing: LayoutError naming both."""
    from scipy.spatial import cKDTree

    pts, owner = [], []
    for i, r in enumerate(rows):
        p = tree_positions(r, origin)
        pts.append(p)
        owner += [(i, k + 1) for k in range(len(p))]
    P = np.concatenate(pts) if pts else np.zeros((0, 2))
    spacing = np.array([rows[i].tree_spacing_m for i, _ in owner])
    if len(P) < 2:
        return
    for a, b in sorted(cKDTree(P).query_pairs(OVERLAP_SHARE * float(spacing.max()))):
        if np.linalg.norm(P[a] - P[b]) < OVERLAP_SHARE * min(spacing[a], spacing[b]):
            (i, ta), (j, tb) = owner[a], owner[b]
            ri, rj = rows[i], rows[j]
            raise LayoutError(f"{path}:{rj.line}: row {rj.row}'s tree {tb} overlaps row {ri.row}'s tree {ta} "
                              f"(line {ri.line}): {np.linalg.norm(P[a] - P[b]):.2f} m apart")


def layout_from_rows(rows_csv, tree_spacing_m: float) -> list[LayoutRow]:
    """A layout from a finished map's rows.csv (each row's line: the span of its apples), numbered as the map numbers
    its rows, a tree every ``tree_spacing_m`` from half a spacing after the start (as the map's trees.csv cuts them)."""
    from pomar.flight import read_csv

    d = read_csv(Path(rows_csv), ["row", "start_lat", "start_lon", "end_lat", "end_lon"])
    return [LayoutRow(int(r), (float(a), float(b)), (float(c), float(e)), float(tree_spacing_m), tree_spacing_m / 2.0)
            for r, a, b, c, e in zip(d["row"], d["start_lat"], d["start_lon"], d["end_lat"], d["end_lon"])
            if np.isfinite([a, b, c, e]).all()]


def write_layout(rows: list[LayoutRow], path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(COLUMNS + ["cultivar"])
        for r in rows:
            w.writerow([r.row, f"{r.start[0]:.9f}", f"{r.start[1]:.9f}", f"{r.end[0]:.9f}", f"{r.end[1]:.9f}",
                        f"{r.tree_spacing_m:g}", f"{r.first_tree_m:g}", r.cultivar])
