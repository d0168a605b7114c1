"""Several flights of one orchard as one map (`ground combine`, ground.orchard.combine; issue 72): each face of each
tree from the flight that saw it best, no apple counted twice, the tree's coverage the union of its faces; bad maps
get one line."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ground.outputs.tables import APPLE_COLUMNS, records_csv, rows_csv, trees_csv

ORIGIN = {"lat": -28.5, "lon": -50.9, "alt": 900.0}
TREES = [(1, 1), (1, 2), (2, 1), (2, 2)]


def _map(folder: Path, covers: dict, apples: list[tuple], shift=(0.0, 0.0), numbering="layout") -> Path:
    """A finished map: ``covers`` (row, tree) -> (left, right) shares seen; ``apples`` (row, tree, side, x) each."""
    folder.mkdir(parents=True)
    trees = [{"row": r, "tree": t, "along_m": t - 0.5, "x": float(t), "y": 4.0 * r, "lat": -28.5 + 1e-5 * t,
              "lon": -50.9 + 1e-5 * r, "count": sum(a[:2] == (r, t) for a in apples),
              "coverage": np.mean(covers[(r, t)]), "cover_left": covers[(r, t)][0], "cover_right": covers[(r, t)][1],
              "sides_seen": sum(c > 0 for c in covers[(r, t)]), "frames_seen": 10} for r, t in TREES]
    rows = [{"row": r, "count": sum(a[0] == r for a in apples), "length_m": 2.0, "apples_per_m": 0.0, "start_x": 0.0,
             "start_y": 4.0 * r, "end_x": 2.0, "end_y": 4.0 * r} for r in (1, 2)]
    recs = [{"id": i + 1, "x": x, "y": 4.0 * r + (0.4 if side == "left" else -0.4), "z": 2.0, "lat": -28.5,
             "lon": -50.9, "alt": 902.0, "row": r, "tree": t, "side": side, "radius_m": 0.037, "observations": 5,
             "reprojection_error_px": 0.5, "first_frame": 0, "last_frame": 4}
            for i, (r, t, side, x) in enumerate(apples)]
    (folder / "trees.csv").write_text(trees_csv(trees))
    (folder / "rows.csv").write_text(rows_csv(rows))
    (folder / "apples.csv").write_text(records_csv(recs, APPLE_COLUMNS, {}))
    (folder / "report.json").write_text(json.dumps({
        "map": {"origin": ORIGIN}, "orchard": {"numbering": numbering, "layout": None,
                                               "layout_shift": {"east_m": shift[0], "north_m": shift[1]}},
        "registration": {"georeference_scale": {"sigma_pct": 1.0}}}))
    return folder


def _read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_each_face_comes_from_the_flight_that_saw_it_best_and_no_apple_counts_twice(tmp_path):
    # flight A flew the rows' left side, B their right; both glimpsed the other side of row 1's first tree
    a = _map(tmp_path / "a", {(1, 1): (1.0, 0.2), (1, 2): (0.9, 0.0), (2, 1): (0.8, 0.0), (2, 2): (0.0, 0.0)},
             [(1, 1, "left", 0.4), (1, 1, "left", 0.6), (1, 1, "right", 0.5), (1, 2, "left", 1.5),
              (2, 1, "left", 0.5)])
    b = _map(tmp_path / "b", {(1, 1): (0.1, 0.9), (1, 2): (0.0, 1.0), (2, 1): (0.3, 0.7), (2, 2): (0.0, 0.6)},
             [(1, 1, "left", 0.4), (1, 1, "right", 0.5), (1, 1, "right", 0.7), (1, 2, "right", 1.4),
              (2, 1, "left", 0.5), (2, 2, "right", 1.6)], shift=(0.5, 0.0))
    out = tmp_path / "both"
    r = subprocess.run([sys.executable, "-m", "ground", "combine", str(a), str(b), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    trees = {(int(t["row"]), int(t["tree"])): t for t in _read(out / "trees.csv")}
    # row 1 tree 1: A's two left apples and B's two right ones, never A's right glimpse or B's left one
    assert {k: int(t["count"]) for k, t in trees.items()} == {(1, 1): 4, (1, 2): 2, (2, 1): 1, (2, 2): 1}
    assert float(trees[(1, 1)]["coverage"]) == pytest.approx(0.95) and trees[(1, 1)]["sides_seen"] == "2"
    assert float(trees[(2, 2)]["coverage"]) == pytest.approx(0.3) and trees[(2, 2)]["sides_seen"] == "1"
    apples = _read(out / "apples.csv")
    assert len(apples) == 8 and sorted(int(x["id"]) for x in apples) == list(range(1, 9))
    assert {(x["row"], x["tree"], x["side"], x["flight"]) for x in apples if x["row"] == "1" and x["tree"] == "1"} \
        == {("1", "1", "left", "1"), ("1", "1", "right", "2")}
    # B's apples moved onto the layout as its own rows were (its shift), in A's frame
    assert sorted(float(x["x"]) for x in apples if x["flight"] == "2") == pytest.approx([0.0, 0.2, 0.9, 1.1])
    rows = {int(x["row"]): int(x["count"]) for x in _read(out / "rows.csv")}
    assert rows == {1: 6, 2: 2}
    report = json.loads((out / "report.json").read_text())
    assert [m["faces_given"] for m in report["combined"]["maps"]] == [{"left": 3, "right": 0}, {"left": 0, "right": 4}]
    assert report["orchard"]["coverage"]["trees_both_sides"] == 3
    # the combined map is a map: the trees to count are chosen from it
    r = subprocess.run([sys.executable, "-m", "ground", "choose-trees", str(out), "--trees", "2", "--out",
                        str(tmp_path / "sample.csv")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_maps_that_cannot_be_combined_get_one_line(tmp_path):
    cov = {k: (1.0, 0.0) for k in TREES}
    a = _map(tmp_path / "a", cov, [(1, 1, "left", 0.5)])
    unnumbered = _map(tmp_path / "u", cov, [(1, 1, "left", 0.5)], numbering="map")
    other = _map(tmp_path / "o", cov, [(1, 1, "left", 0.5)])
    t = (other / "trees.csv").read_text().splitlines()
    (other / "trees.csv").write_text("\n".join(t[:-1]) + "\n")  # a tree fewer: another layout
    old = _map(tmp_path / "old", cov, [(1, 1, "left", 0.5)])
    (old / "trees.csv").write_text((old / "trees.csv").read_text().replace("cover_left", "c_l"))
    for maps, says in (([a], "at least two"), ([a, unnumbered], "not numbered by an orchard layout"),
                       ([a, other], "another layout"), ([a, old], "no column cover_left"),
                       ([a, tmp_path / "none"], "no such file")):
        r = subprocess.run([sys.executable, "-m", "ground", "combine", *map(str, maps), "--out", str(tmp_path / "x")],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, (says, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x" / "trees.csv").exists()
