"""The onboard node end to end: a replay published in one process, received in another (real zenoh,
real video, real .tlog); a truncated video ends with a clear error and loses nothing before it."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import numpy as np

from onboard.replay_detector import TruthReplayDetector
from pomar import transport, wire
from tests.test_wire import free_port, stop


def start_node(flight, port, *extra):
    cmd = [sys.executable, "-m", "onboard", "run", str(flight.path), "--detector", "truth-replay",
           "--listen", f"tcp/127.0.0.1:{port}", "--linger", "60", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def collect(port, flight_id, until_state=("finished", "error"), timeout=60.0):
    """Everything a ground would receive, until the node's final status (plus a second to drain:
    history from the different streams arrives in any order)."""
    s = transport.open_session(connect=[f"tcp/127.0.0.1:{port}"])
    sub = transport.FlightSubscriber(s, flight_id)
    got = {"frames": {}, "keyframes": {}, "statuses": [], "camera": None}
    t0 = time.monotonic()
    end = t0 + timeout
    while time.monotonic() < end:
        m = sub.recv(timeout=0.1)
        if isinstance(m, wire.FrameMessage):
            got["frames"][m.frame] = m
        elif isinstance(m, wire.KeyframeMessage):
            got["keyframes"][m.frame] = m
        elif isinstance(m, wire.CameraMessage):
            got["camera"] = m
        elif isinstance(m, wire.StatusMessage):
            got["statuses"].append(m)
            if m.state in until_state:
                end = min(end, time.monotonic() + 1.0)
    sub.close()
    s.close()
    return got["frames"], got["keyframes"], got["statuses"], got["camera"]


def test_replay_reaches_another_process(small_flight):
    port = free_port()
    p = start_node(small_flight, port, "--keyframe-every", "2")
    try:
        frames, keyframes, statuses, camera = collect(port, small_flight.meta().flight_id)
    finally:
        stop(p)
    meta = small_flight.meta()
    assert sorted(frames) == list(range(meta.frame_count))
    assert sorted(keyframes) == list(range(0, meta.frame_count, 2))
    assert statuses[-1].state == "finished" and statuses[-1].frames_processed == meta.frame_count
    assert camera is not None and camera.camera["width"] == meta.width
    det = TruthReplayDetector(small_flight.path)
    fr = small_flight.truth_frames()
    for i in (0, meta.frame_count // 2, meta.frame_count - 1):
        boxes, scores = det.detect(i)
        np.testing.assert_array_equal(frames[i].boxes, boxes)
        assert frames[i].t_capture == fr["t_unix"][i] or abs(frames[i].t_capture - fr["t_unix"][i]) < 1e-5
        assert frames[i].telemetry.flags == 0 and frames[i].telemetry.gps_fix == 3
    import cv2

    img = cv2.imdecode(np.frombuffer(keyframes[0].jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[0] > 0


def _truncated_copy(flight, dst, fraction, faststart):
    """A copy of the flight whose video is cut at `fraction` of its bytes. With faststart (the index at
    the front) the cut video decodes up to the cut; without it (as a camera that died mid-recording
    leaves it) it cannot be opened at all."""
    import imageio_ffmpeg

    shutil.copytree(flight.path, dst)
    video = dst / "video.mp4"
    if faststart:
        tmp = dst / "faststart.mp4"
        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(video), "-c", "copy",
                        "-movflags", "+faststart", str(tmp)], check=True)
        tmp.replace(video)
    data = video.read_bytes()
    video.write_bytes(data[: int(len(data) * fraction)])


def test_truncated_video_is_a_clear_error_and_keeps_what_was_sent(small_flight, tmp_path):
    from pomar.flight import FlightDir
    from pomar.video import count_frames

    meta = small_flight.meta()
    _truncated_copy(small_flight, tmp_path / "cut", 0.6, faststart=True)
    flight = FlightDir(tmp_path / "cut")
    decodable = count_frames(flight.video)
    assert 0 < decodable < meta.frame_count
    port = free_port()
    p = start_node(flight, port, "--keyframe-every", "0")
    try:
        frames, _, statuses, _ = collect(port, meta.flight_id)
    finally:
        stop(p)
        err = p.stderr.read()
    assert statuses[-1].state == "error" and "video.mp4" in statuses[-1].message and "truncated" in statuses[-1].message
    assert "truncated" in err
    assert sorted(frames) == list(range(decodable))  # every frame before the cut was published


def test_unopenable_video_is_a_clear_error(small_flight, tmp_path):
    from pomar.flight import FlightDir

    _truncated_copy(small_flight, tmp_path / "cut", 0.6, faststart=False)
    port = free_port()
    p = start_node(FlightDir(tmp_path / "cut"), port, "--linger", "0")
    out, err = p.communicate(timeout=60)
    # found before anything is published: an input error (exit 2), like a bad flight.json or camera.json
    assert p.returncode == 2 and "video.mp4" in err and "cannot open" in err


def test_keyframes_go_every_fifth_of_a_second_whatever_the_frame_rate():
    from onboard.node import KeyframePolicy

    rng = np.random.default_rng(0)

    def due(policy, fps, n=61):
        t = np.arange(n) / fps + rng.uniform(-0.003, 0.003, n)  # capture times jitter by milliseconds
        return [i for i in range(n) if policy.due(float(t[i]))]

    assert due(KeyframePolicy(), 10) == list(range(0, 61, 2))
    assert due(KeyframePolicy(), 15) == list(range(0, 61, 3))
    assert due(KeyframePolicy(), 30) == list(range(0, 61, 6))
    assert due(KeyframePolicy(every=3), 30) == list(range(0, 61, 3))  # a frame count alone is one
    assert due(KeyframePolicy(every=0), 30) == []  # none
    assert due(KeyframePolicy(every=3, every_s=0.5), 10) == list(range(0, 61, 5))  # time before the frame count


def test_live_node_enlarges_frames_only_as_far_as_it_keeps_up(small_flight, tmp_path):
    """Real time with the ONNX detector and --detector-scale auto: each frame goes at most at the scale the telemetry
    asks for, never below the frame's own size where that asks to enlarge, and the first frame (no time measured
    yet) at its own size. A slow machine keeps later frames at 1 too; a fast one enlarges them."""
    import json

    from onboard.detector import OnnxDetector
    from pomar.apple_scale import flight_radius_px, policy_for

    policy = policy_for(OnnxDetector(), "auto")
    asked = np.array([policy.scale(r) for r in flight_radius_px(small_flight)])
    assert (asked > 1).all()  # the small flight's apples are smaller than the model's: the policy enlarges
    port, summary = free_port(), tmp_path / "summary.json"
    p = start_node(small_flight, port, "--detector", "onnx", "--realtime", "--wait-for-ground", "30",
                   "--summary", str(summary), "--linger", "1")
    try:
        frames, _, statuses, _ = collect(port, small_flight.meta().flight_id)
    finally:
        stop(p)
    assert statuses[-1].state == "finished" and frames
    got = {i: m.scale for i, m in frames.items()}
    assert all(1.0 <= s <= asked[i] + 1e-9 for i, s in got.items())
    s = json.loads(summary.read_text())  # the node's own account: its first frame went at 1, capped
    assert s["detector_scale"]["min"] == 1.0 and s["detector_scale_capped"] >= 1
    assert s["frames_processed"] >= len(frames) > 0
