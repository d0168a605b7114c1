"""The orchard layout file (pomar/layout.py): written from a finished map, read back, and every way a grower's
edit can break it named by its line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pomar.layout import COLUMNS, LayoutError, read_layout, tree_positions
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


def _tilted_layout(origin, rows=(21, 22, 23), gap=3.5, length=12.0, spacing=1.2, first=0.6, azimuth_deg=30.0):
    """Rows ``gap`` m apart running ``azimuth_deg`` from north, each ``length`` m long: LayoutRows (WGS84 ends from
    ``origin``) and each row's start, along and across unit vectors in ENU."""
    from pomar.layout import LayoutRow

    a = np.radians(azimuth_deg)
    u, n = np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])
    out, lines = [], []
    for k, number in enumerate(rows):
        s = k * gap * n
        e = s + length * u
        (la, lo, _), (lb, lb_lon, _) = np.asarray(origin.to_geodetic(np.array([[*s, 0.0], [*e, 0.0]])), float)
        out.append(LayoutRow(number, (la, lo), (lb, lb_lon), spacing, first, k + 2))
        lines.append((s, u, n))
    return out, lines


def test_apples_take_the_layouts_row_and_nearest_tree_and_those_off_every_row_are_outside():
    """Three tilted rows numbered 21-23 by the grower: an apple within its row's strip goes to that row's nearest tree;
    one between two rows to the nearer; one past a row's end, or far off, is outside (row 0); every tree is listed,
    counted or not, and the rows' counts add up to the apples inside."""
    from ground.orchard.assign import OUTSIDE, orchard_rows

    origin = Origin(-28.516, -50.8811, 20.0)
    layout, lines = _tilted_layout(origin)
    rng = np.random.default_rng(3)
    pts, want_row, want_tree = [], [], []
    for (s, u, n), r in zip(lines, layout):
        for tree in rng.integers(1, 10, 25):  # trees 1..10 of 10 (0.6 + 9 x 1.2 = 11.4 m)
            along = 0.6 + (tree - 1) * 1.2 + rng.uniform(-0.5, 0.5)
            across = rng.uniform(-1.2, 1.2)  # within the canopy, less than half the 3.5-m gap
            pts.append(s + along * u + across * n)
            want_row.append(r.row)
            want_tree.append(tree)
    s, u, n = lines[0]
    pts += [s - 1.5 * u, s + 14.0 * u, s - 30.0 * n, s + 5.0 * u + 1.6 * n]  # before, past, far off; 1.6 m toward 22
    want_row += [OUTSIDE, OUTSIDE, OUTSIDE, 21]
    want_tree += [0, 0, 0, 5]
    # an apple touching the row's end (its centre 2 cm past) is in it; one 10 cm past is not (END_TOLERANCE_M)
    pts += [s + 12.02 * u, s + 12.10 * u]
    want_row += [21, OUTSIDE]
    want_tree += [10, 0]
    P = np.array(pts)
    table = {"id": np.arange(len(P)), "x": P[:, 0], "y": P[:, 1], "z": np.full(len(P), 2.0)}
    row_of, rows, trees = orchard_rows(table, layout, origin)
    assert list(row_of) == want_row
    assert [r["row"] for r in rows] == [21, 22, 23] and sum(r["count"] for r in rows) == len(P) - 4
    assert all(abs(r["length_m"] - 12.0) < 0.01 for r in rows)
    assert len(trees) == 30 and [t["tree"] for t in trees[:10]] == list(range(1, 11))
    got = {(t["row"], t["tree"]): t["count"] for t in trees}
    for r in (21, 22, 23):
        tr = np.array(want_tree)[np.array(want_row) == r]
        assert all(got[(r, k)] == int((tr == k).sum()) for k in range(1, 11)), r
    # a tree's position is its layout position: tree 1 of row 21 is 0.6 m along the row from its start
    t1 = next(t for t in trees if (t["row"], t["tree"]) == (21, 1))
    assert np.allclose([t1["x"], t1["y"]], lines[0][0] + 0.6 * lines[0][1], atol=0.01)
    assert abs(t1["lat"] - layout[0].start[0]) < 1e-5


@pytest.mark.parametrize("sides", [2, 1])
def test_a_map_lying_off_the_layout_across_the_rows_is_shifted_onto_it(sides):
    """Five made-up rows 4 m apart; the apples lie on the canopy's faces (0.5 m off the line, +-0.2 m), each seen from
    a camera 3 m out on its side; the map lies 1.6 m across and 0.6 m along the rows off the layout, as a one-pass
    GPS track can. From both sides the shift is found to 5 cm and the face's offset with it; from one side the two
    cannot be told apart, and the shift holds both (2.1 m: more than half the spacing, so nearer the next row's
    line than the apples' own, which lies on the far side from the camera). Either way every apple then lies in its
    own row's strip, where as mapped a quarter of the apples (two-sided) or most (one-sided) fell in the next row's."""
    from ground.orchard.assign import orchard_rows
    from ground.orchard.register import register_to_layout

    origin = Origin(-28.516, -50.8811, 20.0)
    layout, lines = _tilted_layout(origin, rows=(1, 2, 3, 4, 5), gap=4.0, length=30.0, spacing=1.0, first=0.5)
    rng = np.random.default_rng(7)
    pts, cams_at, want = [], [], []
    for (s, u, n), r in zip(lines, layout):
        for k in range(120):
            side = 1.0 if sides == 1 or k % 2 else -1.0
            across = side * (0.5 + rng.uniform(-0.2, 0.2))
            p = s + rng.uniform(1.0, 29.0) * u + across * n  # along the rows nothing is shifted back
            pts.append(p)
            cams_at.append(p + 6.0 * side * n)
            want.append(r.row)
    s, u, n = lines[0]
    off = 1.6 * n + 0.6 * u
    P, C = np.array(pts) + off, np.array(cams_at) + off
    N = len(P)
    table = {"id": np.arange(N), "x": P[:, 0], "y": P[:, 1], "z": np.full(N, 2.0), "first_frame": np.arange(N),
             "last_frame": np.arange(N)}
    cams = {"frame": np.arange(N), "x": C[:, 0], "y": C[:, 1], "z": np.full(N, 14.0)}
    as_mapped = orchard_rows(table, layout, origin)[0]
    moved, moved_cams, shift = register_to_layout(table, cams, layout, origin)
    got = orchard_rows(moved, layout, origin)[0]
    found = np.array([shift["east_m"], shift["north_m"]])
    expect = 1.6 if sides == 2 else 2.1
    assert abs(found @ n - expect) < 0.05 and abs(found @ u) < 0.01, shift
    assert (sides == 2) == (shift["face_m"] is not None), shift
    if sides == 2:
        assert abs(abs(shift["face_m"]) - 0.5) < 0.05, shift
    assert np.mean(as_mapped != np.array(want)) > 0.2  # as mapped, apples fell in the next row's strip
    assert list(got) == want
    assert np.allclose(moved_cams["x"], C[:, 0] - shift["east_m"], atol=1e-3)
    assert np.array_equal(table["x"], P[:, 0])  # the map's own positions are left as they are


def test_readmes_yield_commands_as_written(replayed_test_flight, tmp_path):
    """README's "Yield" commands, as written, in a folder holding a finished map where they say (``out/demo``: the tiny
    flight's replay, its journal in it):
    - the layout from the map, its rows renumbered as a grower corrects them (31, 30, ...: the other way round);
    - the map made with it: rows.csv holds the layout's rows in its order, apples.csv each apple's layout row (0
      outside every row), trees.csv every tree, with what its canopy showed the camera (also in the recording);
      report.json says whose numbering it is;
    - choose-trees names trees of every row the camera saw, the apples column left to fill;
    - with the counts filled in, load gives the counted trees their counts, every other tree and each row a load
      inside its interval, each row its fruit's size and kilograms, report.json the flight's load;
    - `replay --sample-counts` gives the same loads live; counts of a tree the layout lacks stop it before it starts.
    """
    import csv
    import json
    from dataclasses import replace

    from ground.outputs.rrd_file import rrd_rows
    from pomar.layout import write_layout
    from tests.test_readme_commands import readme_commands, run

    _, out, rep = replayed_test_flight
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "demo").symlink_to(out)
    layout_cmd, plan_cmd, replay_cmd, choose_cmd, load_cmd = readme_commands("### Yield")
    r = run(layout_cmd, tmp_path)
    assert r.returncode == 0, r.stderr
    layout = tmp_path / "orchard.csv"
    rows = [replace(x, row=31 - k) for k, x in enumerate(read_layout(layout))]
    write_layout(rows, layout)
    # the next flight's plan over the layout: every tree of it from both sides (issue 72)
    r = run(plan_cmd, tmp_path)
    assert r.returncode == 0, r.stderr
    plan = json.loads((tmp_path / "out" / "plan" / "plan.json").read_text())
    n_trees = sum(len(tree_positions(x, Origin(rows[0].start[0], rows[0].start[1], 0.0))) for x in rows)
    assert plan["coverage"]["trees"] == n_trees == plan["coverage"]["trees_both_sides"], plan["coverage"]
    assert {w["row"] for f in plan["flights"] for w in f["waypoints"]} == {x.row for x in rows}
    r = run(replay_cmd, tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    got = tmp_path / "out" / "plot"
    read = lambda folder, name: list(csv.DictReader(open(folder / name)))  # noqa: E731
    # strict JSON: what is not known yet (the loads, before the hand counts) is null, not NaN
    report = json.loads((got / "report.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in report.json"))
    assert all(x["load"] is None for x in report["rows"])
    assert report["orchard"]["numbering"] == "layout" and report["orchard"]["layout"] == str(layout.resolve())
    assert rep["orchard"]["numbering"] == "map"  # without a layout, the map's own
    assert [int(x["row"]) for x in read(got, "rows.csv")] == [x.row for x in rows]
    apples = read(got, "apples.csv")
    assert {int(a["row"]) for a in apples} <= {x.row for x in rows} | {0}
    assert report["apples"] == rep["apples"] and report["orchard"]["apples_outside"] <= max(1, 0.05 * rep["apples"])
    assert sum(int(x["count"]) for x in read(got, "rows.csv")) == len(apples) - report["orchard"]["apples_outside"]
    origin = Origin(rows[0].start[0], rows[0].start[1], 0.0)
    trees = read(got, "trees.csv")
    assert len(trees) == sum(len(tree_positions(x, origin)) for x in rows)
    # what each tree's canopy showed the camera: a share in [0, 1], some trees seen, each row's the mean of its trees'
    cov = np.array([float(t["coverage"]) for t in trees])
    assert np.isfinite(cov).all() and (cov >= 0).all() and (cov <= 1).all() and (cov > 0).any(), cov
    for x in read(got, "rows.csv"):
        mine = [float(t["coverage"]) for t in trees if t["row"] == x["row"]]
        assert abs(float(x["coverage"]) - np.mean(mine)) < 1e-3
    assert report["orchard"]["coverage"]["trees"] == len(trees)
    last = rrd_rows(got / "flight.rrd", "/world/trees")["/world/trees"][-1]
    assert sorted(last["Points3D:labels"]) == sorted(f"row {t['row']} tree {t['tree']}: coverage "
                                                     f"{float(t['coverage']):.2f}" for t in trees)
    # the trees to count: every row has one (a row the camera never saw is known by its hand count alone), the rest
    # among the trees the camera saw
    r = run(choose_cmd, tmp_path)
    assert r.returncode == 0, r.stderr
    counts = tmp_path / "counts.csv"
    chosen = list(csv.DictReader(open(counts)))
    row_set = {t["row"] for t in trees}
    assert len(chosen) == min(10, len(trees)) and all(c["apples"] == "" for c in chosen)
    assert {c["row"] for c in chosen} == row_set if len(row_set) <= 10 else len({c["row"] for c in chosen}) == 10
    seen = {(t["row"], t["tree"]) for t in trees if float(t["coverage"]) > 0}
    assert sum((c["row"], c["tree"]) in seen for c in chosen) >= min(10 - len(row_set), len(seen)), chosen
    hand = {(int(c["row"]), int(c["tree"])): 20 + 7 * i for i, c in enumerate(chosen)}
    counts.write_text("row,tree,apples\n" + "".join(f"{a},{b},{n}\n" for (a, b), n in hand.items()))
    r = run(load_cmd, tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("load: "), r.stderr
    trees = read(got, "trees.csv")
    for t in trees:
        key, load, lo, hi = (int(t["row"]), int(t["tree"])), float(t["load"]), float(t["load_lo"]), float(t["load_hi"])
        if key in hand:
            assert int(t["hand_count"]) == hand[key] and load == lo == hi == hand[key], t
        else:
            assert t["hand_count"] == "nan" and 0 <= lo <= load <= hi, t
    plot_rows = read(got, "rows.csv")
    assert all(float(x["load_lo"]) <= float(x["load"]) <= float(x["load_hi"]) for x in plot_rows)
    sized = [x for x in plot_rows if x["diameter_mm"] != "nan"]
    assert sized and all(50 < float(x["diameter_mm"]) < 100 for x in sized)  # the truth's apples: 60-90 mm
    assert all(abs(float(x["kg"]) - float(x["load"]) * float(x["apple_kg"])) < 0.1 for x in sized)
    report = json.loads((got / "report.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in report.json"))
    assert report["load"]["model"] == "linear" and report["load"]["loo"]["trees"] == len(hand)
    # report.json's rows say what rows.csv says
    assert {x["row"]: (round(x["load"], 1), x["kg"] if x["kg"] is None else round(x["kg"], 1)) for x in report["rows"]} \
        == {int(x["row"]): (float(x["load"]), None if x["kg"] == "nan" else float(x["kg"])) for x in plot_rows}
    assert abs(report["load"]["flight"]["load"] - sum(float(x["load"]) for x in plot_rows)) < 1.0
    # more trees after a first sample (as `ground load` suggests): those counted are kept, with their counts
    k = min(len(trees), len(hand) + 4)
    more = choose_cmd.replace("--out counts.csv", f"--trees {k} --counted counts.csv --out more.csv")
    r = run(more, tmp_path)
    assert r.returncode == 0, r.stderr
    again = {(int(c["row"]), int(c["tree"])): c["apples"] for c in csv.DictReader(open(tmp_path / "more.csv"))}
    assert len(again) == k and all(again[key] == str(n) for key, n in hand.items()), again
    r = run(choose_cmd.replace("--out counts.csv", "--trees 3 --counted counts.csv --out few.csv"), tmp_path)
    assert r.returncode == 2 and r.stderr.strip() == f"error: --trees 3 is fewer than the {len(hand)} trees counts.csv " \
                                                     "has counted", r.stderr
    # the same loads live, from the recorded stream with the counts
    live = replay_cmd.replace("out/plot", "out/live") + " --sample-counts counts.csv"
    r = run(live, tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert {(t["row"], t["tree"]): t["load"] for t in read(tmp_path / "out" / "live", "trees.csv")} == \
        {(t["row"], t["tree"]): t["load"] for t in trees}
    # a tree the orchard does not have: one line naming the line, before anything starts
    counts.write_text(counts.read_text() + f"{rows[0].row},999,40\n")
    r = run(replay_cmd.replace("out/plot", "out/bad") + " --sample-counts counts.csv", tmp_path, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == f"error: counts.csv:{len(hand) + 2}: no tree 999 in row " \
                                                     f"{rows[0].row} in the orchard layout orchard.csv", r.stderr
    assert not (tmp_path / "out" / "bad").exists()
    # every counted tree empty: one line, exit 2, and the loads written before stay as they were
    before = (got / "trees.csv").read_text()
    counts.write_text("row,tree,apples\n" + "".join(f"{a},{b},0\n" for (a, b) in hand))
    r = run(load_cmd, tmp_path)
    assert r.returncode == 2 and r.stderr.strip() == (
        f"error: counts.csv: every one of the {len(hand)} trees counted by hand holds 0 apples: nothing relates the "
        "camera's count to a load (count trees that carry fruit)"), r.stderr
    assert (got / "trees.csv").read_text() == before


@pytest.mark.parametrize("scale", [1.0, 1.03])
def test_the_maps_row_spacing_is_measured_against_the_layouts_and_a_disagreement_is_said(scale):
    """Issue 75's row-spacing source: five made-up rows 4 m apart, apples on both faces, the map 3 % too large (or
    true). The map's spacing is measured within its stated 2 sigma, and 3 % off disagrees with the layout's beyond
    3 sigma of the measurement and a 0.5 % map scale together, where the true map agrees."""
    from ground.orchard.register import register_to_layout, spacing_check

    layout, origin, table, cams, _ = _spaced_map(scale)
    _, _, shift = register_to_layout(table, cams, layout, origin)
    assert shift["rows_measured"] == 5
    assert abs(shift["map_spacing_m"] - 4.0 * scale) < 2 * shift["map_spacing_sigma_m"], shift
    assert 0.005 < shift["map_spacing_sigma_m"] / 4.0 < 0.02, shift
    check = spacing_check(shift, 0.005)
    assert check["agrees"] == (scale == 1.0), check
    assert abs(check["factor"] - 1 / scale) < 0.015


def _spaced_map(scale: float, gap: float = 4.0):
    """Five made-up rows ``gap`` apart on their layout, apples on both faces and a camera beside each, the map
    ``scale`` times too large about their centre: (layout, origin, apple table, cameras, map-frame cameras)."""
    origin = Origin(-28.516, -50.8811, 20.0)
    layout, lines = _tilted_layout(origin, rows=(1, 2, 3, 4, 5), gap=gap, length=30.0, spacing=1.0, first=0.5)
    rng = np.random.default_rng(11)
    pts, cams_at = [], []
    for s, u, n in lines:
        for k in range(120):
            side = 1.0 if k % 2 else -1.0
            p = s + rng.uniform(1.0, 29.0) * u + side * (0.5 + rng.uniform(-0.2, 0.2)) * n
            pts.append(p)
            cams_at.append(p + 6.0 * side * n)
    centre = np.mean(pts, axis=0)
    P = centre + scale * (np.array(pts) - centre) + 0.7 * lines[0][2]
    C = centre + scale * (np.array(cams_at) - centre) + 0.7 * lines[0][2]
    N = len(P)
    table = {"id": np.arange(N), "x": P[:, 0], "y": P[:, 1], "z": np.full(N, 2.0), "first_frame": np.arange(N),
             "last_frame": np.arange(N)}
    cams = {"frame": np.arange(N), "x": C[:, 0], "y": C[:, 1], "z": np.full(N, 14.0)}
    return layout, origin, table, cams, np.column_stack([C, np.full(N, 14.0)])


@pytest.mark.parametrize("layout_gap,used", [(4.0, True), (4.6, False)])
def test_the_layouts_row_spacing_scales_the_whole_map_by_its_weight_and_a_disagreeing_one_is_left_out(layout_gap,
                                                                                                       used):
    """Issue 75: a map 3 % too large whose own scale says +-5 %, on a layout of rows 4 m apart: the row spacing
    (measured to about 1 %) joins the map's sources and the whole map shrinks about its cameras' centre by what the
    combination asks (its weight most of it), its positions and apple sizes alike; the scale's sigma falls and the
    report names the source. A layout whose rows lie 4.6 m apart disagrees with a map scale known to 0.5 %: it is
    left out, with why, and the map stays as it was."""
    from types import SimpleNamespace

    from ground.orchard.register import scaled_to_layout
    from ground.outputs.report import scale_figures
    from ground.outputs.snapshot import MapSnapshot
    from pomar.align import IDENTITY

    layout, origin, table, cams, C = _spaced_map(1.03, gap=4.0)
    if not used:
        layout, *_ = _spaced_map(1.0, gap=layout_gap)
    sigma = 5.0 if used else 0.5
    own = {"scale": 2.0, "sigma_pct": sigma,
           "sources": [{"name": "positions", "scale": 2.0, "sigma_pct": sigma, "stated": True, "weight": 1.0}]}
    snap = MapSnapshot(apples={}, counted_ids=[], size={}, frame_of=[], to_enu=IDENTITY, corrections=None,
                       poses={k: SimpleNamespace(centre=c) for k, c in enumerate(C)}, origin=origin, frame_times={},
                       metres_per_unit=0.5, scale=own)
    got = scaled_to_layout(snap, table, cams, layout)
    src = {s["name"]: s for s in got.scale["sources"]}
    assert set(src) == {"positions", "row_spacing"}
    f = got.to_enu.scale
    if used:
        rs = src["row_spacing"]
        assert rs["scale"] / 2.0 == pytest.approx(1 / 1.03, abs=0.015) and 0.5 < rs["sigma_pct"] < 2.0, rs
        w = rs["weight"]
        assert w > 0.9 and got.scale["sigma_pct"] < rs["sigma_pct"]
        assert np.log(f) == pytest.approx(w * np.log(rs["scale"] / 2.0), rel=1e-9)  # the combination's, no more
        assert got.scale["scale"] == pytest.approx(2.0 * f) and got.metres_per_unit == pytest.approx(0.5 * f)
        assert np.allclose(got.to_enu.apply(C).mean(0), C.mean(0))  # held where the GPS holds it
        assert scale_figures(got.scale)["georeference_scale_from"] == "row_spacing"
    else:
        assert f == 1.0 and got.metres_per_unit == 0.5 and got.scale["scale"] == 2.0
        assert "disagrees" in src["row_spacing"]["left_out"] and src["row_spacing"]["weight"] == 0.0
    assert scale_figures(None) == {}


def test_a_row_seen_from_nearly_above_does_not_bend_the_rows_spacing():
    """One pass beside five rows 4 m apart, 12 m above their apples, looking across them: the four rows it looks at
    from the side show their near face, the row 1.5 m beside its track its far face (the camera looks down over its
    top). That row's apples tell no side (FACE_MIN_RUN): the spacing is measured within 2 sigma of 4 m, where taking
    its side from the camera's would have put it about half a canopy off."""
    from ground.orchard.register import FACE_MIN_RUN, register_to_layout

    origin = Origin(-28.516, -50.8811, 20.0)
    layout, lines = _tilted_layout(origin, rows=(1, 2, 3, 4, 5), gap=4.0, length=30.0, spacing=1.0, first=0.5)
    rng = np.random.default_rng(5)
    track = lines[0][0] - 1.5 * lines[0][2]  # 1.5 m outside row 1, looking across rows 1-5
    pts, cams_at = [], []
    for i, (s, u, n) in enumerate(lines):
        for _ in range(150):
            along = rng.uniform(1.0, 29.0)
            face = 1.0 if i == 0 else -1.0  # row 1: its far face from the camera; the others their near face
            # each row's own face offset varies a little (vigour, pruning)
            pts.append(s + along * u + face * (0.5 + rng.uniform(-0.1, 0.1)) * n)
            cams_at.append(track + along * lines[0][1])
    P, C = np.array(pts), np.array(cams_at)
    assert abs((C[0] - P[0]) @ lines[0][2]) < FACE_MIN_RUN * 12.0 < abs((C[-1] - P[-1]) @ lines[0][2])
    N = len(P)
    table = {"id": np.arange(N), "x": P[:, 0], "y": P[:, 1], "z": np.full(N, 2.0), "first_frame": np.arange(N),
             "last_frame": np.arange(N)}
    cams = {"frame": np.arange(N), "x": C[:, 0], "y": C[:, 1], "z": np.full(N, 14.0)}
    _, _, shift = register_to_layout(table, cams, layout, origin)
    assert shift["rows_measured"] == 4, shift
    assert abs(shift["map_spacing_m"] - 4.0) < 2 * shift["map_spacing_sigma_m"], shift


def test_two_rows_each_seen_from_its_own_side_give_no_spacing_rather_than_an_error():
    """Two rows, one seen from its left, the other from its right: the spacing and the two faces' offsets cannot be
    told apart (three unknowns, two places), so no spacing is measured, where the fit used to raise on a singular
    matrix."""
    from ground.orchard.register import map_spacing

    rng = np.random.default_rng(2)
    across = np.concatenate([0.3 + rng.normal(0, 0.05, 40), 4.0 - 0.3 + rng.normal(0, 0.05, 40)])
    side = np.concatenate([np.ones(40), -np.ones(40)])
    got = map_spacing(across, side, 0.0, 4.0)
    assert got["rows"] == 2 and np.isnan(got["map_m"]) and np.isnan(got["sigma_m"])
    # the same rows each seen from both sides measure it
    both = map_spacing(np.concatenate([across, across[:40] - 0.6, across[40:] + 0.6]),
                       np.concatenate([side, -np.ones(40), np.ones(40)]), 0.0, 4.0)
    assert abs(both["map_m"] - 4.0) < 0.05


def test_each_pass_that_films_the_rows_ends_is_placed_along_them_on_its_own():
    """Issue 72: a plan's serpentine, each pass flown past both ends of the rows and placed by its own stretch of
    GPS: the first pass's map lies 2.0 m ahead along the rows, the second 2.5 m behind (a sub-model each). Each pass
    is placed along the rows by where its apples start and stop, within 0.3 m, so that the apples go to their own
    trees; a pass that stops inside the rows is left where it is."""
    from ground.orchard.assign import apple_places
    from ground.orchard.register import register_to_layout

    origin = Origin(-28.516, -50.8811, 20.0)
    layout, lines = _tilted_layout(origin, rows=(1, 2, 3), gap=4.0, length=20.0, spacing=1.0, first=0.5)
    rng = np.random.default_rng(5)
    u, n = lines[0][1], lines[0][2]
    table = {k: [] for k in ("x", "y", "z", "first_frame", "last_frame")}
    cams = {k: [] for k in ("frame", "x", "y", "z")}
    truth_tree, frame = [], 0

    def fly(across, start, stop, offset, rows, look):
        nonlocal frame
        f0 = frame
        for t in np.linspace(start, stop, 60):  # the pass's cameras, shifted along the rows by its GPS's offset
            c = lines[0][0] + t * u + across * n + offset * u
            cams["frame"].append(frame), cams["x"].append(c[0]), cams["y"].append(c[1]), cams["z"].append(12.0)
            frame += 1
        for r in rows:
            s = lines[r][0]
            for _ in range(150):
                tree = int(rng.integers(0, 20))
                p = s + (0.5 + tree + rng.uniform(-0.4, 0.4)) * u + look * 0.4 * n + offset * u
                f = int(rng.integers(f0 + 5, frame - 5))
                table["x"].append(p[0]), table["y"].append(p[1]), table["z"].append(2.0)
                table["first_frame"].append(f - 2), table["last_frame"].append(f + 2)
                truth_tree.append(tree + 1)

    fly(-3.0, -4.0, 24.0, 2.0, [0], 1.0)     # along the first row's near face, past both its ends
    fly(2.0, 24.0, -4.0, -2.5, [0, 1], -1.0)  # back between rows 1 and 2
    fly(6.0, 3.0, 17.0, 1.5, [1, 2], -1.0)   # a third pass that stops inside the rows: not placed along them
    tab = {k: np.array(v, float) for k, v in table.items()}
    tab["id"] = np.arange(len(truth_tree))
    tab["first_frame"], tab["last_frame"] = tab["first_frame"].astype(int), tab["last_frame"].astype(int)
    cam = {k: np.array(v, float) for k, v in cams.items()}
    cam["frame"] = cam["frame"].astype(int)
    moved, moved_cams, record = register_to_layout(tab, cam, layout, origin)
    passes = record["passes"]
    assert len(passes) == 3 and [p["rows"] for p in passes] == [1, 2, 0], passes
    assert abs(passes[0]["along_m"] - 2.0) < 0.3 and abs(passes[1]["along_m"] + 2.5) < 0.3, passes
    assert passes[2]["along_m"] is None
    _, tree, _ = apple_places(moved, layout, origin)
    first_two = np.arange(len(truth_tree)) < 150 + 300
    assert np.mean(tree[first_two] == np.array(truth_tree)[first_two]) > 0.9
    _, tree_before, _ = apple_places(tab, layout, origin)
    assert np.mean(tree_before[first_two] == np.array(truth_tree)[first_two]) < 0.2
    # the cameras move with their pass
    mine = slice(passes[0]["first_frame"], passes[0]["last_frame"] + 1)
    assert passes[0]["first_frame"] == 0 and passes[0]["last_frame"] > 50
    c0 = np.column_stack([cam["x"], cam["y"]])[mine] @ u
    assert np.allclose(np.column_stack([moved_cams["x"], moved_cams["y"]])[mine] @ u, c0 - passes[0]["along_m"])
