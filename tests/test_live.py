"""The onboard node live: a video played as a camera, a MAVLink autopilot on UDP loopback (a real .tlog
re-sent by pymavlink at its own pace), frames with telemetry out over real zenoh."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import numpy as np

from pomar import transport, wire


def _autopilot(tlog, url, stop: threading.Event, heard: list):
    """Re-send a .tlog's messages at their pace, with SYSTEM_TIME moved to now; note heartbeats heard back."""
    from pymavlink import mavutil

    src = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    out = mavutil.mavlink_connection(url, dialect="ardupilotmega", source_system=1, source_component=1)
    msgs = []
    while True:
        m = src.recv_match()
        if m is None:
            break
        if m.get_type() != "BAD_DATA":
            msgs.append(m)
    t0_log, t0 = msgs[0]._timestamp, time.time()
    for m in msgs:
        if stop.is_set():
            break
        delay = t0 + (m._timestamp - t0_log) - time.time()
        if delay > 0:
            time.sleep(delay)
        if m.get_type() == "SYSTEM_TIME":
            m.time_unix_usec = int((t0 + (m._timestamp - t0_log)) * 1e6)
        out.mav.send(m)
        r = out.recv_match(type="HEARTBEAT", blocking=False)
        if r is not None:
            heard.append((r.get_srcComponent(), r.type))


def _live_run(flight, flight_id: str, state_dir, *args: str) -> tuple[list, dict, list]:
    """One `onboard live` run (the test video as its camera at 5 fps, its .tlog re-sent as the autopilot) until it says
    it finished: the messages a ground got, the run's summary, and the heartbeats the autopilot heard back."""
    from ground.replay import free_port

    mav_port, zport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    stop, heard = threading.Event(), []
    node = subprocess.Popen([sys.executable, "-m", "onboard", "live", "--camera", str(flight.video),
                             "--play-fps", "5", "--mavlink", f"udpin:127.0.0.1:{mav_port}",
                             "--camera-json", str(flight.path / "camera.json"), "--flight-id", flight_id,
                             "--detector", "truth-replay", "--truth-flight", str(flight.path),
                             "--state-dir", str(state_dir), "--listen", endpoint, "--wait-for-ground", "30", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    threading.Thread(target=_autopilot, args=(flight.tlog, f"udpout:127.0.0.1:{mav_port}", stop, heard),
                     daemon=True).start()
    session = transport.open_session(connect=[endpoint])
    sub = transport.FlightSubscriber(session, flight_id)
    msgs = []
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60:
            m = sub.recv(timeout=0.5)
            if m is not None:
                msgs.append(m)
            if isinstance(m, wire.StatusMessage) and m.state in ("finished", "error"):
                break
        out, err = node.communicate(timeout=30)
    finally:
        stop.set()
        sub.close()
        session.close()
        if node.poll() is None:
            node.kill()
            node.wait()
    assert node.returncode == 0, err[-2000:]
    return msgs, json.loads(out[out.index("{"):]), heard


def test_live_camera_and_mavlink_to_zenoh(replay_test_flight, tmp_path):
    msgs, summary, heard = _live_run(replay_test_flight, "live-test", tmp_path, "--keyframe-every-s", "0.5",
                                     "--linger", "3")
    frames = [m for m in msgs if isinstance(m, wire.FrameMessage)]
    keyframes = [m for m in msgs if isinstance(m, wire.KeyframeMessage)]
    statuses = [m for m in msgs if isinstance(m, wire.StatusMessage)]
    assert statuses and statuses[-1].state == "finished"
    assert len(frames) == summary["frames_processed"] > 0
    assert summary["frames_read"] == 20
    # telemetry sampled live at each frame's capture time
    from pomar.telemetry import Flags

    lat = np.array([f.telemetry.lat for f in frames])
    ok = np.isfinite(lat)
    assert ok.mean() >= 0.8 and abs(np.nanmean(lat) - -28.516) < 0.01
    # the frames read before the autopilot's first messages are flagged, not filled in
    assert all(f.telemetry.flags & Flags.NO_POSITION for f, good in zip(frames, ok) if not good)
    # the gimbal is its own MAVLink component and its stream may start after the autopilot's position:
    # a frame without a gimbal attitude is flagged, never filled in
    gimbal = np.array([np.isfinite(f.telemetry.q_gimbal).all() for f in frames])
    assert gimbal.mean() >= 0.7
    assert all(f.telemetry.flags & (Flags.NO_GIMBAL | Flags.GIMBAL_GAP) for f, g in zip(frames, gimbal) if not g)
    # keyframes by time: about one every 0.5 s of a 4 s video
    assert 3 <= len(keyframes) <= 12
    # the node announced itself to the autopilot as a companion computer
    assert (191, 18) in heard  # MAV_COMP_ID_ONBOARD_COMPUTER, MAV_TYPE_ONBOARD_CONTROLLER



def test_a_live_node_restarted_mid_flight_goes_on_numbering_its_frames(replay_test_flight, tmp_path):
    """The ground drops a frame whose index it already passed: a node restarted mid-flight that numbered from 0 again
    would lose every frame until it caught up. Restarted with the same flight, it goes on from its last frame, the
    time it was down a gap; another flight starts from 0."""
    def frames(flight_id, n):
        msgs, summary, _ = _live_run(replay_test_flight, flight_id, tmp_path, "--max-frames", str(n), "--linger", "1")
        return [m.frame for m in msgs if isinstance(m, wire.FrameMessage)], summary

    first, s1 = frames("restart-test", 4)
    time.sleep(1.0)  # down for a second
    second, s2 = frames("restart-test", 4)
    assert first and second and first == sorted(first) and second == sorted(second)
    assert s1["resumed_after_frame"] is None and s2["resumed_after_frame"] == first[-1]
    assert second[0] > first[-1] + 1, (first, second)  # the second of downtime is a gap
    other, _ = frames("another-flight", 2)
    assert other[0] < first[-1]
