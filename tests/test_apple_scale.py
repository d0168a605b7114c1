"""Scale normalisation (issue 17): the apple size foreseen from telemetry, the frames rescaled before detection
with their boxes put back in the full frame, the scale on the wire; per-tree counts (trees.csv) and their score."""

from __future__ import annotations

import numpy as np
import pytest

from pomar import wire
from pomar.apple_scale import Pacer, ScalePolicy, expected_radius_px, off_nadir_deg, parse_scale, telemetry_radius_px
from pomar.telemetry import read_log


def test_home_altitude_and_heights_come_from_the_tlogs_relative_altitude(bundled_flight):
    tl = read_log(bundled_flight.telemetry_log)
    assert tl.home_alt == pytest.approx(bundled_flight.origin().alt, abs=0.05)  # the sim's home is the ground
    meta = bundled_flight.meta()
    t, _ = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, 0.0)
    tel = tl.at(t)
    assert 9.0 < np.nanmedian(tel["height"]) < 15.0  # flown at 12 m, with GPS altitude noise
    assert np.nanmedian(off_nadir_deg(tel["q_gimbal"])) == pytest.approx(30.0, abs=2.0)


def test_the_foreseen_apple_size_matches_the_flights_truth(bundled_flight):
    """The telemetry's height and tilt with the lens give the apples' radius in pixels to within 20 %."""
    tl = read_log(bundled_flight.telemetry_log)
    meta, cam = bundled_flight.meta(), bundled_flight.camera()
    t, _ = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, 0.0)
    expected = np.nanmedian(telemetry_radius_px(cam.fx, tl.at(t)))
    d = bundled_flight.truth_detections()
    truth = np.median(d["r_px"][d["visible_fraction"] >= 0.5])
    assert expected == pytest.approx(truth, rel=0.2)


def test_each_image_row_foresees_the_apple_size_where_its_ray_meets_the_canopy(bundled_flight):
    """Per image row: the centre row gives the optical axis's radius; rows nearer the horizon (the top, as the camera
    tilts forward) see smaller apples; and the bundled flight's truth apples follow the rows' radii."""
    from pomar.apple_scale import flight_telemetry, row_radius_px

    meta, cam = bundled_flight.meta(), bundled_flight.camera()
    tel = flight_telemetry(bundled_flight)
    i = meta.frame_count // 2
    r = row_radius_px(cam, tel["height"][i], tel["q_gimbal"][i])
    axis = expected_radius_px(cam.fx, tel["height"][i], off_nadir_deg(tel["q_gimbal"][i]))[0]
    assert r[int(round(cam.cy - 0.5))] == pytest.approx(axis, rel=0.01)
    assert np.all(np.diff(r) > 0) and r[-1] > 1.3 * r[0]
    # the truth's apples against their rows' radii, every 10th frame: right within 25 %, and as right at the top of
    # the frame as at the bottom, where the apples are 1.5 times as large
    d = bundled_flight.truth_detections()
    ratio, top = [], []
    for f in range(0, meta.frame_count, 10):
        sel = (d["frame"] == f) & (d["visible_fraction"] >= 0.5)
        rows = np.clip(np.round(d["v"][sel]).astype(int), 0, cam.height - 1)
        ratio.append(d["r_px"][sel] / row_radius_px(cam, tel["height"][f], tel["q_gimbal"][f])[rows])
        top.append(rows < cam.height / 2)
    ratio, top = np.concatenate(ratio), np.concatenate(top)
    assert np.median(ratio) == pytest.approx(1.0, rel=0.25)
    assert np.median(ratio[top]) == pytest.approx(np.median(ratio[~top]), rel=0.15)
    assert np.isnan(row_radius_px(cam, 1.0, tel["q_gimbal"][i])).all()  # below the canopy: not foreseen


def test_scale_policy_and_its_setting():
    p = ScalePolicy(5.0)
    assert p.scale(10.0) == 0.5 and p.scale(40.0) == 0.25 and p.scale(2.0) == 2.0 and p.scale(1.0) == 2.0  # clamped
    assert p.scale(float("nan")) == 1.0 and ScalePolicy(None).scale(10.0) == 1.0
    assert ScalePolicy(None, fixed=0.7).scale(3.0) == 0.7
    assert p.scale(5.3) == 0.95  # steps of 0.05
    # twice as high above the canopy: half the size
    assert expected_radius_px(1000.0, 2 * 8 + 1.9, 0.0) == pytest.approx(expected_radius_px(1000.0, 8 + 1.9, 0.0) / 2)
    # a height that cannot be a flight over the trees (a take-off point that is not the ground): not foreseen
    assert np.isnan(expected_radius_px(1000.0, 3.0, 30.0)) and ScalePolicy(5.0).scale(float("nan")) == 1.0
    assert parse_scale("auto") == ("auto", None) and parse_scale("0.5") == ("fixed", 0.5)
    for bad in ("big", "0", "20"):
        with pytest.raises(ValueError):
            parse_scale(bad)


def test_live_frames_are_enlarged_only_as_far_as_the_video_rate_leaves_time():
    """The pace of a live node: a scale above 1 is cut to what a frame's time (per input pixel, smoothed) fits in the
    video's frame period, never below 1; scales of 1 or less are left alone; a scale the user set is never paced."""
    w, h, period = 1280, 720, 0.1
    p = Pacer()
    assert p.cap(1.35, w, h, period) == 1.0 and p.cap(0.7, w, h, period) == 0.7  # no time measured yet
    p.observe(0.5, w, h, 1.0)  # a CPU detector: 5 frame periods at the frame's own size
    assert p.cap(1.35, w, h, period) == 1.0 and p.cap(0.55, w, h, period) == 0.55
    fast = Pacer()
    fast.observe(0.02 * 1.35**2, w, h, 1.35)  # 0.02 s at scale 1: room for sqrt(5) = 2.24
    assert fast.cap(1.35, w, h, period) == 1.35 and fast.cap(2.0, w, h, period) == 2.0 and fast.capped == 0
    mid = Pacer()
    mid.observe(0.05, w, h, 1.0)  # room for sqrt(2) = 1.414: down to the policy's step below it
    assert mid.cap(1.6, w, h, period) == 1.4 and mid.cap(1.3, w, h, period) == 1.3
    assert p.capped == 2 and mid.capped == 1
    mid.observe(0.5, w, h, 1.0)  # frames got slower: the smoothed time follows, and the cap with it
    assert mid.cap(1.4, w, h, period) < 1.4
    assert ScalePolicy(5.0).pacer() is not None
    assert ScalePolicy(None).pacer() is None and ScalePolicy(None, fixed=1.5).pacer() is None  # off, or the user's


def test_frame_message_carries_its_scale():
    tel = wire.Telemetry(-28.5, -50.9, 972.0, (1, 0, 0, 0), (1, 0, 0, 0), 3, 0.5, 0)
    m = wire.FrameMessage("f", "d", 3, 1.5e9, tel, 3840, 2160, np.array([[10, 10, 20, 20]], np.float32),
                          np.array([0.9], np.float32), scale=0.55)
    assert wire.FrameMessage.decode(m.encode()).scale == pytest.approx(0.55)
    import msgpack

    d = msgpack.unpackb(m.encode(), raw=False)
    d["scale"] = 0.0
    with pytest.raises(wire.WireError, match="scale"):
        wire.FrameMessage.decode(msgpack.packb(d, use_bin_type=True))
    del d["scale"]  # a sender from before scales: frames at their own size
    assert wire.FrameMessage.decode(msgpack.packb(d, use_bin_type=True)).scale == 1.0


def test_a_rescaled_frame_gives_boxes_in_the_full_frames_pixels(bundled_flight):
    """The shipped model on a bundled frame twice its size (apples twice as large), scaled back by 0.5: the same
    apples as on the frame itself, at the same places."""
    import cv2

    from onboard.detector import DEFAULT_MODEL, OnnxDetector
    from pomar.video import read_frame

    assert DEFAULT_MODEL.is_file(), f"{DEFAULT_MODEL} is missing from this checkout"
    det = OnnxDetector()
    assert det.apple_radius_px and 3 < det.apple_radius_px < 8  # the model says the size it detects best
    img = read_frame(bundled_flight.video, 80)
    big = cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2), interpolation=cv2.INTER_LINEAR)
    ref, _ = det.detect(80, img)
    got, _ = det.detect(80, big, scale=0.5)
    assert len(ref) > 20 and abs(len(got) - len(ref)) <= 0.2 * len(ref)
    c_ref = (ref[:, :2] + ref[:, 2:]) / 2
    c_got = ((got[:, :2] + got[:, 2:]) / 2 + 0.5) / 2 - 0.5  # the big frame's pixels -> the frame's
    d = np.linalg.norm(c_got[:, None] - c_ref[None], axis=2).min(1)
    assert np.median(d) < 1.0 and got[:, 2].max() > img.shape[1]  # boxes in the big frame's pixels


def test_trees_csv_cuts_rows_into_tree_segments(tmp_path):
    from ground.orchard.map_rows import rows_summary, trees_summary
    from ground.outputs.tables import write_map

    rng = np.random.default_rng(1)
    n = 120
    along = rng.uniform(0, 12, n)
    row = np.repeat([1, 2], n // 2)
    table = {"id": np.arange(n), "x": np.where(row == 1, 0.0, 4.0) + rng.normal(0, 0.2, n), "y": along,
             "z": np.full(n, 2.0), "lat": np.zeros(n), "lon": np.zeros(n), "alt": np.zeros(n), "row": row,
             "radius_m": np.full(n, 0.04), "observations": np.full(n, 5), "reprojection_error_px": np.ones(n),
             "first_frame": np.zeros(n, int), "last_frame": np.ones(n, int)}
    direction = np.pi / 2  # rows run north
    rows = rows_summary(table, direction)
    trees = trees_summary(table, rows, direction, 1.5)
    for r in rows:
        mine = [t for t in trees if t["row"] == r["row"]]
        assert sum(t["count"] for t in mine) == r["count"]
        assert len(mine) == int(np.ceil(r["length_m"] / 1.5 - 1e-9))
        assert np.allclose(np.diff([t["along_m"] for t in mine]), 1.5)
    write_map(tmp_path, table, rows, trees)
    lines = (tmp_path / "trees.csv").read_text().splitlines()
    from ground.outputs.tables import TREE_COLUMNS

    assert lines[0] == ",".join(TREE_COLUMNS) and lines[0].startswith("row,tree,along_m,x,y,lat,lon,count,")
    assert len(lines) == len(trees) + 1
    with pytest.raises(ValueError, match="spacing"):
        trees_summary(table, rows, direction, 0.0)


def test_per_tree_score_is_one_for_a_perfect_map_and_falls_with_misplaced_apples():
    from ground.evaluation.scoring import per_tree

    rng = np.random.default_rng(2)
    truth = np.column_stack([np.repeat([0.0, 4.0], 60), rng.uniform(0, 20, 120) ** 1.3 / 2, np.full(120, 2.0)])
    direction = np.pi / 2  # rows run north; across-row offsets along the normal (-x here), as score_map gives them
    rows_id, across = np.array([1, 2]), np.array([0.0, -4.0])
    truth_row = np.repeat([1, 2], 60)
    perfect = per_tree(truth, truth, truth_row, rows_id, across, direction)
    assert perfect["r"] == pytest.approx(1.0) and perfect["mae"] == 0 and perfect["bins"] > 20
    shuffled = truth.copy()
    shuffled[:, 1] = rng.permutation(shuffled[:, 1])
    assert per_tree(shuffled, truth, truth_row, rows_id, across, direction)["r"] < 0.9


def _views(frames, index=0):
    from ground.apples.association import Detection

    return [Detection(f, index) for f in frames]


def test_size_check_leaves_out_apples_too_small_to_be_whole():
    """With the size check on, apples whose radius is under the ratio times the map's median are not counted; with
    fewer than MIN_SIZED sized apples, or the check off, all are."""
    from ground.apples.association import Apple
    from ground.apples.counting import Counting, CountingSettings
    from ground.apples.frames import AssociationFrames

    count = Counting(CountingSettings(min_radius_ratio=0.85), AssociationFrames(), reach=100)
    radii = np.r_[np.full(30, 0.036), np.full(6, 0.026)]  # 30 whole apples, 6 half hidden
    count.apples = {i: Apple(i, np.zeros(3), _views([0, 1, 2]), 0.5) for i in range(len(radii) + 1)}
    count.radius = {i: r for i, r in enumerate(radii)}  # the last apple has no radius: it counts
    ids = count.counted_ids()
    assert ids == list(range(30)) + [36] and count.size_rejected == 6
    checks = count.checks()
    assert list(checks["left_out"]) == [""] * 30 + ["small"] * 6 + [""]
    count.s.min_radius_ratio = 0.0
    assert len(count.counted_ids()) == 37 and count.size_rejected == 0
    count.s.min_radius_ratio = 0.85
    count.radius = {i: count.radius[i] for i in list(range(10)) + [30, 31]}  # 12 sized apples: too few to judge
    assert len(count.counted_ids()) == 37


def test_an_apples_fruit_size_comes_from_its_least_hidden_views_its_size_check_from_all():
    """Leaves only shrink a box: the fruit's radius is the median of the largest tenth of its views' radii (boxes x
    depth / focal length), the size check's the median of all; on a long track one loose box sets neither."""
    from ground.apples.association import Apple, Detection
    from ground.apples.counting import Counting, CountingSettings
    from ground.apples.frames import AssociationFrames
    from ground.poses.georeference import Pose
    from pomar.camera import Camera

    frames = AssociationFrames()
    count = Counting(CountingSettings(), frames, reach=100)
    count.camera = Camera.from_fov(640, 360, 60.0)
    fx = count.camera.fx
    P = count.camera.K_opencv @ np.hstack([np.eye(3), np.zeros((3, 1))])
    for f in range(30):
        frames.add(f, Pose(f, np.eye(3), np.zeros(3), "registered", 0.0, 0.0), P)
    # an apple of radius 0.04 m at 10 m: 20 views half hidden (box 0.75 of its radius), 9 whole, 1 loose box (1.6)
    scale = [0.75] * 20 + [1.0] * 9 + [1.6]
    views = [Detection(f, 0, (320 - s * r, 180 - s * r, 320 + s * r, 180 + s * r), 0.95)
             for f, s, r in zip(range(30), scale, [fx * 0.04 / 10.0] * 30)]
    median, size = count.radius_of(Apple(1, np.array([0.0, 0.0, 10.0]), views, 0.5))
    assert median == pytest.approx(0.75 * 0.04)
    assert size == pytest.approx(0.04)
    # the detector's boxes pull sizes to a middle one (box = 0.8 r + 1 px as it saw the frame, at scale 2 here): the
    # fruit's size is taken back through it, the size check's median is not
    count.box_response = (0.8, 1.0)
    frames.scale = [2.0] * 30
    r_det = 2.0 * fx * 0.04 / 10.0
    views = [Detection(f, 0, (320 - b, 180 - b, 320 + b, 180 + b), 0.95)
             for f, b in zip(range(30), [(0.8 * r_det + 1.0) / 2.0] * 30)]
    median, size = count.radius_of(Apple(1, np.array([0.0, 0.0, 10.0]), views, 0.5))
    assert size == pytest.approx(0.04) and median == pytest.approx((0.8 * r_det + 1.0) / 2.0 * 10.0 / fx)
    no_pose = Counting(CountingSettings(), AssociationFrames(), reach=100)
    no_pose.camera = count.camera
    assert np.isnan(no_pose.radius_of(Apple(2, np.array([0.0, 0.0, 10.0]), views[:3], 0.5))).all()


def test_expected_views_leave_out_apples_seen_in_few_of_the_frames_they_lie_in():
    from ground.apples.association import Apple
    from ground.apples.counting import Counting, CountingSettings
    from ground.apples.frames import AssociationFrames
    from pomar.camera import Camera

    frames = AssociationFrames()
    count = Counting(CountingSettings(min_radius_ratio=0.0, min_view_ratio=0.15), frames, reach=100)
    count.camera = Camera.from_fov(640, 360, 60.0)
    P = count.camera.K_opencv @ np.hstack([np.eye(3), np.zeros((3, 1))])  # at the origin, looking along +z
    for f in range(40):
        frames.add(f, None, P)
    seen = Apple(1, np.array([0.0, 0.0, 10.0]), _views(range(10, 18)), 0.5)  # 8 views of 40
    glimpsed = Apple(2, np.array([1.0, 0.5, 10.0]), _views([20, 21, 22]), 0.5)  # 3 of 40
    behind = Apple(3, np.array([0.0, 0.0, -10.0]), _views([5, 6, 7]), 0.5)  # never in view: 3 of 0
    count.apples = {1: seen, 2: glimpsed, 3: behind}
    assert count.expected_views(seen) == 40 and count.expected_views(behind) == 0
    assert count.counted_ids() == [1, 3] and count.views_rejected == 1
    c = count.checks()
    assert list(c["left_out"]) == ["", "few_views", ""] and list(c["expected_views"]) == [40, 40, 0]
    assert list(c["observations"]) == [8, 3, 3]


def test_apples_whose_views_meet_at_a_narrow_angle_are_left_out():
    """An apple 10 m away seen from cameras 1 m apart (5.7 degrees) counts; one seen from cameras 10 cm apart (0.6
    degrees: its depth is a guess) does not, unless the check is off; an apple with a frame without a pose counts."""
    from ground.apples.association import Apple
    from ground.apples.counting import Counting, CountingSettings
    from ground.apples.frames import AssociationFrames
    from ground.poses.stage import Pose

    frames = AssociationFrames()
    count = Counting(CountingSettings(min_radius_ratio=0.0, min_view_ratio=0.0, min_parallax_deg=2.0), frames, 100)
    for f, x in enumerate([0.0, 0.05, 0.1, 1.0]):  # camera centres along x, looking along +z
        frames.add(f, Pose(f, np.eye(3), -np.array([x, 0.0, 0.0]), "registered", 0.0, 0.0), np.eye(3, 4))
    frames.frame.append(4)  # frame 4: fed, no pose
    X = np.array([0.5, 0.0, 10.0])
    wide = Apple(1, X, _views([0, 1, 3]), 0.5)
    narrow = Apple(2, X, _views([0, 1, 2], 1), 0.5)
    unposed = Apple(3, X, _views([2, 3, 4], 2), 0.5)
    count.apples = {1: wide, 2: narrow, 3: unposed}
    assert count.parallax_deg(wide) == pytest.approx(np.degrees(np.arctan(0.5 / 10) * 2), abs=0.01)
    assert count.parallax_deg(narrow) < 1.0 and np.isnan(count.parallax_deg(unposed))
    assert count.counted_ids() == [1, 3] and count.parallax_rejected == 1
    assert list(count.checks()["left_out"]) == ["", "narrow", ""]
    count.s.min_parallax_deg = 0.0
    assert count.counted_ids() == [1, 2, 3] and count.parallax_rejected == 0


def test_a_frame_without_a_foreseen_size_keeps_its_neighbours():
    """Frames past a once-a-second log's last subtitle (no height): the last size foreseen before them, so that they
    reach the detector at their neighbours' scale, not at their own size; frames before the first, the first's."""
    from pomar.apple_scale import held_radius_px

    r = np.array([np.nan, 4.0, 4.2, np.nan, 4.4, np.nan, np.nan])
    np.testing.assert_array_equal(held_radius_px(r), [4.0, 4.0, 4.2, 4.2, 4.4, 4.4, 4.4])
    assert np.isnan(held_radius_px(np.full(3, np.nan))).all()
