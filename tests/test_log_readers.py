"""Every telemetry reader on real files from public repositories (../shared/datasets/logs, read in place), each DJI
.SRT layout, and files cut short or of unknown layout: they parse, land at the place they were recorded on a
plausible track, and say what they could not read."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pomar.telemetry import TelemetryError, detect_format, read_log
from pomar.telemetry.srt import parse_subtitle

LOGS = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "logs"
needs_logs = pytest.mark.skipif(not LOGS.is_dir(), reason="../shared/datasets/logs not present")

#: file -> (format, where it was recorded: lat, lon within 0.05 degrees, at least this many positions)
REAL = {
    "ardupilot-tlog/ardusub_2023-05-04_small.tlog": ("tlog", 48.386, -124.631, 700),
    "px4-ulog/sample_log_small.ulg": ("ulog", 63.417, 10.408, 30),
    "px4-ulog/sample_px4_events.ulg": ("ulog", 47.398, 8.546, 100),
    "dji-srt/p4p_sample.SRT": ("srt", 47.469, 8.209, 5),
    "dji-srt/mavic_mini.SRT": ("srt", 48.077, -121.746, 100),
    "dji-srt/mavic_pro.SRT": ("srt", -20.253, 149.025, 400),
    "dji-srt/old_format.SRT": ("srt", -20.253, 149.025, 400),
    "dji-srt/mavic_2_style.SRT": ("srt", -20.253, 149.025, 400),
    "dji-srt/matrice_300.srt": ("srt", 36.615, -6.113, 300),
    "dji-srt/air2s.srt": ("srt", 41.425, 2.234, 15),
    "dji-srt/broken_incomplete.SRT": ("srt", -34.738, -58.456, 15),
}


@needs_logs
@pytest.mark.parametrize("name", sorted(REAL))
def test_real_file_parses_at_its_place_on_a_plausible_track(name):
    fmt, lat, lon, n = REAL[name]
    path = LOGS / name
    assert detect_format(path) == fmt
    tl = read_log(path)
    s = tl.summary_dict()
    assert s["format"] == fmt and s["positions"] >= n, s
    assert abs(np.mean(s["lat_range"]) - lat) < 0.05 and abs(np.mean(s["lon_range"]) - lon) < 0.05, s
    assert s["max_jump_m"] is not None and s["max_jump_m"] < 50.0, s
    assert np.all(np.diff(tl.position.t) > 0) and s["span_s"] > 0


@needs_logs
def test_summary_json_from_the_command_line(tmp_path):
    out = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "onboard", "telemetry", str(LOGS / "px4-ulog/sample_px4_events.ulg"),
                        "--json", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    s = json.loads(out.read_text())
    for key in ("format", "positions", "lat_range", "lon_range", "span_s", "attitudes", "gimbal_attitudes",
                "camera_events", "problems"):
        assert key in s, key
    assert s["format"] == "ulog" and s["attitudes"] > 600 and s["camera_events"] == 0
    assert any("camera_capture" in p for p in s["problems"])  # no camera events: said, with what is used instead


@needs_logs
def test_ardusub_streams_share_one_clock():
    """The vehicle's SYSTEM_TIME has no UTC and the ground station sends its own: GPS_RAW_INT and
    GLOBAL_POSITION_INT must still cover the same span; the retracted mount is no gimbal; packets of a dialect
    pymavlink cannot check are counted by type."""
    tl = read_log(LOGS / "ardupilot-tlog/ardusub_2023-05-04_small.tlog")
    assert abs(tl.gps.t[0] - tl.position.t[0]) < 1.0 and abs(tl.gps.t[-1] - tl.position.t[-1]) < 1.0
    assert abs(tl.attitude.t[0] - tl.position.t[0]) < 1.0
    assert len(tl.gimbal) == 0 and any("retract" in p for p in tl.problems)
    assert "no UTC" in " ".join(tl.problems) and "receive" in tl.clock
    assert tl.bad_packets == 4 and set(tl.bad_by_type) == {"CAMERA_INFORMATION", "VIDEO_STREAM_INFORMATION",
                                                           "CAMERA_SETTINGS", "CAMERA_CAPTURE_STATUS"}
    # a 1-Hz-ish GPS stream is not a gap at every sample
    assert not [g for g in tl.gaps if g.stream == "position"]


def test_srt_layouts():
    # Phantom 4 Pro / Mavic Mini: longitude first, H above take-off
    lay, f = parse_subtitle("F/3.2, SS 160, ISO 100, EV 0, GPS (8.2090, 47.4692, 18), D 49.21m, H 45.60m, "
                            "H.S 0.00m/s, V.S 0.00m/s")
    assert lay == "p4p" and (f["lat"], f["lon"], f["alt"]) == (47.4692, 8.2090, 45.60)
    # Mavic Pro: HOME and date, then GPS (longitude first) and barometer
    lay, f = parse_subtitle("HOME(149.0251,-20.2532) 2017.08.05 14:11:51\nGPS(149.0251,-20.2533,16) BAROMETER:1.9\n"
                            "ISO:100 Shutter:60 EV: Fnum:2.2")
    assert lay == "home" and (f["lat"], f["lon"], f["alt"]) == (-20.2533, 149.0251, 1.9) and f["date"] > 1.5e9
    # Matrice 300: latitude first, metres
    lay, f = parse_subtitle("2022.06.21 16:06:17\nGPS(36.6146,-6.1120,0.0M) BAROMETER:0.3M")
    assert lay == "m300" and (f["lat"], f["lon"], f["alt"]) == (36.6146, -6.1120, 0.3)
    # Mavic 3 / Mini 3: brackets, rel_alt and abs_alt, gimbal angles
    lay, f = parse_subtitle('<font size="28">FrameCnt: 12, DiffTime: 33ms\n2023-04-11 10:22:33.456\n[iso: 110] '
                            "[shutter: 1/1000.0] [fnum: 1.7] [ev: 0] [color_md: default] [focal_len: 24.00] "
                            "[latitude: 50.123456] [longitude: 8.654321] [rel_alt: 12.300 abs_alt: 152.780] "
                            "[gb_yaw: 91.2 gb_pitch: -60.0 gb_roll: 0.0] </font>")
    assert lay == "bracket" and (f["lat"], f["lon"], f["alt"], f["abs_alt"]) == (50.123456, 8.654321, 12.3, 152.78)
    assert f["gimbal"] == (0.0, -60.0, 91.2)
    # Mavic 2 (early firmware) spells it "longtitude"
    lay, f = parse_subtitle("[latitude : -20.2533] [longtitude : 149.0251] [iso : 100] [shutter : 1/60.0]")
    assert lay == "bracket" and (f["lat"], f["lon"]) == (-20.2533, 149.0251)
    with pytest.raises(ValueError):
        parse_subtitle("ISO 100 SS 1/60 (no position here)")


def test_srt_of_an_unknown_layout_is_a_clear_error(tmp_path):
    p = tmp_path / "odd.SRT"
    p.write_text("1\n00:00:00,000 --> 00:00:01,000\nALT 12.0 SPEED 3.1 POSITION 47.1/8.2\n\n"
                 "2\n00:00:01,000 --> 00:00:02,000\nALT 12.1 SPEED 3.1 POSITION 47.1/8.2\n\n")
    with pytest.raises(TelemetryError, match=r"odd\.SRT: subtitle 1 has no layout this reader knows"):
        read_log(p)


@needs_logs
def test_cut_files_keep_what_they_could_read(tmp_path):
    # the real DJI file cut in the middle of a subtitle
    tl = read_log(LOGS / "dji-srt/broken_incomplete.SRT")
    assert len(tl.position) == 19 and any("cut short" in p for p in tl.problems)
    # a PX4 log cut mid-record
    src = (LOGS / "px4-ulog/sample_px4_events.ulg").read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(src[: len(src) * 6 // 10])
    full, part = read_log(LOGS / "px4-ulog/sample_px4_events.ulg"), read_log(cut)
    assert 0 < len(part.position) < len(full.position) and any("cut short" in p for p in part.problems)
    np.testing.assert_array_equal(part.position.values, full.position.values[: len(part.position)])


def test_not_a_log(tmp_path):
    junk = tmp_path / "x.dat"
    junk.write_bytes(b"hello, not a log" * 10)
    with pytest.raises(TelemetryError, match=r"x\.dat: not a telemetry log"):
        read_log(junk)
    with pytest.raises(TelemetryError, match="not found"):
        read_log(tmp_path / "missing.ulg")


@pytest.fixture(scope="module")
def sim_logs(replay_test_flight, tmp_path_factory):
    """The tiny simulated flight's telemetry also as a DataFlash .bin, a PX4 .ulg and a DJI .SRT (python -m sim
    logs)."""
    out = tmp_path_factory.mktemp("logs")
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(replay_test_flight.path), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return replay_test_flight, out / "telemetry.bin", out / "video.SRT"


def test_sim_logs_give_the_tlogs_samples(sim_logs):
    """Each format, read by its own reader, samples the frames as the .tlog does: the same capture times, positions
    within their rounding (the SRT's 5 decimals, as a Mavic 3 writes them), and camera attitudes within their
    rounding (DataFlash's centidegrees; the SRT's tenths of a degree). The ULog carries the tlog's float samples as
    they are: positions, heights and the stated accuracy to float precision."""
    from pomar.rotations import quat_wxyz_to_rotation
    from sim.logs import SRT_LAYOUTS

    flight, binf, srtf = sim_logs
    meta = flight.meta()
    ref = read_log(flight.tlog)
    t_ref, _ = ref.frame_times(meta.frame_count, meta.video_start_utc, meta.fps)
    s_ref = ref.at(t_ref)
    for path, fmt in ((binf, "dataflash"), (binf.with_name("telemetry.ulg"), "ulog"), (srtf, "srt")):
        tl = read_log(path)
        assert tl.format == fmt
        t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps)
        np.testing.assert_allclose(t, t_ref, atol=2e-3)
        assert not (flags & 64).any()  # every frame timed by the log itself (CAM events, subtitles)
        s = tl.at(t)
        deg = {"dataflash": 1e-6, "ulog": 1e-9}.get(fmt, 0.5 * 10.0 ** -SRT_LAYOUTS["mavic3"][1] + 1e-9)
        for k, tol in (("lat", deg), ("lon", deg), ("alt", 1e-3 if fmt == "ulog" else 0.01)):
            np.testing.assert_allclose(s[k], s_ref[k], atol=tol)
        ang = (quat_wxyz_to_rotation(s["q_gimbal"]).inv() * quat_wxyz_to_rotation(s_ref["q_gimbal"])).magnitude()
        assert np.degrees(ang).max() < {"dataflash": 0.05, "ulog": 1e-4}.get(fmt, 0.1), (fmt, np.degrees(ang).max())
        if fmt in ("dataflash", "ulog"):  # the receiver's stated accuracy in metres (GPA's HAcc, eph), as the tlog's
            np.testing.assert_allclose(s["h_acc"], s_ref["h_acc"], atol=0.01)
            assert np.nanmin(s["h_acc"]) > 0


@needs_logs
def test_real_autopilot_logs_say_where_their_height_comes_from():
    """The EKF's height source is read from each real log's parameters: a barometer's height is trusted to
    BARO_HEIGHT_SIGMA_M, a GPS's to its stated vertical accuracy (the ULog's epv)."""
    from pomar.telemetry.base import BARO_HEIGHT_SIGMA_M

    want = {"ardupilot-tlog/ardusub_2023-05-04_small.tlog": "baro, EK3_SRC1_POSZ = 1",
            "px4-ulog/sample_log_small.ulg": "baro, EKF2_HGT_MODE = 0",
            "px4-ulog/sample_px4_events.ulg": "gps, EKF2_HGT_REF = 1"}
    for name, source in want.items():
        tl = read_log(LOGS / name)
        assert tl.height_from == source, name
        if source.startswith("baro"):
            assert tl.height_sigma_m == BARO_HEIGHT_SIGMA_M
        else:
            epv = tl.gps.values[:, 2]
            assert tl.height_sigma_m == pytest.approx(np.median(epv[epv > 0])) and 0.2 < tl.height_sigma_m < 5


def test_sim_logs_carry_the_ekfs_height_source(sim_logs):
    """The simulated autopilot's parameter survives into each log it writes (the tlog's PARAM_VALUE, DataFlash's
    PARM, the ULog's initial parameters, in PX4's name there): each reader gives the same source and accuracy, the
    receiver's stated vertical accuracy for GPS heights."""
    from sim.config import rendered_config

    flight, binf, _ = sim_logs
    tel = rendered_config(flight.path).telemetry
    logs = {"tlog": read_log(flight.tlog), "dataflash": read_log(binf),
            "ulog": read_log(binf.with_name("telemetry.ulg"))}
    for fmt, tl in logs.items():
        assert tl.height_from is not None and tl.height_from.split(",")[0] == "gps", (fmt, tl.height_from)
        assert tl.height_sigma_m == pytest.approx(logs["tlog"].height_sigma_m, abs=0.01), fmt
    assert tel.height_source == "gps" and logs["tlog"].height_sigma_m == pytest.approx(tel.gps_alt_noise_m, abs=0.001)
    assert logs["ulog"].height_from == "gps, EKF2_HGT_REF = 1" and "EK3_SRC1_POSZ = 3" in logs["dataflash"].height_from


def test_a_dataflash_log_without_gpa_states_no_accuracy(sim_logs, tmp_path):
    """A DataFlash log whose receiver's accuracy is not logged (no GPA): the positions' accuracy is unstated (NaN, so
    the ground takes its default), never GPS's HDop, which is no distance."""
    from pymavlink import DFReader

    from sim.logs import DF_FORMATS

    _, binf, _ = sim_logs
    data = binf.read_bytes()
    gpa = DF_FORMATS["GPA"][0]
    size = {t: 3 + DFReader.struct.calcsize(DFReader.DFFormat(t, n, 0, f, c).msg_struct)
            for n, (t, f, c) in DF_FORMATS.items()}
    size[128] = 89
    out, i = bytearray(), 0
    while i < len(data):  # every record but GPA's
        t = data[i + 2]
        if t != gpa:
            out += data[i:i + size[t]]
        i += size[t]
    bare = tmp_path / "no-gpa.bin"
    bare.write_bytes(bytes(out))
    tl = read_log(bare)
    assert len(tl.gps) and np.isnan(tl.gps.values[:, 1]).all() and (tl.gps.values[:, 0] >= 3).all()


def test_dataflash_cut_mid_record_keeps_what_it_read(sim_logs, tmp_path):
    _, binf, _ = sim_logs
    data = binf.read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: len(data) * 2 // 3 + 5])
    full, part = read_log(binf), read_log(cut)
    assert 0 < len(part.position) < len(full.position) and len(part.captures) < len(full.captures)
    assert any("cut" in p for p in part.problems), part.problems


def test_replay_from_the_srt(sim_logs, replayed_test_flight, tmp_path):
    """The tiny flight replayed through both processes with its DJI .SRT instead of its .tlog: every frame mapped,
    the map about as the .tlog's."""
    from ground.replay import replay

    flight, _, srtf = sim_logs
    _, _, ref = replayed_test_flight
    rep = replay(flight.path, tmp_path / "out", detector="onnx", keyframe_every=1, keyframe_width=0, quiet=True,
                 onboard_args=["--log", str(srtf)])
    assert rep["frames"]["frames"] == 20 and rep["frames"]["missing_frames"] == 0
    assert rep["onboard"]["telemetry_flagged_frames"] <= 20
    assert 0.5 * ref["apples"] - 2 <= rep["apples"] <= 1.5 * ref["apples"] + 2, (rep["apples"], ref["apples"])


def test_builtin_cameras_and_container_time(tmp_path):
    from pomar.assemble import camera_for, mp4_creation_time
    from pomar.camera import CameraFileError

    cam, source = camera_for("Phantom 4 Pro", 3840, 2160)  # the paper's drone: about 74 degrees across
    assert abs(np.degrees(2 * np.arctan(1920 / cam.fx)) - 73.7) < 0.5 and "phantom-4-pro" in source
    with pytest.raises(CameraFileError, match="unknown camera 'Phantom 5'"):
        camera_for("Phantom 5", 3840, 2160)
    # an MP4 whose moov/mvhd says 2021-06-01 00:00:00 UTC
    t = 1622505600 + 2082844800
    mvhd = b"\x00\x00\x00\x00" + t.to_bytes(4, "big") * 2 + bytes(88)
    moov = (8 + 8 + len(mvhd)).to_bytes(4, "big") + b"moov" + (8 + len(mvhd)).to_bytes(4, "big") + b"mvhd" + mvhd
    p = tmp_path / "v.mp4"
    p.write_bytes((16).to_bytes(4, "big") + b"ftypisom" + bytes(4) + moov)
    assert mp4_creation_time(p) == 1622505600.0


def test_flight_built_from_video_log_and_camera(sim_logs, replayed_test_flight, tmp_path):
    """The tiny flight's video with its DataFlash .bin and camera.json, no flight directory written by hand: the
    start comes from the CAM events, and the replay maps every frame, about as the .tlog's."""
    from ground.replay import replay
    from pomar.assemble import assemble_flight

    flight, binf, _ = sim_logs
    _, _, ref = replayed_test_flight
    built = assemble_flight(flight.video, binf, str(flight.path / "camera.json"), tmp_path / "flight")
    meta = flight.meta()
    assert built["frames"] == meta.frame_count and built["fps"] == meta.fps and built["log_format"] == "dataflash"
    # frame 0's true capture time (the autopilot's clock; the video's own clock runs 0.1 s apart in this flight)
    assert "camera events" in built["start_from"] and abs(built["start_unix"] - flight.truth_frames()["t_unix"][0]) < 0.01
    rep = replay(built["flight_dir"], tmp_path / "out", detector="onnx", keyframe_every=1, keyframe_width=0, quiet=True)
    assert rep["frames"]["frames"] == 20 and rep["frames"]["missing_frames"] == 0
    assert 0.5 * ref["apples"] - 2 <= rep["apples"] <= 1.5 * ref["apples"] + 2, (rep["apples"], ref["apples"])


def test_python_m_pomar_builds_a_flight_that_sim_info_reads_through_its_own_log(sim_logs, tmp_path):
    """`python -m pomar flight` from the tiny flight's video, its DataFlash .bin and camera.json: the directory names
    the .bin (no telemetry.tlog in it), and `sim info` reads it with the DataFlash reader; a log that is not there is
    a clear error naming it, and no directory is written."""
    flight, binf, _ = sim_logs
    out = tmp_path / "built"
    r = subprocess.run([sys.executable, "-m", "pomar", "flight", "--video", str(flight.video), "--log", str(binf),
                        "--camera", str(flight.path / "camera.json"), "--out", str(out), "--json", str(tmp_path / "f.json")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "f.json").read_text())
    assert rep["frames"] == flight.meta().frame_count and rep["log_format"] == "dataflash"
    assert not (out / "telemetry.tlog").exists()
    r = subprocess.run([sys.executable, "-m", "sim", "info", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert f"telemetry (dataflash, {binf.name})" in r.stdout and "CAM " in r.stdout
    missing = tmp_path / "nowhere.bin"
    r = subprocess.run([sys.executable, "-m", "pomar", "flight", "--video", str(flight.video), "--log", str(missing),
                        "--camera", str(flight.path / "camera.json"), "--out", str(tmp_path / "not-built")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and str(missing) in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "not-built").exists()


def test_python_m_pomar_foresees_the_apples_size_as_the_onboard_node_does():
    """`python -m pomar scale` for the paper's setting (Phantom 4 Pro, 4K, 12 m, 30 degrees off nadir) against the
    shipped model's metadata: the scale the onboard node's policy gives for that radius."""
    from pomar.apple_scale import ScalePolicy, expected_radius_px
    from pomar.assemble import camera_for

    meta = Path(__file__).resolve().parents[1] / "onboard" / "models" / "apple-detector.json"
    r = subprocess.run([sys.executable, "-m", "pomar", "scale", "--camera", "phantom-4-pro", "--width", "3840",
                        "--height-m", "12", "--tilt-deg", "60", "--model", str(meta)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    cam, _ = camera_for("phantom-4-pro", 3840, 2160)
    radius = float(expected_radius_px(cam.fx, 12.0, 30.0))
    target = json.loads(meta.read_text())["apple_radius_px"]
    assert f"{radius:.2f} px" in r.stdout and f"{ScalePolicy(target_px=target).scale(radius):.2f}" in r.stdout
    assert 0.25 < ScalePolicy(target_px=target).scale(radius) < 1.0  # a 4K frame from 12 m is shrunk
    assert "inside its envelope" in r.stdout
    # 60 m up, the apples are under the model's envelope even enlarged twice: said, not silent
    r = subprocess.run([sys.executable, "-m", "pomar", "scale", "--camera", "phantom-4-pro", "--width", "3840",
                        "--height-m", "60", "--tilt-deg", "60", "--model", str(meta)], capture_output=True, text=True)
    assert r.returncode == 0 and "OUTSIDE its envelope" in r.stdout, r.stdout + r.stderr


@needs_logs
def test_a_log_from_another_time_is_refused(replay_test_flight, tmp_path):
    """A PX4 log without camera events, from 2024, with a video whose container says 2010: a clear error naming
    the log, and no flight directory half written."""
    from pomar.assemble import assemble_flight
    from pomar.flight import FlightFormatError

    video = tmp_path / "v.mp4"
    data = bytearray(replay_test_flight.video.read_bytes())
    i = data.find(b"mvhd")
    assert i > 0
    data[i + 8:i + 12] = (1262304000 + 2082844800).to_bytes(4, "big")  # 2010-01-01
    video.write_bytes(bytes(data))
    with pytest.raises(FlightFormatError, match=r"sample_px4_events\.ulg: its positions span .* do not overlap"):
        assemble_flight(video, LOGS / "px4-ulog/sample_px4_events.ulg", str(replay_test_flight.path / "camera.json"),
                        tmp_path / "flight")
    assert not (tmp_path / "flight").exists()


def test_frames_past_a_once_a_second_log_get_their_poses_from_the_map(replay_test_flight, tmp_path):
    """The tiny flight (4 s at 5 fps) with a Phantom 4 Pro's SRT, one subtitle a second: its last four frames lie
    past the last subtitle, without a position. With a keyframe every 3rd frame, its last frame also lies past the
    last keyframe: the map carries it on from the two posed frames before it (``extrapolated``). Every frame is posed,
    none skipped, and the carried-on frame lies where the truth has it, within a tenth of a frame's travel."""
    from ground.evaluation.scoring import map_shape_fit, replay_cameras
    from ground.replay import replay

    flight = replay_test_flight
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(flight.path), "--out", str(tmp_path / "logs"),
                        "--srt-layout", "p4p"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rep = replay(flight.path, tmp_path / "out", detector="onnx", keyframe_every=3, keyframe_width=0, quiet=True,
                 onboard_args=["--log", str(tmp_path / "logs" / "video.SRT")])
    n = flight.meta().frame_count
    fr = rep["frames"]
    assert fr["frames"] == n and fr["frames_without_pose"] == 0 and fr["telemetry"] == 0, fr
    assert fr["extrapolated"] >= 1, fr
    cams = replay_cameras(flight, tmp_path / "out")
    frames, centres, _ = cams
    assert sorted(frames) == list(range(n))
    fit = map_shape_fit(flight, tmp_path / "out", cams)[0]
    R_true, t_true = flight.truth_poses()
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    err = np.linalg.norm(fit.similarity.apply(centres) - C_true[frames], axis=1)
    travel = np.linalg.norm(np.diff(C_true, axis=0), axis=1).mean()
    last = frames == n - 1
    assert err[last][0] < 0.1 * travel + 0.02, (err[last], travel, np.median(err))
