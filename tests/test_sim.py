"""The simulator: config errors name the key; flights are deterministic from the seed; PX4 variant."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from sim import config
from sim.config import ConfigError
from tests.conftest import SMALL_CONFIG


@pytest.mark.parametrize("text, key", [
    ("[flight]\naltitud_m = 12\n", "flight.altitud_m"),
    ("[flight]\naltitude_m = 'high'\n", "flight.altitude_m"),
    ("[flight]\naltitude_m = -3\n", "flight.altitude_m"),
    ("[camera]\nwidth = 1281\n", "camera.width"),
    ("[telemetry]\ncapture_message = 'CAM'\n", "telemetry.capture_message"),
    ("[flight]\npasses = [{ across_m = 1.0, look = 3 }]\n", "flight.passes[0].look"),
    ("[flight]\npasses = [{ acros_m = 1.0 }]\n", "flight.passes[0].acros_m"),
    ("orchard = 3\n", "orchard"),
    ("[orchard\nrows = 3\n", "not valid TOML"),
])
def test_bad_config_names_the_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        config.load(p)
    assert key in str(exc.value) and str(p) in str(exc.value)


def test_cli_reports_bad_config(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("seed = 1\n[apples]\nper_tre = 3\n")
    r = subprocess.run([sys.executable, "-m", "sim", "flight", "--config", str(p), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "apples.per_tre" in r.stderr and "Traceback" not in r.stderr


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        config.load(tmp_path / "nope.toml")


def test_default_config_is_valid():
    cfg = config.from_dict({})
    assert cfg.orchard.rows == 10 and cfg.camera.width == 1280 and cfg.flight.altitude_m == 12.0


def _read(fd):
    return fd.truth_apples(), fd.truth_frames(), fd.truth_detections()


def test_small_flight_is_deterministic_and_consistent(small_flight, tmp_path):
    from pomar.flight import FlightDir
    from pomar.video import count_frames
    from sim.flight import simulate_flight

    again = tmp_path / "again"
    simulate_flight(config.load(SMALL_CONFIG), again, jobs=1, progress=False)  # other job count, same result
    fd2 = FlightDir(again)
    for x, y in zip(_read(small_flight), _read(fd2)):
        for k in x:
            assert np.array_equal(x[k], y[k]), k
    assert small_flight.tlog.read_bytes() == fd2.tlog.read_bytes()
    meta = small_flight.meta()
    assert count_frames(small_flight.video) == meta.frame_count
    # the clock offset of the config shows in flight.json, not in the truth
    fr = small_flight.truth_frames()
    assert meta.video_start_utc - fr["t_unix"][0] == pytest.approx(0.25, abs=1e-6)
    d = small_flight.truth_detections()
    assert len(np.unique(d["apple_id"])) > 10


def test_seed_changes_the_orchard(tmp_path):
    from sim.orchard import build_scene

    a = build_scene(config.from_dict({"seed": 1, "orchard": {"rows": 2, "row_length_m": 4.0}}))
    b = build_scene(config.from_dict({"seed": 2, "orchard": {"rows": 2, "row_length_m": 4.0}}))
    assert not np.array_equal(a.apples["xyz"][:5], b.apples["xyz"][:5])


def test_row_load_sets_each_rows_apples_and_leaves_an_unloaded_orchard_as_it_was():
    from sim.orchard import build_scene

    base = {"seed": 5, "orchard": {"rows": 3, "row_length_m": 40.0}, "apples": {"per_tree": 10}}
    even = build_scene(config.from_dict(base))
    ones = build_scene(config.from_dict({**base, "apples": {"per_tree": 10, "row_load": [1.0]}}))
    assert np.array_equal(even.apples["xyz"], ones.apples["xyz"])  # a factor of 1 draws the same orchard
    loaded = build_scene(config.from_dict({**base, "apples": {"per_tree": 10, "row_load": [0.5, 1.0, 1.5]}}))
    n = np.bincount(loaded.apples["row"], minlength=4)[1:]
    assert n[0] < 0.7 * n[1] and n[2] > 1.3 * n[1], n
    with pytest.raises(config.ConfigError, match="row_load"):
        config.from_dict({**base, "apples": {"row_load": [-1.0]}})


def test_apples_do_not_interpenetrate():
    from scipy.spatial import cKDTree

    from sim.orchard import APPLE, build_scene

    # dense apples, so the draw puts some through each other before the removal
    sc = build_scene(config.from_dict({"seed": 3, "orchard": {"rows": 2, "row_length_m": 6.0}, "apples": {"per_tree": 60}}))
    xyz, r = sc.apples["xyz"], sc.apples["radius_m"]
    pairs = cKDTree(xyz).query_pairs(2 * r.max(), output_type="ndarray")
    gap = np.linalg.norm(xyz[pairs[:, 0]] - xyz[pairs[:, 1]], axis=1) - r[pairs].sum(axis=1)
    assert len(pairs) > 0 and gap.min() >= 0
    # each apple is drawn by exactly one primitive, at its truth position
    apple = sc.kind == APPLE
    assert np.array_equal(np.sort(sc.apple_index[apple]), np.arange(len(xyz)))
    assert np.allclose(sc.pos[apple], xyz[sc.apple_index[apple]], atol=1e-5)
    assert np.array_equal(sc.apples["apple_id"], np.arange(len(xyz)))


def test_interpenetration_removes_the_later_apple_only():
    from sim.orchard import _without_interpenetration

    # a chain: 0 overlaps 1, 1 overlaps 2, 0 and 2 are clear; 3 is 9 cm from 2, 1 cm clear of it
    xyz = np.array([[0, 0, 0], [0.06, 0, 0], [0.12, 0, 0], [0.12, 0.09, 0]], float)
    r = np.full(4, 0.04)
    assert _without_interpenetration(xyz, r).tolist() == [True, False, True, True]


def test_px4_capture_messages(tmp_path):
    from sim.flight import simulate_flight
    from pomar.telemetry import read_log

    cfg = config.load(SMALL_CONFIG)
    cfg.telemetry.capture_message = "CAMERA_TRIGGER"
    cfg.camera.width, cfg.camera.height = 160, 96
    summary = simulate_flight(cfg, tmp_path / "px4", jobs=1, progress=False)
    counts = read_log(tmp_path / "px4" / "telemetry.tlog").counts
    assert counts["CAMERA_TRIGGER"] == summary["frames"] and "CAMERA_FEEDBACK" not in counts


def test_apples_sizes_rows_and_varieties(bundled_flight):
    a = bundled_flight.truth_apples()
    d = 2 * a["radius_m"]
    assert d.min() >= 0.06 - 1e-4 and d.max() <= 0.09 + 1e-4
    assert set(np.unique(a["row"]).tolist()) == set(range(1, 11))
    assert set(np.unique(a["variety"]).tolist()) == {"Gala", "Fuji"}
    # rows about 4 m apart, parallel
    x_by_row = [np.median(a["x"][a["row"] == r]) for r in range(1, 11)]
    assert np.allclose(np.diff(x_by_row), 4.0, atol=0.2)
    # some apples are hidden: the flight sees some only partly
    det = bundled_flight.truth_detections()
    assert (det["visible_fraction"] < 0.5).mean() > 0.1


def test_rewrite_telemetry_same_settings_is_identical_and_rtk_is_accurate(bundled_flight, tmp_path):
    import json

    import numpy as np

    from ground.poses.telemetry_poses import frame_telemetry
    from pomar.flight import FRAMES_COLUMNS, FlightDir, read_csv
    from pomar.geo import Origin
    from sim.flight import rewrite_telemetry

    rewrite_telemetry(bundled_flight.path, tmp_path / "same")
    # the same messages at the same times; the simulator now sends its EKF's height source first (PARAM_VALUE,
    # which the bundled flight, rendered before, lacks), so the sequence numbers after it differ
    from pymavlink import mavutil

    def messages(path, skip=("PARAM_VALUE",)):
        conn, out = mavutil.mavlink_connection(str(path)), []
        while (m := conn.recv_match()) is not None:
            if m.get_type() not in skip:
                out.append((m._timestamp, m.get_srcComponent(), m.to_dict()))
        return out

    same = messages(tmp_path / "same" / "telemetry.tlog")
    assert same == messages(bundled_flight.tlog) and len(same) > 1000
    assert len(messages(tmp_path / "same" / "telemetry.tlog", skip=())) == len(same) + 1

    rewrite_telemetry(bundled_flight.path, tmp_path / "rtk", gps_noise_m=0.02, gps_alt_noise_m=0.03)
    rtk = FlightDir(tmp_path / "rtk")
    assert rtk.video.resolve() == bundled_flight.video.resolve()
    truth = read_csv(bundled_flight.truth_dir / "frames.csv", FRAMES_COLUMNS)
    o = json.loads((bundled_flight.truth_dir / "origin.json").read_text())
    origin = Origin(o["lat"], o["lon"], o["alt"])
    true_enu = origin.to_enu(truth["lat"], truth["lon"], truth["alt"])

    def gps_error(flight):
        _, s = frame_telemetry(flight)
        return np.linalg.norm(origin.to_enu(s["lat"], s["lon"], s["alt"]) - true_enu, axis=1)

    assert np.median(gps_error(rtk)) < 0.1 < np.median(gps_error(bundled_flight))


def test_rewrite_telemetry_refuses_unknown_keys_and_real_flights(bundled_flight, tmp_path):
    import pytest

    from pomar.flight import FlightFormatError
    from sim.config import ConfigError
    from sim.flight import rewrite_telemetry

    with pytest.raises(ConfigError, match="gps_nois"):
        rewrite_telemetry(bundled_flight.path, tmp_path / "x", gps_nois=1.0)
    (tmp_path / "real").mkdir()
    with pytest.raises(FlightFormatError, match="sim_config.json"):
        rewrite_telemetry(tmp_path / "real", tmp_path / "y")


def test_ground_texture_lookup_is_remap_and_takes_textures_wider_than_opencv_allows():
    import cv2

    from sim.render import _remap_window

    rng = np.random.default_rng(7)
    src = rng.integers(0, 256, (300, 500, 3), np.uint8)
    # a footprint inside the texture, and one running over two of its edges (reflected there)
    for lo, hi in (((120.3, 40.7), (380.2, 210.9)), ((-30.5, -12.25), (530.75, 150.5))):
        mx = rng.uniform(lo[0], hi[0], (60, 80)).astype(np.float32)
        my = rng.uniform(lo[1], hi[1], (60, 80)).astype(np.float32)
        want = cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        assert np.array_equal(_remap_window(src, mx, my), want)
    # a 900-m orchard's texture is over 32,767 px long, which cv2.remap refuses whole
    wide = np.zeros((20, 40_000, 3), np.uint8)
    wide[:, 35_000:35_010] = (10, 20, 30)
    mx, my = np.full((4, 4), 35_004.0, np.float32), np.full((4, 4), 10.0, np.float32)
    with pytest.raises(cv2.error):
        cv2.remap(wide, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    assert (_remap_window(wide, mx, my) == (10, 20, 30)).all()


def test_an_autopilot_that_takes_its_height_from_the_barometer(bundled_flight, tmp_path):
    """``height_source = "baro"`` (ArduPilot's default): the tlog's heights above take-off are the truth's within a
    barometer's drift, not the GPS's vertical error; its horizontal positions are the same, sample for sample."""
    from ground.poses.telemetry_poses import frame_telemetry
    from pomar.flight import FlightDir
    from sim.flight import rewrite_telemetry
    from sim.telemetry import BARO_DRIFT_M

    rewrite_telemetry(bundled_flight.path, tmp_path / "baro", height_source="baro")
    baro = FlightDir(tmp_path / "baro")
    true_h = np.asarray(bundled_flight.truth_frames()["alt"], float) - bundled_flight.origin().alt
    _, s_gps = frame_telemetry(bundled_flight)
    _, s_baro = frame_telemetry(baro)
    np.testing.assert_array_equal(s_baro["lat"], s_gps["lat"])
    np.testing.assert_array_equal(s_baro["lon"], s_gps["lon"])
    err_baro = np.abs(s_baro["height"] - true_h)
    err_gps = np.abs(s_gps["height"] - true_h)
    assert np.median(err_baro) < 4 * BARO_DRIFT_M < np.median(err_gps)
    # its log says so (EK3_SRC1_POSZ = 1), and the heights are trusted to a barometer's accuracy
    from pomar.telemetry import read_log
    from pomar.telemetry.base import BARO_HEIGHT_SIGMA_M

    tl = read_log(baro.tlog)
    assert tl.height_from == "baro, EK3_SRC1_POSZ = 1" and tl.height_sigma_m == BARO_HEIGHT_SIGMA_M
    # one drone, one barometer: a DJI SRT written for this flight carries the same heights as its tlog
    from sim.__main__ import main as sim_main

    assert sim_main(["logs", str(baro.path), "--out", str(tmp_path / "dji")]) == 0
    srt = read_log(tmp_path / "dji" / "video.SRT")
    h_srt = srt.height_above_home(srt.position.values[:, 2])
    np.testing.assert_allclose(h_srt, s_baro["height"][:len(h_srt)], atol=0.002)


def test_a_barometers_drift_over_a_short_flight_is_as_large_as_said():
    """The barometer's offset over a 12-s flight (its 20-s process at 5 Hz) has the spread BARO_DRIFT_M says, not the
    1.6 times of a process normalised by its own short sample's spread (which the other processes keep, so that flights
    rendered before regenerate byte for byte)."""
    from sim.telemetry import BARO_DRIFT_M
    from sim.trajectory import smooth_noise

    def offsets(by_gain):
        return np.array([smooth_noise(np.random.default_rng([s, 38]), 60, 20.0, BARO_DRIFT_M, rate_hz=5.0,
                                      by_gain=by_gain).mean() for s in range(600)])

    assert 0.85 * BARO_DRIFT_M < offsets(True).std() < 1.15 * BARO_DRIFT_M < offsets(False).std()


def test_the_truth_holds_every_trees_full_load_and_each_apples_mass(bundled_flight, small_flight):
    """Every tree's full load (the apples it carries, seen or not) and every apple's tree and mass, for scoring yield
    (issue 59), drawn without a draw from the generator (a flight rendered before comes out the same apple for apple:
    checked on issue 62's flights, rendered the same day)."""
    from pomar.fruit import apple_mass_kg
    from sim.orchard import build_scene

    scene = build_scene(config.load(bundled_flight.path / "sim_config.toml"))
    tr = scene.trees
    assert tr["apples"].sum() == len(scene.apples["xyz"])
    assert np.isclose(tr["mass_kg"].sum(), scene.apples["mass_kg"].sum())
    # an apple hangs in its own tree's canopy (its half-length along the row: at most 0.68 x 1.15 x 1.07 tree spacings)
    own = {(r, t): x for r, t, x in zip(tr["row"], tr["tree"], tr["xyz"])}
    centre = np.array([own[(r, t)] for r, t in zip(scene.apples["row"], scene.apples["tree"])])
    spacing = config.load(bundled_flight.path / "sim_config.toml").orchard.tree_spacing_m
    along = (scene.apples["xyz"][:, :2] - centre[:, :2]) @ (scene.orchard_to_enu @ [0.0, 1.0])
    assert np.abs(along).max() < 0.9 * spacing, np.abs(along).max()
    d_m, m_kg = 2 * scene.apples["radius_m"], scene.apples["mass_kg"]
    assert 0.06 <= d_m.min() and d_m.max() <= 0.09 and 0.09 < m_kg.min() and m_kg.max() < 0.34
    # its mass is pomar.fruit's of its diameter and cultivar, the ground's relation
    for v in np.unique(scene.apples["variety"]):
        sel = np.asarray(scene.apples["variety"]) == v
        np.testing.assert_allclose(m_kg[sel], apple_mass_kg(d_m[sel], v))
    # a flight rendered now writes them: truth/trees.csv, and each apple's tree and mass beside it
    t = small_flight.truth_trees()
    a = small_flight.truth_apples()
    assert t["apples"].sum() == len(a["apple_id"]) > 0 and (t["mass_kg"] > 0).sum() == (t["apples"] > 0).sum()


def test_rows_of_other_fruit_sizes_and_trees_of_other_vigour_leave_a_plain_orchard_as_it_was():
    """apples.row_diameter_m (each row's [min, max], cycled) and apples.tree_vigour_cv (a gamma factor on each tree's
    expected load): without them the orchard is drawn as before; with them the rows' fruit differ by their ranges and
    the trees' loads spread wider than a Poisson load."""
    from sim.orchard import build_scene

    base = {"seed": 5, "orchard": {"rows": 4, "row_length_m": 30.0, "leaves_per_tree": 50}, "apples": {"per_tree": 20}}
    plain = build_scene(config.from_dict(base))
    same = build_scene(config.from_dict({**base, "apples": {"per_tree": 20, "row_diameter_m": [[0.06, 0.09]],
                                                           "tree_vigour_cv": 0.0}}))
    assert np.array_equal(plain.apples["xyz"], same.apples["xyz"])
    sized = build_scene(config.from_dict({**base, "apples": {"per_tree": 20,
                                                            "row_diameter_m": [[0.06, 0.07], [0.08, 0.09]]}}))
    d = 2 * sized.apples["radius_m"]
    odd = sized.apples["row"] % 2 == 1
    assert d[odd].max() <= 0.07 and d[~odd].min() >= 0.08
    vigour = build_scene(config.from_dict({**base, "apples": {"per_tree": 20, "tree_vigour_cv": 0.5}}))
    cv = lambda s: s.trees["apples"].std() / s.trees["apples"].mean()  # noqa: E731
    assert cv(plain) < 0.3 < cv(vigour), (cv(plain), cv(vigour))
    for bad, key in (({"row_diameter_m": [[0.08, 0.07]]}, "row_diameter_m"), ({"tree_vigour_cv": -1.0}, "vigour")):
        with pytest.raises(config.ConfigError, match=key):
            config.from_dict({**base, "apples": bad})


def test_the_tall_spindle_preset_gives_trees_as_heavy_as_real_ones_under_the_configs_own_keys():
    """[apples] preset = "tall-spindle" (issue 71): a mature high-density orchard's trees, about 120 apples each
    (published figures in sim.config), fruit 69-84 mm; the config's own keys win over the preset's; an unknown preset is
    one line naming the file and the presets there are."""
    from sim.orchard import build_scene

    base = {"seed": 5, "orchard": {"rows": 3, "row_length_m": 12.0, "leaves_per_tree": 50}}
    heavy = build_scene(config.from_dict({**base, "apples": {"preset": "tall-spindle"}}))
    assert 100 <= heavy.trees["apples"].mean() <= 140
    d = 2 * heavy.apples["radius_m"]
    assert d.min() >= 0.069 and d.max() <= 0.084
    own = config.from_dict({**base, "apples": {"preset": "tall-spindle", "per_tree": 60.0}})
    assert own.apples.per_tree == 60.0 and own.apples.diameter_min_m == 0.069
    with pytest.raises(config.ConfigError, match=r"^f.toml: apples.preset 'heavy' is not one of tall-spindle$"):
        config.from_dict({**base, "apples": {"preset": "heavy"}}, "f.toml")


def test_a_growers_hand_counts_come_from_the_trees_full_loads(small_flight, tmp_path):
    """`python -m sim counts`: the trees asked for, or K drawn at random, with their full loads (exact, or with a
    human's counting error); a tree the orchard lacks is one line naming it, exit 2."""
    t = small_flight.truth_trees()
    load = {(int(r), int(k)): int(n) for r, k, n in zip(t["row"], t["tree"], t["apples"])}
    out = tmp_path / "counts.csv"
    asked = sorted(load)[:2]
    r = subprocess.run([sys.executable, "-m", "sim", "counts", str(small_flight.path), "--out", str(out), "--trees",
                        *[f"{a}:{b}" for a, b in asked]], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "row,tree,apples" and lines[1:] == [f"{a},{b},{load[(a, b)]}" for a, b in asked]
    from sim.counts import sample_counts

    drawn = sample_counts(small_flight, random=3, seed=2)
    assert len({(c["row"], c["tree"]) for c in drawn}) == 3 and all(c["apples"] == load[(c["row"], c["tree"])]
                                                                    for c in drawn)
    noisy = sample_counts(small_flight, trees=sorted(load), count_error_cv=0.2, seed=2)
    assert any(c["apples"] != load[(c["row"], c["tree"])] for c in noisy if load[(c["row"], c["tree"])] >= 5)
    r = subprocess.run([sys.executable, "-m", "sim", "counts", str(small_flight.path), "--out", str(out), "--trees",
                        "99:1"], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "no tree 99:1" in r.stderr, r.stderr


def test_the_orchards_layout_fitted_to_its_trees_puts_each_tree_where_it_stands(small_flight, tmp_path):
    """`python -m sim layout`: one line a row, numbered as the truth; read back, its tree k of row r lies within the
    canopies' jitter (a few cm) of the truth's tree k of row r, and each row has as many trees as the truth's."""
    from pomar.layout import read_layout, tree_positions

    out = tmp_path / "orchard.csv"
    r = subprocess.run([sys.executable, "-m", "sim", "layout", str(small_flight.path), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    t = small_flight.truth_trees()
    origin = small_flight.origin()
    rows = read_layout(out)
    assert [x.row for x in rows] == sorted(set(t["row"].astype(int)))
    for x in rows:
        sel = t["row"].astype(int) == x.row
        order = np.argsort(t["tree"][sel])
        truth = np.stack([t["x"][sel], t["y"][sel]], 1)[order]
        got = tree_positions(x, origin)
        assert len(got) == sel.sum(), (x.row, len(got), sel.sum())
        assert np.abs(got - truth).max() < 0.25, np.abs(got - truth).max()
