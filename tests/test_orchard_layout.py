"""The orchard layout file (ground/orchard/layout.py): written from a finished map, read back, and every way a grower's
edit can break it named by its line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from ground.orchard.layout import COLUMNS, LayoutError, read_layout, tree_positions
from pomar.geo import Origin

HEAD = ",".join(COLUMNS) + "\n"
# two rows 3.5 m apart (about 3.2e-5 deg of longitude at 28.5 S), 20 m long (1.8e-4 deg of latitude)
GOOD = HEAD + "12,-28.51600,-50.88110,-28.51618,-50.88110,1.0,0.5\n13,-28.51600,-50.881136,-28.51618,-50.881136,1.0,0.5\n"


def test_a_layout_from_a_finished_map_reads_back_with_its_trees_along_each_row(replayed_test_flight, tmp_path):
    """`python -m ground layout MAP --out FILE`: one line a row of the map's rows.csv, its ends those of the row's
    line; read back, each row holds a tree every spacing from half a spacing after its start."""
    _, out, rep = replayed_test_flight
    path = tmp_path / "orchard.csv"
    r = subprocess.run([sys.executable, "-m", "ground", "layout", str(out), "--out", str(path), "--tree-spacing-m",
                        "0.8"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = read_layout(path)
    assert [x.row for x in rows] == [x["row"] for x in rep["rows"]]
    origin = Origin(rows[0].start[0], rows[0].start[1], 0.0)
    for x, want in zip(rows, rep["rows"]):
        t = tree_positions(x, origin)
        assert len(t) == int(np.floor((want["length_m"] - 0.4) / 0.8 + 1e-6)) + 1, (len(t), want["length_m"])
        assert np.allclose(np.linalg.norm(np.diff(t, axis=0), axis=1), 0.8, atol=1e-3)
    r = subprocess.run([sys.executable, "-m", "ground", "layout", "--check", str(path)], capture_output=True, text=True)
    assert r.returncode == 0 and f"{len(rows)} rows" in r.stdout, r.stderr


@pytest.mark.parametrize("text,says", [
    (HEAD + "12,-28.516,-50.8811,-28.51618,x,1.0,0.5\n", ":2: end_lon 'x' is not a number"),
    (HEAD + "A,-28.516,-50.8811,-28.51618,-50.8811,1.0,0.5\n", ":2: row 'A' is not a whole number"),
    (GOOD + "12,-28.5170,-50.8815,-28.5172,-50.8815,1.0,0.5\n", ":4: row 12 is given twice (first on line 2)"),
    (HEAD + "7,-28.516,-50.8811,-28.516,-50.8811,1.0,0.5\n", ":2: row 7's two ends are in one place"),
    (HEAD + "7,-28.516,-50.8811,-28.51618,-50.8811,0,0.5\n", ":2: tree_spacing_m must be more than 0 m"),
    (HEAD + "7,-28.516,-50.8811,-28.51618,-50.8811,1.0,50\n", ":2: row 7's first tree (50 m) lies past its end"),
    (GOOD + "14,-28.51600,-50.881101,-28.51618,-50.881101,1.0,0.5\n", ":4: row 14's tree 1 overlaps row 12's tree 1"),
    ("row,start_lat\n1,2\n", ":1: an orchard layout needs the columns"),
])
def test_a_broken_layout_is_one_line_naming_its_line(tmp_path, text, says):
    path = tmp_path / "orchard.csv"
    path.write_text(text)
    with pytest.raises(LayoutError) as e:
        read_layout(path)
    assert str(e.value).startswith(str(path)) and says in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_good_layout_reads_and_a_broken_one_stops_the_command(tmp_path):
    path = tmp_path / "orchard.csv"
    path.write_text(HEAD + "7,-28.516,-50.8811,-28.516,-50.8811,1.0,0.5\n")
    r = subprocess.run([sys.executable, "-m", "ground", "layout", "--check", str(path)], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip() == f"error: {path}:2: row 7's two ends are in one place (0.00 m apart)"
    path.write_text(GOOD)
    rows = read_layout(path)
    assert [r.row for r in rows] == [12, 13] and rows[1].line == 3
    t = tree_positions(rows[0], Origin(rows[0].start[0], rows[0].start[1], 0.0))
    assert len(t) == 20 and abs(t[0, 1] + 0.5) < 0.01  # the row runs south: its first tree half a metre south
