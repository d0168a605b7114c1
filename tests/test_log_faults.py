"""What a DJI grower's logs (and the other formats' faulty files) get: each fault found trying the README's DJI path
on real files, a refusal naming the file or a named problem with the frames flagged, never silence or a traceback.
Real files from ../shared/datasets/logs where one shows the fault; simulated ones beside them otherwise."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pomar.rotations import quat_wxyz_to_rotation, rotation_to_ned_euler
from pomar.telemetry import Flags, TelemetryError, read_log

LOGS = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "logs"
needs_logs = pytest.mark.skipif(not LOGS.is_dir(), reason="../shared/datasets/logs not present")
SRT = LOGS / "dji-srt"


def _set_creation_time(src: Path, dst: Path, unix: int) -> None:
    """A copy of an MP4 whose moov/mvhd creation time says ``unix``."""
    data = bytearray(src.read_bytes())
    i = data.find(b"mvhd")
    assert i > 0
    data[i + 8:i + 12] = (unix + 2082844800).to_bytes(4, "big")
    dst.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def srt_without_attitudes(replay_test_flight, tmp_path_factory):
    """The tiny simulated flight's telemetry as a Mavic 3 SRT without attitude fields, as most DJI drones write."""
    out = tmp_path_factory.mktemp("srt-no-att")
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(replay_test_flight.path), "--out", str(out),
                        "--no-attitude"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return replay_test_flight, out / "video.SRT", out / "telemetry.bin"


@needs_logs
@pytest.mark.parametrize("name", ["p4p_sample.SRT", "mavic3.srt", "matrice_300.srt", "mavic_pro.SRT"])
def test_a_real_srt_without_attitudes_gives_the_camera_a_fixed_mount(name):
    """Every real SRT without gimbal angles took the track-heading path that scipy 1.17 refuses (a 1-D yaw for one
    axis): each frame now gets a camera attitude, flagged FIXED_MOUNT, pitched down by the tilt."""
    tl = read_log(SRT / name)
    assert not len(tl.gimbal) and not len(tl.attitude)
    t = np.linspace(tl.position.t[0], tl.position.t[-1], 40)
    s = tl.at(t, 60.0, 90.0)
    moving = np.isfinite(s["q_gimbal"]).all(1)
    assert moving.sum() >= 30
    assert (s["flags"][moving] & Flags.FIXED_MOUNT).all()
    pitch = rotation_to_ned_euler(quat_wxyz_to_rotation(s["q_gimbal"][moving]))[:, 1]
    np.testing.assert_allclose(pitch, -60.0, atol=1e-6)


def test_camera_yaw_turns_the_fixed_mount_from_the_track(srt_without_attitudes):
    """The paper's flight: along the row, the camera looking across it. With --camera-yaw-deg 90 the SRT's camera
    attitude is the true gimbal's within the flight's wobble; looking along the track (yaw 0) it is 90 degrees off."""
    flight, srtf, _ = srt_without_attitudes
    meta = flight.meta()
    ref = read_log(flight.tlog)
    t_ref, _ = ref.frame_times(meta.frame_count, meta.video_start_utc, meta.fps)
    q_true = quat_wxyz_to_rotation(ref.at(t_ref)["q_gimbal"])
    tl = read_log(srtf)
    t, _ = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps)
    err = {}
    for yaw in (90.0, 0.0):
        q = tl.at(t, 60.0, yaw)["q_gimbal"]
        err[yaw] = np.degrees(np.median((quat_wxyz_to_rotation(q).inv() * q_true).magnitude()))
    assert err[90.0] < 5.0 and abs(err[0.0] - 90.0) < 10.0, err


def test_a_track_heading_from_rounded_positions_points_along_the_track_at_every_frame(tmp_path):
    """A Mavic 3 SRT's positions to 5 decimals (1.1 m) once a frame, flying east at 2 m/s: two neighbours are often
    the same, or a rounding step apart. The heading is taken over TRACK_HEADING_S of track, so no frame's camera
    points anywhere (from neighbours: north where two were the same, and 123 or 159 degrees in a flight heading 90)."""
    lines = []
    for i in range(300):  # 30 s at 10 Hz
        t = i * 0.1
        lat, lon = -28.516261, -50.881253 + 2.0 * t / (111320.0 * np.cos(np.radians(28.516261)))
        lines.append(f"{i + 1}\n00:00:{t:06.3f} --> 00:00:{t + 0.1:06.3f}\n".replace(".", ",")
                     + f'<font size="28">FrameCnt: {i + 1}, DiffTime: 100ms\n2023-05-01 10:00:{t:06.3f}\n'
                     + f"[latitude: {lat:.5f}] [longitude: {lon:.5f}] [rel_alt: 12.000 abs_alt: 900.000] </font>\n")
    srtf = tmp_path / "DJI_0001.SRT"
    srtf.write_text("\n".join(lines))
    tl = read_log(srtf)
    t = tl.position.t[10:-10]
    yaw = rotation_to_ned_euler(quat_wxyz_to_rotation(tl.at(t, 60.0, 90.0)["q_gimbal"]))[:, 2]
    assert np.abs(yaw - 180.0).max() < 10.0, np.round(yaw, 1)


@needs_logs
def test_phantom_4_rtk_angles_are_read_and_the_jump_between_two_drones_is_named():
    """F.PRY (pitch, roll, yaw) is the vehicle's attitude and G.PRY the gimbal's; the 112-m jump to the Mavic 2 Pro's
    lines is a named problem, and frames between the two positions get none (POSITION_JUMP), not a point between."""
    tl = read_log(SRT / "mix_p4rtk_mavic2pro.srt")
    assert len(tl.attitude) == 6 and len(tl.gimbal) == 6
    veh = rotation_to_ned_euler(quat_wxyz_to_rotation(tl.attitude.values))
    gim = rotation_to_ned_euler(quat_wxyz_to_rotation(tl.gimbal.values))
    np.testing.assert_allclose(veh[0], [2.9, -8.9, -75.0], atol=1e-6)  # roll, pitch, yaw
    np.testing.assert_allclose(gim[0], [0.0, -27.3, -76.0], atol=1e-6)
    assert not any("no gimbal" in p for p in tl.problems)
    assert any("jumps 112 m" in p for p in tl.problems), tl.problems
    assert any("layouts in one file" in p for p in tl.problems), tl.problems
    j = tl.jumps[0]
    s = tl.at(np.array([j.start - 0.5, (j.start + j.end) / 2]))
    assert np.isfinite(s["lat"][0]) and not s["flags"][0] & Flags.POSITION_JUMP
    assert np.isnan(s["lat"][1]) and s["flags"][1] & Flags.POSITION_JUMP


@needs_logs
def test_frames_past_a_short_srt_fall_outside_it_and_a_late_first_subtitle_starts_the_video_earlier():
    """A video longer than its SRT (air2s.srt: 17 subtitles, 0.57 s): the frames past it carry on at the video's
    rate and are flagged NO_POSITION, not frozen on its last entry. An SRT whose first subtitle is at 1 s
    (mavic_pro.SRT): the video starts 1 s before it."""
    from pomar.assemble import start_time

    tl = read_log(SRT / "air2s.srt")
    n, fps = 100, 30.0
    t, _ = tl.frame_times(n, 0.0, fps)
    assert (np.diff(t) > 0).all()
    s = tl.at(t)
    past = t > tl.position.t[-1]
    assert past.sum() >= 80 and (s["flags"][past] & Flags.NO_POSITION).all() and np.isnan(s["lat"][past]).all()
    tl = read_log(SRT / "mavic_pro.SRT")
    t0, how, _ = start_time(tl, 30.0, None)
    assert "subtitles" in how and abs(t0 - (tl.position.t[0] - 1.0)) < 1e-6


@needs_logs
def test_an_srt_of_another_year_than_its_video_is_refused(replay_test_flight, tmp_path):
    """The Mavic 3's real SRT (2021) beside a video whose container says 2033: refused, naming the SRT and the way
    out (--clock-offset-s), and no flight directory written; the same clock offset given by hand is accepted."""
    from pomar.assemble import assemble_flight
    from pomar.flight import FlightFormatError

    video = tmp_path / "v.mp4"
    _set_creation_time(replay_test_flight.video, video, 1988150400)  # 2033-01-01
    cam = str(replay_test_flight.path / "camera.json")
    with pytest.raises(FlightFormatError, match=r"mavic3\.srt: the log puts the video's start at 2021-12-25 .*"
                                                r"2033-01-01.*--clock-offset-s"):
        assemble_flight(video, SRT / "mavic3.srt", cam, tmp_path / "flight")
    assert not (tmp_path / "flight").exists()
    tl = read_log(SRT / "mavic3.srt")
    offset = 1988150400 - float(tl.log_time_of_video(0.0))
    assemble_flight(video, SRT / "mavic3.srt", cam, tmp_path / "flight", clock_offset_s=offset)


@needs_logs
def test_a_subtitle_cut_mid_number_is_cut_not_a_jump(tmp_path):
    """air2s.srt cut inside its last longitude (`[longitude: 2.1`): that subtitle is reported cut short and not read
    as lon 2.1 (5.2 km away)."""
    text = (SRT / "air2s.srt").read_text(encoding="utf-8-sig")
    i = text.rindex("[longitude: 2.") + len("[longitude: 2.1")
    cut = tmp_path / "cut.srt"
    cut.write_text(text[:i], encoding="utf-8")
    full, part = read_log(SRT / "air2s.srt"), read_log(cut)
    assert len(part.position) == len(full.position) - 1
    assert not part.jumps and part.summary_dict()["max_jump_m"] < 50
    assert any("cut short" in p for p in part.problems), part.problems


def test_a_jump_in_any_log_is_named_and_its_frames_flagged(srt_without_attitudes, tmp_path):
    """One subtitle of the simulated SRT moved 300 m (a glitch): a problem names the jump, and only the frames
    between the glitch and its neighbours lose their position."""
    _, srtf, _ = srt_without_attitudes
    text = srtf.read_text()
    blocks = text.split("\n\n")
    k = len(blocks) // 2
    lat = float(blocks[k].split("[latitude: ")[1].split("]")[0])
    blocks[k] = blocks[k].replace(f"[latitude: {lat:.5f}]", f"[latitude: {lat + 0.0027:.5f}]")
    bad = tmp_path / "glitch.SRT"
    bad.write_text("\n\n".join(blocks))
    tl = read_log(bad)
    assert len(tl.jumps) == 2 and sum("the position jumps" in p for p in tl.problems) == 2, tl.problems
    s = tl.at(tl.position.t)
    assert (s["flags"] & Flags.POSITION_JUMP).sum() == 0  # the samples themselves sit on the ends of the jumps
    mid = np.array([(j.start + j.end) / 2 for j in tl.jumps])
    assert (tl.at(mid)["flags"] & Flags.POSITION_JUMP).all()
    assert not read_log(srtf).jumps


@needs_logs
def test_repeated_dates_are_named_not_dropped_silently():
    """mavic_2_style.SRT: 468 subtitles, 5 with a date an earlier one had: the problems say so."""
    tl = read_log(SRT / "mavic_2_style.SRT")
    assert len(tl.position) == 463
    assert any(p.startswith("5 subtitle(s) repeat an earlier subtitle's time") for p in tl.problems), tl.problems


@needs_logs
@pytest.mark.parametrize("name", ["mavic3.srt", "p4p_sample.SRT", "matrice_300.srt"])
def test_srt_positions_stand_for_a_gps_fix(name):
    """DJI writes a position only with a fix (0, 0 before): its frames are not flagged NO_GPS_FIX."""
    tl = read_log(SRT / name)
    s = tl.at(tl.position.t)
    assert not (s["flags"] & Flags.NO_GPS_FIX).any()
    assert not (s["flags"] & Flags.incomplete() & ~Flags.NO_GIMBAL).any()


def test_dataflash_cut_one_to_three_bytes_into_a_record_is_named(srt_without_attitudes, tmp_path):
    """A .bin that ends 1, 2 or 3 bytes into a new record (DFReader's own offset does not show it)."""
    _, _, binf = srt_without_attitudes
    data = binf.read_bytes()
    for k in (1, 2, 3):
        cut = tmp_path / f"cut{k}.bin"
        cut.write_bytes(data + data[:k])  # the head of the file's first record: A3 95 and its type
        tl = read_log(cut)
        assert any(f"the last {k} bytes are no whole record" in p for p in tl.problems), (k, tl.problems)
    assert not any("whole record" in p for p in read_log(binf).problems)


def test_random_bytes_are_not_a_tlog(tmp_path):
    """Random bytes named .tlog: refused, one line naming the file, exit 2."""
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(np.random.default_rng(5).integers(0, 256, 200_000, dtype=np.uint8).tobytes())
    with pytest.raises(TelemetryError, match="junk.tlog: no position, GPS, attitude"):
        read_log(junk)
    r = subprocess.run([sys.executable, "-m", "onboard", "telemetry", str(junk)], capture_output=True, text=True)
    assert r.returncode == 2 and str(junk) in r.stderr and "Traceback" not in r.stderr


def test_bad_command_line_inputs_are_one_line_errors(replay_test_flight, tmp_path):
    """A binary file as --camera, a folder as --log, a width of 0: exit 2, one line naming what is wrong."""
    flight = replay_test_flight
    runs = {
        "binary camera": (["pomar", "flight", "--video", str(flight.video), "--log", str(flight.tlog), "--camera",
                           str(flight.video), "--out", str(tmp_path / "a")], f"{flight.video}: not a camera.json"),
        "folder log": (["pomar", "flight", "--video", str(flight.video), "--log", str(flight.path), "--camera",
                        str(flight.path / "camera.json"), "--out", str(tmp_path / "b")], "is a folder, not a log file"),
        "width 0": (["pomar", "cameras", "--width", "0"], "must be at least 1 pixel"),
    }
    for what, (argv, said) in runs.items():
        r = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True)
        assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, (what, r.stderr)


def test_a_replay_whose_onboard_node_fails_at_once_prints_no_traceback(replay_test_flight, tmp_path):
    """The onboard node refuses the flight (camera.json for another image size) and exits at once; the ground
    started beside it is stopped while it is still starting: one clear error, no KeyboardInterrupt traceback."""
    import json
    import shutil

    flight = tmp_path / "flight"
    shutil.copytree(replay_test_flight.path, flight)
    cam = json.loads((flight / "camera.json").read_text())
    cam["width"] = 1280
    (flight / "camera.json").write_text(json.dumps(cam))
    r = subprocess.run([sys.executable, "-m", "ground", "replay", str(flight), "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "the onboard node failed before it sent a frame" in r.stderr, r.stderr
    assert "Traceback" not in r.stdout + r.stderr
    assert "Traceback" not in (tmp_path / "out" / "ground.log").read_text()


def test_a_gimbal_whose_yaw_is_in_the_vehicle_frame_is_turned_by_the_vehicle_yaw():
    """GIMBAL_DEVICE_ATTITUDE_STATUS without the earth-frame flag: its yaw is the vehicle's plus its own (the path
    took a 1-D yaw that scipy 1.17 refuses, as the DJI fixed mount did)."""
    from pomar.mavlink import dialect
    from pomar.rotations import ned_euler_to_rotation, rotation_to_quat_wxyz
    from pomar.telemetry.tlog import MavlinkAccumulator

    m = dialect().MAVLink(None, srcSystem=1, srcComponent=1)
    acc = MavlinkAccumulator()
    q_rel = rotation_to_quat_wxyz(ned_euler_to_rotation(0.0, -60.0, 90.0))  # pitched down, turned right
    for k in range(10):
        for msg in (m.system_time_encode(int((1.7e9 + k * 0.1) * 1e6), k * 100),
                    m.attitude_encode(k * 100, 0.0, 0.0, np.radians(30.0), 0.0, 0.0, 0.0),
                    m.global_position_int_encode(k * 100, -285000000, -508000000, 960000, 12000, 0, 0, 0, 0),
                    m.gimbal_device_attitude_status_encode(1, 1, k * 100, 0, [float(x) for x in q_rel], 0.0, 0.0,
                                                           0.0, 0)):
            msg._timestamp = 1.7e9 + k * 0.1
            msg._header.srcSystem = 1
            acc.add(msg)
    tl = acc.build("synthetic", quiet=True)
    yaw = rotation_to_ned_euler(quat_wxyz_to_rotation(tl.gimbal.values))[:, 2]
    np.testing.assert_allclose(yaw, 120.0, atol=1e-6)
