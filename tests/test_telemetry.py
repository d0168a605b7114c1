"""The onboard telemetry reader on real .tlog files: ours (against truth), a real ArduPilot SITL log,
and damaged copies (cut mid-packet, a 5 s gap, garbage)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from pomar.telemetry import Flags, TelemetryError
from pomar.telemetry.tlog import read_tlog
from pomar.rotations import camera_from_gimbal_attitude, quat_wxyz_to_rotation

SITL = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "tlogs" / "sitl_missionplanner.tlog"


def frame_samples(flight, tlog_path):
    meta = flight.meta()
    tl = read_tlog(tlog_path)
    t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps)
    s = tl.at(t)
    s["flags"] |= flags
    return tl, t, s


def test_bundled_tlog_reproduces_truth_at_frame_times(bundled_flight):
    tl, t, s = frame_samples(bundled_flight, bundled_flight.tlog)
    fr = bundled_flight.truth_frames()
    assert tl.clock == "SYSTEM_TIME of system 1" and tl.capture_message == "CAMERA_FEEDBACK" and not tl.gaps
    np.testing.assert_allclose(t, fr["t_unix"], atol=1e-5)  # capture records give the true capture times
    assert (s["flags"] == 0).all()
    sig = json.loads((bundled_flight.path / "sim_config.json").read_text())["telemetry"]
    o = bundled_flight.origin()
    err = o.to_enu(s["lat"], s["lon"], s["alt"]) - o.to_enu(fr["lat"], fr["lon"], fr["alt"])
    assert np.median(np.linalg.norm(err[:, :2], axis=1)) < 4 * sig["gps_noise_m"]
    assert np.median(np.abs(err[:, 2])) < 4 * sig["gps_alt_noise_m"]
    cam = bundled_flight.camera()
    r_cam = camera_from_gimbal_attitude(quat_wxyz_to_rotation(s["q_gimbal"]), cam.r_gimbal_from_camera)
    r_true = quat_wxyz_to_rotation(np.stack([fr[k] for k in ("qw", "qx", "qy", "qz")], 1)).as_matrix()
    ang = np.degrees(np.arccos(np.clip((np.trace(r_true @ r_cam, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.median(ang) < 1.0


def test_frame_times_without_capture_records_use_the_clock_offset(bundled_flight):
    meta = bundled_flight.meta()
    tl = read_tlog(bundled_flight.tlog)
    tl.captures = {}
    offset = json.loads((bundled_flight.path / "sim_config.json").read_text())["telemetry"]["clock_offset_s"]
    t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, clock_offset_s=offset)
    assert (flags == Flags.NO_CAPTURE_RECORD).all()
    np.testing.assert_allclose(t, bundled_flight.truth_frames()["t_unix"], atol=1e-5)


@pytest.mark.skipif(not SITL.exists(), reason="shared/datasets/tlogs not present")
def test_real_ardupilot_log():
    tl = read_tlog(SITL)
    assert tl.clock.startswith("SYSTEM_TIME") and len(tl.position) > 400 and len(tl.attitude) > 900
    assert tl.bad_packets == 2  # the log's own damaged packets are skipped and counted
    s = tl.at(tl.position.t[10:20])
    assert np.allclose(s["lat"], tl.position.values[10:20, 0]) and (np.abs(s["lat"] - 36.7) < 0.1).all()
    assert np.isfinite(s["q_attitude"]).all()
    assert (s["flags"] & Flags.NO_GIMBAL).all()  # this vehicle has no gimbal: said, not invented
    assert np.isnan(s["q_gimbal"]).all()
    assert tl.capture_message is None


def _rewrite(src: Path, dst: Path, keep) -> None:
    """Copy a .tlog record by record, keeping the messages keep(msg, t) accepts."""
    from pomar.mavlink import dialect

    dialect()
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(src), dialect="ardupilotmega")
    with open(dst, "wb") as f:
        while (m := conn.recv_match()) is not None:
            if m.get_type() != "BAD_DATA" and keep(m, m._timestamp):
                f.write(struct.pack(">Q", int(round(m._timestamp * 1e6))) + m.get_msgbuf())
    conn.close()


def test_tlog_cut_mid_packet_keeps_everything_before(bundled_flight, tmp_path):
    data = bundled_flight.tlog.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 7])
    full, part = read_tlog(bundled_flight.tlog), read_tlog(cut)
    assert part.truncated_bytes > 0 and full.truncated_bytes == 0
    n_full, n_part = sum(full.counts.values()), sum(part.counts.values())
    assert abs(n_part - n_full / 2) < n_full * 0.1  # about half, every whole record of it
    assert set(part.captures) == set(range(len(part.captures)))


def test_five_second_gap_is_reported_and_frames_flagged(bundled_flight, tmp_path):
    fr = bundled_flight.truth_frames()
    t0 = fr["t_unix"][40]
    gap = tmp_path / "gap.tlog"
    _rewrite(bundled_flight.tlog, gap, lambda m, t: not (t0 <= t < t0 + 5.0))
    tl, t, s = frame_samples(bundled_flight, gap)
    streams = {g.stream for g in tl.gaps}
    assert {"position", "attitude", "gimbal"} <= streams and all(4.5 < g.seconds < 6.0 for g in tl.gaps)
    in_gap = (fr["t_unix"] > t0 + 0.3) & (fr["t_unix"] < t0 + 4.7)
    assert in_gap.sum() > 30
    assert (s["flags"][in_gap] & Flags.POSITION_GAP).all() and (s["flags"][in_gap] & Flags.GIMBAL_GAP).all()
    assert (s["flags"][in_gap] & Flags.NO_CAPTURE_RECORD).all()  # their CAMERA_FEEDBACK is lost too
    far = (fr["t_unix"] < t0 - 1.5) | (fr["t_unix"] > t0 + 6.5)
    assert (s["flags"][far] == 0).all()


def test_not_a_tlog(tmp_path):
    with pytest.raises(TelemetryError, match="not found"):
        read_tlog(tmp_path / "none.tlog")
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 40)
    with pytest.raises(TelemetryError, match="no MAVLink"):
        read_tlog(junk)


AUTOPILOT = """
import sys, time
from pomar.mavlink import dialect
dialect()
from pymavlink import mavutil
src = mavutil.mavlink_connection(sys.argv[1], dialect="ardupilotmega")
out = mavutil.mavlink_connection("udpout:127.0.0.1:" + sys.argv[2], dialect="ardupilotmega", source_system=1)
msgs = []
while (m := src.recv_match()) is not None:
    msgs.append(m)
for m in msgs:
    out.write(m.get_msgbuf())
    time.sleep(0.0005)
comps, t0 = set(), time.time()
while time.time() - t0 < 4 and 191 not in comps:
    r = out.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
    if r is not None:
        comps.add(r.get_srcComponent())
print("heartbeat components", sorted(comps), flush=True)
"""


def test_live_udp_link_matches_the_file_and_identifies_as_companion(bundled_flight):
    import subprocess
    import sys
    import time

    from onboard.telemetry import LiveTelemetry
    from tests.test_wire import free_port

    port = free_port()
    live = LiveTelemetry(f"udpin:127.0.0.1:{port}", heartbeat_s=0.2)
    p = subprocess.Popen([sys.executable, "-c", AUTOPILOT, str(bundled_flight.tlog), str(port)],
                         stdout=subprocess.PIPE, text=True)
    try:
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
        time.sleep(0.3)
        snap = live.snapshot()
        live.close()
    assert "191" in out  # the autopilot side heard our HEARTBEAT as MAV_COMP_ID_ONBOARD_COMPUTER
    ref = read_tlog(bundled_flight.tlog)
    assert len(snap.position) >= 0.95 * len(ref.position) and len(snap.captures) >= 0.95 * len(ref.captures)
    t = ref.position.t[5:50]
    a, b = snap.at(t), ref.at(t)
    ok = np.isfinite(a["lat"])
    assert ok.mean() > 0.9
    np.testing.assert_allclose(a["lat"][ok], b["lat"][ok], atol=1e-7)


def test_gps_reports_that_stop_are_not_repeated(bundled_flight, tmp_path):
    """GPS_RAW_INT for the first 3 s only (as in an ArduPilot autotest log, 12 s of GPS against 302 s of
    positions): frames after it have no fix information, flagged, instead of the last fix repeated."""
    fr = bundled_flight.truth_frames()
    t_stop = fr["t_unix"][0] + 3.0
    short = tmp_path / "short-gps.tlog"
    _rewrite(bundled_flight.tlog, short, lambda m, t: m.get_type() != "GPS_RAW_INT" or t < t_stop)
    tl, t, s = frame_samples(bundled_flight, short)
    late = fr["t_unix"] > t_stop + 1.0
    early = fr["t_unix"] < t_stop - 0.5
    assert late.sum() > 100 and early.sum() > 20
    assert (s["gps_fix"][early] == 3).all() and np.isfinite(s["h_acc"][early]).all()
    assert (s["gps_fix"][late] == 0).all() and np.isnan(s["h_acc"][late]).all()
    assert (s["flags"][late] & Flags.NO_GPS_FIX).all() and not (s["flags"][late] & Flags.NO_POSITION).any()
    assert any("GPS reports span" in p for p in tl.problems)


def test_a_clock_offset_means_the_same_live_and_recorded():
    """--clock-offset-s is the camera's clock minus the log's, for a recorded video and a live camera alike: both put
    a frame at its camera time minus the offset (live added it, so a stated offset moved frames twice as far wrong)."""
    from onboard.live import LiveFrames
    from pomar.telemetry import TelemetryLog
    from tests.conftest import BUNDLED

    offset = 2.5
    tl = TelemetryLog.__new__(TelemetryLog)  # frame_times of a log with no camera events and no video clock
    tl.video_clock, tl.captures = np.zeros(0), {}
    t, _ = tl.frame_times(3, 1000.0, 10.0, clock_offset_s=offset)
    assert t[0] == 1000.0 - offset
    frames = LiveFrames(str(BUNDLED / "video.mp4"), telemetry=None, camera_fx=1000.0, clock_offset_s=offset)
    c = next(iter(frames))
    frames._frames._thread.join(60)  # the reader goes to the video's end: let it, not the interpreter's exit, stop it
    assert c.t_capture == c.t_read - offset
