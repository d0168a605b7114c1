"""The flight plan (pomar/plan.py, issue 72) on made-up orchards whose answer follows from geometry: every tree filmed
from both sides at the detector's apple size, the speed from the views and the blur, whole rows per battery, and one
line for what cannot be planned."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pomar.apple_scale import expected_radius_px
from pomar.assemble import camera_for
from pomar.coverage import Sight, tree_coverage
from pomar.drones import DRONES
from pomar.geo import Origin
from pomar.layout import LayoutRow, write_layout
from pomar.plan import PlanSettings, flight_time_s, layout_trees_enu, make_plan, plan_cameras

ROOT = Path(__file__).resolve().parents[1]
DETECTOR = {"apple_radius_px": 5.4, "min_apple_radius_px": 3.0}
NS = {"k": "http://www.opengis.net/kml/2.2", "w": "http://www.dji.com/wpmz/1.0.2"}


def _layout(rows=6, length=30.0, gap=4.0, azimuth_deg=140.0, spacing=1.0):
    """Rows ``gap`` m apart, ``length`` m long, running ``azimuth_deg`` from north, numbered 1..rows."""
    origin = Origin(-28.516, -50.8811, 0.0)
    a = np.radians(azimuth_deg)
    u, n = np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])
    out = []
    for k in range(rows):
        s, e = k * gap * n, k * gap * n + length * u
        (la, lo, _), (lb, lob, _) = origin.to_geodetic(np.array([[*s, 0.0], [*e, 0.0]]))
        out.append(LayoutRow(k + 1, (float(la), float(lo)), (float(lb), float(lob)), spacing, spacing / 2))
    return out


def _camera(drone):
    return camera_for(drone.camera, drone.video_width, drone.video_height)[0]


def test_a_plan_films_every_tree_from_both_sides_at_the_detectors_size():
    """Six rows of 30 trees, a Phantom 4 Pro: two passes a row; the apples at the detector's 5.4 px (by the geometry
    the onboard node foresees them with), every tree's expected coverage 1 from both sides, where one pass (the
    flight a grower flies today) sees one side of a few rows; the speed is the slowest of the views' (5 frames at the
    detector's rate), the blur's (1 px at the shutter) and the drone's own."""
    drone = DRONES["phantom-4-pro"]
    cam = _camera(drone)
    layout = _layout()
    plan = make_plan(layout, cam, drone, DETECTOR, PlanSettings(fps=2.0), "phantom-4-pro")
    g, sp = plan.geometry, plan.speed
    assert len(plan.flights) == 1 and len(plan.flights[0]) == 12
    assert expected_radius_px(cam.fx, g["height_m"], 30.0) == pytest.approx(5.4, rel=1e-6)
    assert g["height_m"] > 3.0 + 2.0 and g["offset_m"] > 0.5
    cov = np.array([t["coverage"] for t in plan.trees])
    assert len(cov) == 6 * 30 and cov.min() >= 0.9 and all(t["sides_seen"] == 2 for t in plan.trees)
    # the speed: an apple crosses the frame's width at the face (width x range / fx) in that over the speed
    footprint = cam.width * g["range_m"] / cam.fx
    by_views, by_blur = 2.0 * footprint / 5, 1.0 * g["range_m"] / (cam.fx * drone.shutter_s)
    assert sp["speed_mps"] == pytest.approx(min(by_views, by_blur, drone.max_speed_mps))
    assert sp["views"] >= 5 - 1e-9 and sp["blur_px"] <= 1 + 1e-9
    # one pass along the first row's right-hand side, as flown today: one side of few rows
    one = make_plan(layout[:1], cam, drone, DETECTOR, PlanSettings(fps=2.0))
    p = [q for q in one.flights[0] if q.side == -1]
    cams = plan_cameras([p], sp["speed_mps"], 2.0, g["height_m"], 60.0)
    rows, trees = layout_trees_enu(layout, plan.origin)
    none = {k: np.zeros(0) for k in ("id", "x", "y", "z", "row")}
    from pomar.coverage import DEFAULT_HEDGE

    got = tree_coverage(trees, rows, none, cams, Sight(cam, min_px=3.0), default_hedge=DEFAULT_HEDGE)
    one_cov = np.array([c["coverage"] for c in got])
    assert one_cov.mean() <= 0.5 and not any(c["sides_seen"] == 2 for c in got)


def test_a_plan_one_battery_cannot_fly_is_split_into_flights_of_whole_rows():
    """Ten rows of 400 m on a generic quad (20 min a battery, 70 % of it used): several flights, each within the
    battery, each holding both passes of its rows, every row in one of them."""
    drone = DRONES["generic-quad"]
    plan = make_plan(_layout(rows=10, length=400.0), _camera(drone), drone, DETECTOR, PlanSettings())
    assert len(plan.flights) >= 2
    seen = []
    for passes, minutes in zip(plan.flights, plan.minutes):
        assert minutes * 60 <= drone.usable_s + 1e-6
        rows = [p.row for p in passes]
        assert all(rows.count(r) == 2 for r in set(rows))
        assert minutes * 60 == pytest.approx(flight_time_s(passes, plan.speed["speed_mps"], plan.geometry["height_m"],
                                                           drone))
        seen += sorted(set(rows))
    assert sorted(seen) == list(range(1, 11))


def test_plan_command_writes_the_plan_and_refuses_what_cannot_be_planned(tmp_path):
    """`python -m pomar plan` as the README gives it: plan.json and coverage.csv; then an unknown drone, a row the
    layout lacks and a legal height under the canopy: one line each naming the file and what is wrong, exit 2, and
    nothing written."""
    orchard = tmp_path / "orchard.csv"
    write_layout(_layout(rows=3), orchard)
    out = tmp_path / "plan"
    r = subprocess.run([sys.executable, "-m", "pomar", "plan", str(orchard), "--camera", "phantom-4-pro", "--drone",
                        "phantom-4-pro", "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    d = json.loads((out / "plan.json").read_text())
    assert d["format"] == "pomar-plan/1" and d["batteries"] == 1 and d["coverage"]["trees_both_sides"] == 90
    assert "above the take-off point" in d["heights"] and len(d["flights"][0]["waypoints"]) == 12
    lines = (out / "coverage.csv").read_text().splitlines()
    assert lines[0].startswith("row,tree,lat,lon,coverage") and len(lines) == 91
    assert "2 passes" not in r.stdout and "6 passes" in r.stdout and "from both sides" in r.stdout
    import cv2

    png = cv2.imread(str(out / "plan.png"))  # the picture to check at a glance: trees coloured, passes drawn
    assert png is not None and min(png.shape[:2]) > 300 and len(np.unique(png.reshape(-1, 3), axis=0)) > 10
    for extra, says in ((["--drone", "dji-x"], "dji-x: not a drone this tool knows"),
                        (["--drone", "mavic-3", "--rows", "7"], f"{orchard}: --rows: the layout has no row 7"),
                        (["--drone", "mavic-3", "--max-height", "4"], f"{orchard}: a height of 4.0 m is below the "
                                                                      "canopy's top")):
        bad = tmp_path / "bad"
        r = subprocess.run([sys.executable, "-m", "pomar", "plan", str(orchard), "--out", str(bad), *extra],
                           capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and says in r.stderr, r.stderr
        assert not bad.exists()


def test_a_boundary_keeps_the_flight_inside_and_says_what_it_costs(tmp_path):
    """Three rows of 30 m, a boundary (GeoJSON) drawn across the rows 20 m from their start: every waypoint lies inside
    it, each pass stops short of its row's end and says so, and the trees past the line are named as not seen from
    both sides, a line a row; the trees well inside keep both sides. A boundary the rows lie wholly outside, and files
    that are no polygon: one line naming the file, exit 2, nothing written."""
    from pomar.boundary import inside

    layout = _layout(rows=3)
    origin = Origin(-28.516, -50.8811, 0.0)
    a = np.radians(140.0)
    u, n = np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])
    corners = [-30 * u - 20 * n, 8 * u - 20 * n, 8 * u + 30 * n, -30 * u + 30 * n]  # the rows' first 8 m, and more
    ll = [origin.to_geodetic(np.array([[*c, 0.0]]))[0] for c in corners]
    ring = [[float(lo), float(la)] for la, lo, _ in ll]
    fence = tmp_path / "fence.geojson"
    fence.write_text(json.dumps({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring + ring[:1]]}}))
    orchard = tmp_path / "orchard.csv"
    write_layout(layout, orchard)
    out = tmp_path / "plan"
    r = subprocess.run([sys.executable, "-m", "pomar", "plan", str(orchard), "--drone", "phantom-4-pro", "--boundary",
                        str(fence), "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    d = json.loads((out / "plan.json").read_text())
    poly = np.array(corners)
    wps = np.array([np.asarray(origin.to_enu(w["lat"], w["lon"], 0.0))[:2] for f in d["flights"] for w in f["waypoints"]])
    assert inside(poly * 1.001, wps).all(), wps
    stops = [x for x in d["problems"] if "stops its pass" in x and "row's end" in x]
    assert len(stops) == 6, d["problems"]  # both sides of three rows
    lost = [x for x in d["problems"] if "not seen from both sides" in x]
    assert len(lost) == 3 and all(x in r.stdout for x in d["problems"]), (d["problems"], r.stdout)
    assert not [x for x in d["problems"] if "hop" in x]  # a convex boundary holds every hop between its waypoints
    cov = {(int(t["row"]), int(t["tree"])): int(t["sides_seen"]) for t in csv.DictReader(open(out / "coverage.csv"))}
    assert all(cov[(k, t)] == 2 for k in (1, 2, 3) for t in range(1, 9)) and cov[(2, 30)] < 2
    # a boundary the rows lie outside, a file that is no polygon, one with two vertices
    far = [[lo + 0.01, la] for lo, la in ring]
    away = tmp_path / "away.geojson"
    away.write_text(json.dumps({"type": "Polygon", "coordinates": [far]}))
    line = tmp_path / "line.csv"
    line.write_text("lat,lon\n-28.516,-50.8811\n-28.517,-50.8811\n")
    text = tmp_path / "notes.geojson"
    text.write_text("the north fence")
    for bad_file, says in ((away, "no pass of the rows asked lies inside the boundary"),
                           (line, f"{line}: a boundary needs 3 or more positions"),
                           (text, f"{text}: not JSON")):
        bad = tmp_path / "bad"
        r = subprocess.run([sys.executable, "-m", "pomar", "plan", str(orchard), "--drone", "phantom-4-pro",
                            "--boundary", str(bad_file), "--out", str(bad)], capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and says in r.stderr, r.stderr
        assert not bad.exists()


def test_a_hop_between_passes_that_leaves_a_notched_boundary_is_named():
    """Two passes 4 m apart whose rows end by a notch cut into the boundary: the hop from one's end to the next's start
    crosses the notch (2 m of it outside), which no waypoint shows; the plan names that hop, and no other."""
    from pomar.plan import Pass, hops_outside

    look = np.array([0.0, 1.0])
    a = Pass(1, 1, np.array([0.0, 0.0]), np.array([30.0, 0.0]), look)
    b = Pass(1, -1, np.array([30.0, 4.0]), np.array([0.0, 4.0]), -look)
    c = Pass(2, 1, np.array([0.0, 5.0]), np.array([30.0, 5.0]), look)
    notched = np.array([[-5, -2], [35, -2], [35, 1], [28, 1], [28, 3], [35, 3], [35, 6], [-5, 6]], float)
    lines = hops_outside([[a, b, c]], notched, "fence.csv")
    assert lines == ["flight 1: the hop from row 1's left side to row 1's right side leaves the boundary fence.csv "
                     "for 2.0 m: fly it by hand, or add a waypoint"]
    box = np.array([[-5, -2], [35, -2], [35, 6], [-5, 6]], float)
    assert hops_outside([[a, b, c]], box, "fence.csv") == []


def test_each_flight_is_written_for_the_apps_and_reads_back(tmp_path):
    """A plan of two flights (a generic quad over long rows): each as QGroundControl's .plan (its documented fields,
    SimpleItems, heights above take-off), as QGC WPL 110 (loaded by pymavlink's mavwp) and as Litchi's CSV (its
    documented columns): the same passes at the plan's height, speed and gimbal pitch, the video started once and
    stopped once, home in the end."""
    from pymavlink import mavwp

    from pomar.plan import write_plan
    from pomar.plan_export import (LITCHI_COLUMNS, NAV_RETURN_TO_LAUNCH, NAV_TAKEOFF, NAV_WAYPOINT, VIDEO_START_CAPTURE,
                                   VIDEO_STOP_CAPTURE)

    drone = DRONES["generic-quad"]
    plan = make_plan(_layout(rows=4, length=400.0), _camera(drone), drone, DETECTOR, PlanSettings())
    assert len(plan.flights) >= 2
    write_plan(plan, tmp_path)
    d = plan.as_dict()
    h = plan.geometry["height_m"]
    for k, f in enumerate(d["flights"]):
        q = json.loads((tmp_path / f"flight-{k + 1}.plan").read_text())
        assert q["fileType"] == "Plan" and q["version"] == 1 and q["groundStation"] == "QGroundControl"
        m = q["mission"]
        assert m["version"] == 2 and m["firmwareType"] in (3, 12) and len(m["plannedHomePosition"]) == 3
        items = m["items"]
        assert all(i["type"] == "SimpleItem" and len(i["params"]) == 7 and i["autoContinue"] for i in items)
        assert [i["doJumpId"] for i in items] == list(range(1, len(items) + 1))
        assert items[0]["command"] == NAV_TAKEOFF and items[-1]["command"] == NAV_RETURN_TO_LAUNCH
        nav = [i for i in items if i["command"] == NAV_WAYPOINT]
        assert len(nav) == len(f["waypoints"]) and all(i["frame"] == 3 and i["AltitudeMode"] == 1 for i in nav)
        assert all(abs(i["params"][6] - h) < 1e-9 for i in nav)
        assert [(i["params"][4], i["params"][5]) for i in nav] == [(w["lat"], w["lon"]) for w in f["waypoints"]]
        cmds = [i["command"] for i in items]
        assert cmds.count(VIDEO_START_CAPTURE) == 1 and cmds.count(VIDEO_STOP_CAPTURE) == 1
        loader = mavwp.MAVWPLoader()
        n = loader.load(str(tmp_path / f"flight-{k + 1}.waypoints"))
        assert n == len(items) + 1  # home, then the mission
        back = [loader.wp(j) for j in range(1, n)]
        assert [w.command for w in back] == cmds
        assert [(round(w.x, 6), round(w.y, 6)) for w in back if w.command == NAV_WAYPOINT] == \
            [(round(w["lat"], 6), round(w["lon"], 6)) for w in f["waypoints"]]
        rows = list(csv.DictReader(open(tmp_path / f"flight-{k + 1}.litchi.csv")))
        assert list(rows[0]) == LITCHI_COLUMNS and len(rows) == len(f["waypoints"])
        assert all(r["altitudemode"] == "0" and float(r["altitude(m)"]) == pytest.approx(h, abs=0.01) for r in rows)
        assert all(float(r["gimbalpitchangle"]) == -60.0 for r in rows)
        assert rows[0]["action1type"] == "2" and rows[-1]["action1type"] == "3"
        assert float(rows[0]["speed(m/s)"]) == pytest.approx(plan.speed["speed_mps"], abs=0.01)
        # DJI Pilot 2's KMZ: both documents parse as XML, the same waypoints, heights relative to the start point
        with zipfile.ZipFile(tmp_path / f"flight-{k + 1}.kmz") as z:
            assert sorted(z.namelist()) == ["wpmz/template.kml", "wpmz/waylines.wpml"]
            for name, height_tag in (("wpmz/template.kml", "height"), ("wpmz/waylines.wpml", "executeHeight")):
                root = ET.fromstring(z.read(name))
                marks = root.findall(".//k:Placemark", NS)
                assert len(marks) == len(f["waypoints"])
                lonlat = [tuple(map(float, m.find("k:Point/k:coordinates", NS).text.split(","))) for m in marks]
                assert np.allclose(lonlat, [(w["lon"], w["lat"]) for w in f["waypoints"]], atol=1e-8)
                assert all(float(m.find(f"w:{height_tag}", NS).text) == pytest.approx(h, abs=0.01) for m in marks)
                assert "relativeToStartPoint" in z.read(name).decode()
                funcs = [a.text for a in root.iter(f"{{{NS['w']}}}actionActuatorFunc")]
                assert funcs.count("startRecord") == 1 and funcs.count("stopRecord") == 1


def test_plan_render_replay_combine_load_end_to_end(tmp_path):
    """A small simulated orchard (2 rows of 8 m), planned on its layout before any flight (`sim layout --config`) for
    a drone of one short battery, so that the plan is two flights of a row each; each flight flown by the simulator
    (`sim flight --plan --plan-flight`: its lines, height, speed and pitch), replayed with the layout, the two maps
    combined (`ground combine`), and the combined map's loads calibrated by hand counts of four trees: every tree of
    both rows seen from both sides, as the plan said, no apple counted twice, and each video as long as its passes."""
    cfg = tmp_path / "orchard.toml"
    cfg.write_text('seed = 7301\nflight_id = "plan-e2e"\n[orchard]\nrows = 2\nrow_length_m = 8.0\n[apples]\n'
                   'per_tree = 12.0\n[flight]\nfps = 3.0\n[camera]\nwidth = 1280\nheight = 720\nhfov_deg = 50.0\n')
    drone = tmp_path / "drone.json"  # a battery for one row's two passes (0.6 min of 0.9 usable), not two rows'
    drone.write_text(json.dumps({"name": "short-battery", "what": "a test drone", "battery_min": 1.3,
                                 "max_speed_mps": 10.0, "min_speed_mps": 0.5, "climb_mps": 3.0,
                                 "camera": "phantom-4-pro", "video_width": 1280, "video_height": 720,
                                 "video_fps": 30.0}))
    py = [sys.executable, "-m"]

    def ok(*cmd, timeout=600):
        r = subprocess.run([*py, *map(str, cmd)], capture_output=True, text=True, cwd=ROOT, timeout=timeout)
        assert r.returncode == 0, (cmd, r.stderr[-2000:])
        return r

    ok("sim", "layout", "--config", cfg, "--out", tmp_path / "orchard.csv")
    from pomar.camera import Camera
    from pomar.flight import FlightDir

    Camera.from_fov(1280, 720, 50.0).save(tmp_path / "camera.json")
    ok("pomar", "plan", tmp_path / "orchard.csv", "--drone", drone, "--camera", tmp_path / "camera.json",
       "--fps", "3", "--shutter-s", "0.004", "--out", tmp_path / "plan")
    plan = json.loads((tmp_path / "plan" / "plan.json").read_text())
    assert plan["coverage"]["trees_both_sides"] == plan["coverage"]["trees"] == 16 and len(plan["flights"]) == 2
    maps = []
    for n, flight in enumerate(plan["flights"], start=1):
        ok("sim", "flight", "--config", cfg, "--plan", tmp_path / "plan" / "plan.json", "--plan-flight", n,
           "--out", tmp_path / f"flight-{n}", "--quiet")
        # the video: the plan's path (its passes and the hops between them) at the plan's speed, within 10 %
        meta = FlightDir(tmp_path / f"flight-{n}").meta()
        o = Origin(plan["origin"]["lat"], plan["origin"]["lon"], 0.0)
        path = np.array([o.to_enu(w["lat"], w["lon"], 0.0)[:2] for w in flight["waypoints"]])
        path_s = np.linalg.norm(np.diff(path, axis=0), axis=1).sum() / plan["speed_mps"]
        assert abs(meta.frame_count / meta.fps / path_s - 1) < 0.1, (n, meta.frame_count / meta.fps, path_s)
        ok("ground", "replay", tmp_path / f"flight-{n}", "--orchard", tmp_path / "orchard.csv", "--out",
           tmp_path / f"map-{n}", timeout=900)
        maps.append(tmp_path / f"map-{n}")
    ok("ground", "combine", *maps, "--out", tmp_path / "map")
    trees = list(csv.DictReader(open(tmp_path / "map" / "trees.csv")))
    assert len(trees) == 16 and all(int(t["sides_seen"]) == 2 for t in trees), [t["sides_seen"] for t in trees]
    # each face of each tree from one flight: the combined count is each face's count in the map that gave it
    apples = [list(csv.DictReader(open(m / "apples.csv"))) for m in maps]
    combined = list(csv.DictReader(open(tmp_path / "map" / "apples.csv")))
    for t in trees:
        for side in ("left", "right"):
            mine = [a for a in combined if (a["row"], a["tree"], a["side"]) == (t["row"], t["tree"], side)]
            given = {a["flight"] for a in mine}
            assert len(given) <= 1
            if given:
                k = int(given.pop()) - 1
                assert len(mine) == sum((a["row"], a["tree"], a["side"]) == (t["row"], t["tree"], side)
                                        for a in apples[k])
    assert sum(int(t["count"]) for t in trees) == len(combined) <= sum(len(a) for a in apples)
    ok("sim", "counts", tmp_path / "flight-1", "--out", tmp_path / "counts.csv", "--trees", "1:2", "1:6", "2:3", "2:7")
    ok("ground", "load", tmp_path / "map", "--sample-counts", tmp_path / "counts.csv")
    rows = list(csv.DictReader(open(tmp_path / "map" / "rows.csv")))
    assert [r["row"] for r in rows] == ["1", "2"] and all(float(r["load"]) > 0 for r in rows)


def test_a_plan_from_another_tool_or_edited_into_nonsense_is_refused_in_one_line(tmp_path):
    """`sim flight --plan`: a QGroundControl .plan given as plan.json, a plan whose height was edited to -5 and one
    whose passes lost a waypoint: one line naming the file and what is wrong, exit 2, no flight written."""
    orchard = tmp_path / "orchard.csv"
    write_layout(_layout(rows=2, length=10.0), orchard)
    r = subprocess.run([sys.executable, "-m", "pomar", "plan", str(orchard), "--drone", "mavic-3", "--out",
                        str(tmp_path / "p")], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    good = json.loads((tmp_path / "p" / "plan.json").read_text())
    cases = {"qgc.json": ((tmp_path / "p" / "flight-1.plan").read_text(), "not a plan of python -m pomar plan"),
             "height.json": (json.dumps({**good, "height_m": -5}), "out of range"),
             "odd.json": (json.dumps({**good, "flights": [{**good["flights"][0],
                                                            "waypoints": good["flights"][0]["waypoints"][:-1]}]}),
                          "waypoints in pairs")}
    for name, (text, says) in cases.items():
        (tmp_path / name).write_text(text)
        out = tmp_path / f"flight-{name}"
        r = subprocess.run([sys.executable, "-m", "sim", "flight", "--plan", str(tmp_path / name), "--out", str(out)],
                           capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert str(tmp_path / name) in r.stderr and says in r.stderr, r.stderr
        assert not out.exists()
