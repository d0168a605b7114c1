"""What the grower sees in rerun: the recording read back from its .rrd (lines inside their image, boxes only with
their image, the summary and per-row series matching the map files) and the layout's panels."""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest

from ground.outputs.tables import PALETTE, row_colours
from ground.outputs.rerun_log import PANELS, RerunLog, blueprint, clip_segment, epipolar_segments
from ground.outputs.rrd_file import rrd_rows


def _rgb(packed: int) -> list[int]:
    """rerun's colour component, 0xRRGGBBAA, as [r, g, b]."""
    return [(packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255]


def _views(container) -> list:
    import rerun.blueprint as rrb

    out = []
    for c in container.contents:
        out += _views(c) if isinstance(c, rrb.Container) else [c]
    return out


def test_a_row_too_short_for_a_density_shows_a_dash_not_nan():
    from ground.outputs.summary import summary_markdown

    text = summary_markdown({"apples": 3, "rows": [{"row": 1, "count": 3, "apples_per_m": float("nan"), "length_m": 0.2}]},
                            {})
    assert "| row 1 | 3 | – | 0 m |" in text and "nan" not in text


def test_the_plots_share_one_time_axis_from_the_first_frame():
    """Every time-series panel spans the flight from frame 0 to the frame shown, whichever series started later."""
    import rerun.blueprint as rrb

    series = [v for v in _views(blueprint().root_container) if isinstance(v, rrb.TimeSeriesView)]
    assert len(series) == 3
    for v in series:
        ranges = v.properties["VisibleTimeRanges"].ranges.as_arrow_array().to_pylist()
        assert [(r["timeline"], r["range"]["start"]) for r in ranges] == [("frame", 0)], (v.name, ranges)


def test_layout_names_its_panels():
    names = [v.name for v in _views(blueprint().root_container)]
    assert sorted(names) == sorted(PANELS)
    # a second layout, once the ground and the rows are known: the same panels
    names = [v.name for v in _views(blueprint(-12.0, ((0.0, -20.0, 5.0), (0.0, 0.0, -10.0))).root_container)]
    assert sorted(names) == sorted(PANELS)


def test_epipolar_lines_are_clipped_on_all_four_sides():
    rng = np.random.default_rng(3)
    w, h = 640.0, 360.0
    kept = 0
    for _ in range(200):
        F = rng.normal(size=(3, 3))
        xy = rng.uniform([0, 0], [w, h], size=(5, 2))
        for x in xy:
            segs = epipolar_segments(F, x[None], w, h)
            if not segs:
                continue
            (p, q), = segs
            kept += 1
            for pt in (p, q):
                assert -1e-6 <= pt[0] <= w + 1e-6 and -1e-6 <= pt[1] <= h + 1e-6, (p, q)
            # both ends lie on the point's epipolar line
            a, b, c = F @ [*x, 1.0]
            assert abs(a * p[0] + b * p[1] + c) / np.hypot(a, b) < 1e-6
            assert abs(a * q[0] + b * q[1] + c) / np.hypot(a, b) < 1e-6
    assert kept > 100
    # a nearly vertical line through the image, and one that misses it
    assert clip_segment(np.array([100.0, -1e5]), np.array([100.1, 1e5]), w, h)[:, 1].tolist() == pytest.approx([0, h])
    assert clip_segment(np.array([-10.0, -1e5]), np.array([-10.0, 1e5]), w, h) is None


class _Pose:
    def __init__(self, R, centre):
        self.R, self.centre, self.t = R, centre, -R @ centre


class _Msg:
    def __init__(self, boxes):
        self.boxes = boxes
        self.centres = (boxes[:, :2] + boxes[:, 2:]) / 2


class _Event:
    def __init__(self, frame, pose, msg, keyframe):
        self.frame, self.t_capture, self.pose, self.msg, self.keyframe = frame, 1.7e9 + frame / 10, pose, msg, keyframe
        self.new_apples = []


def test_boxes_only_with_their_image_and_lines_inside_it(tmp_path):
    """Frames with and without images, poses looking down at a flat scene: every box is logged on a frame whose
    image was logged, and every 2-D line lies inside the image."""
    from pomar.camera import Camera

    cam = Camera(640, 360, 500.0, 500.0, 320.0, 180.0)
    jpeg = cv2.imencode(".jpg", np.full((180, 320, 3), 90, np.uint8))[1].tobytes()  # half-size images
    R = np.diag([1.0, -1.0, -1.0])  # looking straight down
    rng = np.random.default_rng(0)
    rrd = tmp_path / "t.rrd"
    rl = RerunLog("test-flight", rrd)
    for f in range(12):
        boxes = rng.uniform([0, 0], [600, 340], size=(6, 2))
        boxes = np.hstack([boxes, boxes + 8]).astype(np.float32)
        rl.frame(_Event(f, _Pose(R, np.array([0.2 * f, 0.05 * f, 10.0])), _Msg(boxes), jpeg if f % 2 == 0 else None),
                 cam, {"rate/ground": 3.0})
        if f == 9:
            rl.apple_views(7, [(4, boxes[0]), (6, boxes[1]), (7, boxes[2]), (8, boxes[3])])
    rl.close()
    data = rrd_rows(rrd, "/world/camera")
    image_frames = {r["frame"] for r in data["/world/camera/image"]}
    assert image_frames == set(range(0, 12, 2))
    for path in ("/world/camera/image/detections", "/world/camera/image/epipolar/7"):
        box_frames = {r["frame"] for r in data[path] if r.get("Boxes2D:half_sizes")}
        assert box_frames and box_frames <= image_frames, (path, box_frames)
    # the apple's own view: its box on frames 4, 6 and 8, the epipolar line of its previous view from frame 6 on, each
    # cleared on the frame after it (7 is a view of its own, without an image: frame 6's box stays over its image)
    ap = data["/world/camera/image/epipolar/7"]
    assert [r["frame"] for r in ap] == [4, 5, 6, 8, 9]
    assert [len(r.get("LineStrips2D:strips") or []) for r in ap] == [0, 0, 1, 1, 0]
    assert [len(r.get("Boxes2D:half_sizes") or []) for r in ap] == [1, 0, 1, 1, 0]
    res = data["/world/camera"][0]["Pinhole:resolution"][0]
    assert res == [320.0, 180.0]
    n_lines = 0
    for path, rows in data.items():
        for r in rows:
            for strip in r.get("LineStrips2D:strips") or []:
                n_lines += 1
                for x, y in strip:
                    assert -1e-3 <= x <= res[0] + 1e-3 and -1e-3 <= y <= res[1] + 1e-3, (path, r["frame"], strip)
    assert n_lines >= 10


def test_the_recording_streams_without_its_index_and_gets_it_compacted_at_close(tmp_path):
    """While the flight goes on, flight.rrd is written without its chunk index (the file sink would hold one entry
    per chunk in memory to the end); at close it is compacted and indexed, with every frame still in it."""
    from rerun.chunk import RrdReader

    from pomar.camera import Camera

    cam = Camera(640, 360, 500.0, 500.0, 320.0, 180.0)
    R = np.diag([1.0, -1.0, -1.0])
    rrd = tmp_path / "t.rrd"
    rl = RerunLog("test-flight", rrd)
    for f in range(60):
        rl.frame(_Event(f, _Pose(R, np.array([0.2 * f, 0.0, 10.0])), _Msg(np.zeros((0, 4), np.float32)), None), cam,
                 {"rate/ground": 3.0, "delay/behind_drone_s": 0.1})
        rl.rec.flush()  # each frame its own chunks, as on a live flight
    with pytest.warns(Warning), pytest.raises(RuntimeError):  # no index yet
        RrdReader(str(rrd)).store()
    with pytest.warns(Warning):
        streamed = sum(1 for _ in RrdReader(str(rrd)).stream())
    rl.close()
    store = RrdReader(str(rrd)).store()
    assert len(store) < streamed / 3, (len(store), streamed)
    frames = [r["frame"] for r in rrd_rows(rrd, "/world/camera")["/world/camera"]]
    assert frames == list(range(60))


def test_recording_of_a_replay_matches_its_map_files(replayed_test_flight):
    """The tiny flight's replay, read back from flight.rrd: the summary's total is apples.csv's, each row's series
    is named and coloured as the row is in the 3-D view and on the map, and the camera panel's lines stay inside
    the image."""
    _, out, rep = replayed_test_flight
    with open(out / "apples.csv", newline="") as f:
        apples = list(csv.DictReader(f))
    with open(out / "rows.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    data = rrd_rows(out / "flight.rrd")
    # the summary, at its last update, says the total and each row's count
    text = data["/summary"][-1]["TextDocument:text"][0]
    assert text.startswith(f"# {len(apples)} apples"), text
    for r in rows:
        assert f"| row {r['row']} | {r['count']} |" in text, (r, text)
    # per-row series: named "row N", in row N's colour, ending at rows.csv's count
    for r in rows:
        path = f"/stats/rows/row_{r['row']}"
        style = [x for x in data[path] if x.get("SeriesLines:names")]
        assert style and style[0]["SeriesLines:names"] == [f"row {r['row']}"], style
        assert _rgb(style[0]["SeriesLines:colors"][0]) == row_colours([int(r["row"])])[0].tolist()
        values = [x["Scalars:scalars"][0] for x in data[path] if x.get("Scalars:scalars")]
        assert values[-1] == float(r["count"]), (path, values)
        # from the flight's first frame, as the delay plot: one time axis
        first = [x["frame"] for x in data[path] if x.get("Scalars:scalars")][0]
        assert first == min(x["frame"] for x in data["/world/camera"] if x["frame"] is not None), (path, first)
        assert values[0] == 0.0
    # the 3-D apples and the map's apples in their rows' colours
    last = data["/world/apples"][-1]
    by_label = {lab: _rgb(c) for lab, c in zip(last["Points3D:labels"], last["Points3D:colors"])}
    for a in apples:
        assert by_label[f"apple {a['id']}, row {a['row']}"] == PALETTE[(int(a["row"]) - 1) % len(PALETTE)].tolist()
    # apples a fixed size on screen, the structure-from-motion cloud a quarter of it (rerun: negative = UI points)
    from ground.outputs.rerun_log import APPLE_UI_POINTS

    assert (np.array(last["Points3D:radii"]) == -APPLE_UI_POINTS).all()
    cloud = [r for p, rws in data.items() if p.startswith("/world/points/") for r in rws]
    assert cloud and all(np.array(r["Points3D:radii"]) == -APPLE_UI_POINTS / 4 for r in cloud)
    # the ground's and the drone's rates in two colours
    rates = {p: [x for x in data[p] if x.get("SeriesLines:colors")] for p in ("/stats/rate/ground", "/stats/rate/drone")}
    colours = {p: _rgb(v[0]["SeriesLines:colors"][0]) for p, v in rates.items()}
    assert colours["/stats/rate/ground"] != colours["/stats/rate/drone"], colours
    assert {_rgb(c)[0] for c in data["/map/apples"][-1]["GeoPoints:colors"]} <= {int(c[0]) for c in PALETTE}
    # every 2-D line inside the image it is drawn on
    res = data["/world/camera"][-1]["Pinhole:resolution"][0]
    for path, rws in data.items():
        if path.startswith("/world/camera/image"):
            for r in rws:
                for strip in r.get("LineStrips2D:strips") or []:
                    for x, y in strip:
                        assert -1e-3 <= x <= res[0] + 1e-3 and -1e-3 <= y <= res[1] + 1e-3, (path, r["frame"])
    # the rows' lines, in 3-D and on the map
    assert len(data["/world/rows"][-1]["LineStrips3D:strips"]) == len(rows)
    # each row's name in white, not in its row's colour (rerun draws a label in its entity's colour on grey)
    labels = data["/world/row_labels"][-1]
    assert labels["Points3D:labels"] == [f"row {r['row']}" for r in rows]
    assert {tuple(_rgb(c)) for c in labels["Points3D:colors"]} == {(255, 255, 255)}
    assert len(data["/map/rows"][-1]["GeoLineStrings:line_strings"]) == len(rows)
