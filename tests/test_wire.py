"""The wire format (round trips, clear errors) and its zenoh transport between processes on loopback."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import msgpack
import numpy as np
import pytest

from pomar import wire


def frame(i: int) -> wire.FrameMessage:
    rng = np.random.default_rng(i)
    n = i % 7
    xy = rng.uniform(4, 476, (n, 2)).astype(np.float32)
    boxes = np.concatenate([xy - 4, xy + 4], axis=1)
    tel = wire.Telemetry(-28.5 + i * 1e-6, -50.9, 972.0, (1.0, 0.0, 0.0, 0.0), (0.5, 0.5, -0.5, 0.5), 3, 0.5, i % 3,
                         12.0 + i, 0.1)
    return wire.FrameMessage("flight-1", "drone-1", i, 1.5e9 + i / 10, tel, 640, 480, boxes, rng.random(n).astype(np.float32))


def jpeg(w: int, h: int) -> bytes:
    import cv2

    img = np.random.default_rng(w * h).integers(0, 255, (h, w, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def assert_same(a: wire.FrameMessage, b: wire.FrameMessage):
    assert (a.flight_id, a.drone_id, a.frame, a.t_capture, a.width, a.height) == (b.flight_id, b.drone_id, b.frame, b.t_capture, b.width, b.height)
    assert a.telemetry == b.telemetry
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)


def test_round_trips():
    for i in range(10):
        assert_same(frame(i), wire.FrameMessage.decode(frame(i).encode()))


def test_telemetry_of_older_nodes_without_a_height_still_decodes():
    """Nodes and journals from before the height (8 fields): the height and its accuracy are unknown (NaN)."""
    t = wire.Telemetry.from_list(frame(3).telemetry.to_list()[:8])
    assert t.h_acc == 0.5 and np.isnan(t.height) and np.isnan(t.height_acc)
    with pytest.raises(wire.WireError, match="8 or 10 fields"):
        wire.Telemetry.from_list(frame(3).telemetry.to_list()[:9])
    np.testing.assert_allclose(frame(3).centres, (frame(3).boxes[:, :2] + frame(3).boxes[:, 2:]) / 2)
    k = wire.KeyframeMessage("f", "d", 4, jpeg(64, 48))
    assert wire.decode(k.encode()) == k and k.size == (64, 48)
    s = wire.StatusMessage("f", "d", 12.5, frames_read=10, frames_processed=8, frames_dropped=2, fps=3.0)
    assert wire.decode(s.encode()) == s and s.first_frame == 0
    s.first_frame = 120  # a node restarted mid-flight
    assert wire.decode(s.encode()) == s
    older = msgpack.unpackb(s.encode(), raw=False)
    del older["first_frame"]  # a node from before the first frame was said
    assert wire.decode(msgpack.packb(older, use_bin_type=True)).first_frame == 0
    c = wire.CameraMessage("f", "d", {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}, 10.0, 5.0)
    assert wire.decode(c.encode()) == c and c.keyframe_width == 0
    c.keyframe_width = 6
    assert wire.decode(c.encode()) == c
    older = msgpack.unpackb(c.encode(), raw=False)
    del older["kfw"]  # a node from before the keyframe width was said
    assert wire.decode(msgpack.packb(older, use_bin_type=True)).keyframe_width == 0
    assert c.altitude_reference is None and "altref" not in older  # not said: sea level, as a MAVLink position's
    for ref in wire.ALTITUDE_REFERENCES:
        c.altitude_reference = ref
        assert wire.decode(c.encode()).altitude_reference == ref
    odd = {**msgpack.unpackb(c.encode(), raw=False), "altref": "geoid"}
    with pytest.raises(wire.WireError, match="altitude reference must be one of") as e:
        wire.decode(msgpack.packb(odd, use_bin_type=True))
    assert e.value.reason == "out_of_range"
    f = frame(2)
    f.keyframe = True  # a keyframe of this frame follows
    assert wire.decode(f.encode()).keyframe is True and wire.decode(frame(2).encode()).keyframe is False
    older = msgpack.unpackb(f.encode(), raw=False)
    del older["kf"]  # a node from before frames announced their keyframes
    assert wire.decode(msgpack.packb(older, use_bin_type=True)).keyframe is False


def test_unknown_version_and_malformed_messages_are_clear_errors():
    d = msgpack.unpackb(frame(2).encode(), raw=False)
    d["v"] = 99
    with pytest.raises(wire.WireError, match="unknown schema version 99"):
        wire.decode(msgpack.packb(d, use_bin_type=True))
    with pytest.raises(wire.WireError, match="unknown schema version 99"):
        wire.FrameMessage.decode(msgpack.packb(d, use_bin_type=True))
    d["v"] = wire.SCHEMA_VERSION
    del d["tel"]
    with pytest.raises(wire.WireError, match="lacks field"):
        wire.decode(msgpack.packb(d, use_bin_type=True))
    with pytest.raises(wire.WireError, match="not a msgpack"):
        wire.decode(b"\xc1\xc1garbage")
    with pytest.raises(wire.WireError, match="not a JPEG"):
        wire.decode(wire.KeyframeMessage("f", "d", 1, b"PNG....").encode())
    d = msgpack.unpackb(frame(3).encode(), raw=False)
    d["n"] = 5  # more boxes than the bytes hold
    with pytest.raises(wire.WireError, match="5 boxes announced") as e:
        wire.decode(msgpack.packb(d, use_bin_type=True))
    assert e.value.reason == "malformed"


def _mutated(msg, **fields) -> bytes:
    d = msgpack.unpackb(msg.encode(), raw=False)
    d.update(fields)
    return msgpack.packb(d, use_bin_type=True)


def _reason(payload: bytes) -> str:
    with pytest.raises(wire.WireError) as e:
        wire.decode(payload)
    assert e.value.reason in wire.REASONS
    return e.value.reason


def test_every_field_is_validated_with_a_reason():
    f = frame(6)  # 6 boxes
    tel = f.telemetry.to_list()
    million = np.zeros((1_000_000, 4), "<f4")
    cases = {
        "too_many_boxes": _mutated(f, n=1_000_000, boxes=million.tobytes(), scores=np.zeros(1_000_000, "<f4").tobytes()),
        "not_finite": _mutated(f, boxes=np.full((6, 4), np.nan, "<f4").tobytes()),
        "box_outside_image": _mutated(f, boxes=(f.boxes + 1000).astype("<f4").tobytes()),
        "out_of_range": _mutated(f, frame=-1),
    }
    for reason, payload in cases.items():
        assert _reason(payload) == reason, reason
    for i, bad, reason in ((0, float("inf"), "not_finite"), (0, float("nan"), "not_finite"), (0, 91.0, "out_of_range"),
                           (3, [1.0, 1.0, 0.0, 0.0], "bad_quaternion"), (4, [0.5, float("nan"), 0.5, 0.5], "not_finite"),
                           (5, "3", "malformed"), (7, 1.5, "malformed")):
        t = list(tel)
        t[i] = bad
        assert _reason(_mutated(f, tel=t)) == reason, (i, bad)
    # unknown is NaN throughout, and allowed (the frame's flags say why)
    t = list(tel)
    t[0:3] = [float("nan")] * 3
    t[4] = [float("nan")] * 4
    assert np.isnan(wire.decode(_mutated(f, tel=t)).telemetry.lat)
    k = wire.KeyframeMessage("f", "d", 4, jpeg(64, 48))
    assert _reason(_mutated(k, frame="abc")) == "malformed"
    assert _reason(_mutated(k, frame=True)) == "malformed"
    assert _reason(_mutated(k, jpeg=jpeg(64, 48)[:-300])) == "bad_jpeg"  # cut short
    assert _reason(_mutated(k, flight="a/b")) == "malformed"
    c = wire.CameraMessage("f", "d", {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}, 10.0, 5.0)
    assert wire.decode(_mutated(c, fps=10)).fps == 10.0  # an int is a number
    assert _reason(_mutated(c, fps="10")) == "malformed"
    assert _reason(_mutated(c, kfw=-1)) == "out_of_range" and _reason(_mutated(c, kfw="960")) == "malformed"
    assert _reason(_mutated(f, kf=1)) == "malformed" and _reason(_mutated(f, kf="yes")) == "malformed"
    assert _reason(_mutated(c, fps=0)) == "out_of_range"
    assert _reason(_mutated(c, camera={"model": "PINHOLE", "width": 8})) == "malformed"
    st = wire.StatusMessage("f", "d", 12.5)
    assert _reason(_mutated(st, state="landed")) == "malformed"
    assert _reason(_mutated(st, frames_processed=-3)) == "out_of_range"
    assert _reason(_mutated(st, fps=float("inf"))) == "not_finite"


def test_no_decoder_exception_but_wire_error_on_garbled_messages():
    """Random changes to valid messages: each decodes, or raises WireError, never anything else."""
    rng = np.random.default_rng(0)
    msgs = [frame(5), wire.KeyframeMessage("f", "d", 4, jpeg(32, 24)), wire.StatusMessage("f", "d", 1.0),
            wire.CameraMessage("f", "d", {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}, 10.0)]
    junk = [None, True, -1, 2**63, 1e308, float("nan"), "x" * 3, b"\x00" * 5, [], [1, 2], {}, {"a": 1}, [[1]] * 8]
    refused = 0
    for _ in range(3000):
        m = msgs[rng.integers(len(msgs))]
        d = msgpack.unpackb(m.encode(), raw=False)
        k = list(d)[rng.integers(len(d))]
        if rng.random() < 0.5:
            d[k] = junk[rng.integers(len(junk))]
        else:
            del d[k]
        raw = msgpack.packb(d, use_bin_type=True)
        if rng.random() < 0.3:  # flip a byte of the packed message too
            i = int(rng.integers(len(raw)))
            raw = raw[:i] + bytes([raw[i] ^ int(rng.integers(1, 256))]) + raw[i + 1:]
        try:
            wire.decode(raw)
        except wire.WireError as exc:
            assert exc.reason in wire.REASONS
            refused += 1
    assert refused > 1500


def test_stream_filter_keeps_to_the_flight_and_its_drone():
    clock = [100.0]
    sf = wire.StreamFilter("flight-1", clock=lambda: clock[0], max_ahead_s=10.0)
    cam = wire.CameraMessage("flight-1", "drone-1", {"model": "PINHOLE", "width": 640, "height": 480,
                                                     "params": [500, 500, 320, 240]}, 10.0)

    def reason(payload, key=None):
        with pytest.raises(wire.WireError) as e:
            sf.accept(payload, key)
        return e.value.reason

    assert sf.accept(cam.encode(), "pomar/flight-1/drone-1/camera") is not None
    assert sf.drone_ids == {"drone-1"}  # the first drone heard
    for i in range(5):
        assert sf.accept(frame(i).encode(), "pomar/flight-1/drone-1/frames").frame == i
    assert sf.accept(frame(2).encode()) is None and sf.duplicates == 1  # a repeat
    far = wire.KeyframeMessage("flight-1", "drone-1", 99999, jpeg(640, 480))
    assert reason(far.encode()) == "frame_window"
    ahead = wire.KeyframeMessage("flight-1", "drone-1", 4 + 150, jpeg(640, 480))
    assert reason(ahead.encode()) == "frame_window"  # 15 s of video ahead, 10 allowed
    clock[0] += 6.0  # ... unless the stream was silent that long (a link outage)
    assert sf.accept(ahead.encode()).frame == 154
    evil = wire.FrameMessage("flight-1", "evil", 7, 1.5e9, frame(7).telemetry, 640, 480)
    assert reason(evil.encode(), "pomar/flight-1/evil/frames") == "other_drone"
    assert reason(frame(8).encode(), "pomar/flight-1/evil/frames") == "drone_mismatch"
    assert reason(frame(8).encode(), "pomar/flight-2/drone-1/frames") == "wrong_flight"
    small = frame(9)
    small.width, small.height = 320, 240
    small.boxes = small.boxes / 2
    assert reason(small.encode()) == "image_size"
    broken = bytearray(jpeg(640, 480))
    broken[broken.find(b"\xff\xda") + 1] = 0xFE  # header and end marker intact, no scan: no image
    assert reason(wire.KeyframeMessage("flight-1", "drone-1", 9, bytes(broken)).encode()) == "bad_jpeg"
    assert reason(wire.KeyframeMessage("flight-1", "drone-1", 9, jpeg(600, 480)).encode()) == "image_size"
    assert reason(wire.KeyframeMessage("flight-1", "drone-1", 9, jpeg(320, 240)).encode()) == "image_size"  # not 640 wide
    assert sf.rejected == {"frame_window": 2, "other_drone": 1, "drone_mismatch": 1, "wrong_flight": 1, "image_size": 3,
                           "bad_jpeg": 1}
    slow = wire.CameraMessage("flight-1", "drone-1", cam.camera, 0.01)  # would narrow the frame window to nothing
    assert reason(slow.encode()) == "camera_changed" and sf.fps == 10.0
    told = wire.StreamFilter("flight-1", drone_ids=["drone-2"])
    with pytest.raises(wire.WireError, match="not of"):
        told.accept(cam.encode())


def test_keys():
    assert wire.key("f-1", "d.2", "frames") == "pomar/f-1/d.2/frames"
    with pytest.raises(ValueError):
        wire.key("f/1", "d", "frames")
    with pytest.raises(ValueError):
        wire.key("f", "d", "video")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


PUBLISHER = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {tests!r})
    from test_wire import frame
    from pomar import transport, wire
    s = transport.open_session(listen=["tcp/127.0.0.1:{port}"])
    p = transport.FlightPublisher(s, "flight-1", "drone-1")
    for i in range({n}):
        p.publish(frame(i))
        if i == {bad_at}:
            p.put("frames", b"\\x81\\xa1v\\x63")  # a message of an unknown schema version (99)
    print("published", flush=True)
    time.sleep(120)  # closing a session with data queued loses it: the test stops us by PID
""")


def start_publisher(port: int, n: int, bad_at: int = -1) -> subprocess.Popen:
    code = PUBLISHER.format(tests=os.path.dirname(__file__), port=port, n=n, bad_at=bad_at)
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    return p


def receive(port: int, n: int, timeout: float = 20.0):
    from pomar import transport

    s = transport.open_session(connect=[f"tcp/127.0.0.1:{port}"])
    sub = transport.FlightSubscriber(s, "flight-1")
    got = {}
    t0 = time.monotonic()
    while len(got) < n and time.monotonic() - t0 < timeout:
        m = sub.recv(timeout=0.2)
        if m is not None:
            got[m.frame] = m
    errors = list(sub.errors)
    sub.close()
    s.close()
    return got, errors


def stop(p: subprocess.Popen):
    p.send_signal(signal.SIGTERM)
    try:
        p.wait(timeout=10)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


def test_every_frame_arrives_in_another_process_even_late_and_past_a_bad_message():
    port = free_port()
    p = start_publisher(port, 300, bad_at=150)
    try:
        assert p.stdout.readline().strip() == "published"  # everything is sent before we subscribe
        got, errors = receive(port, 300)
    finally:
        stop(p)
    assert sorted(got) == list(range(300))
    for i in (0, 150, 299):
        assert_same(got[i], frame(i))
    assert len(errors) == 1 and "unknown schema version 99" in errors[0]


def test_a_refreshed_subscriber_asks_for_the_history_again():
    """A ground missing frames at the end asks the publisher's history again: the repeats come, and are dropped."""
    from pomar import transport

    port = free_port()
    p = start_publisher(port, 50)
    s = None
    try:
        assert p.stdout.readline().strip() == "published"
        s = transport.open_session(connect=[f"tcp/127.0.0.1:{port}"])
        sub = transport.FlightSubscriber(s, "flight-1")
        got = set()
        t0 = time.monotonic()
        while len(got) < 50 and time.monotonic() - t0 < 20:
            if (m := sub.recv(timeout=0.2)) is not None:
                got.add(m.frame)
        assert len(got) == 50 and sub.duplicates == 0
        sub.refresh()
        t0 = time.monotonic()
        while sub.duplicates < 50 and time.monotonic() - t0 < 20:
            assert sub.recv(timeout=0.2) is None  # nothing new: only repeats
        assert sub.duplicates == 50 and sub.refreshes == 1
        sub.close()
    finally:
        if s is not None:
            s.close()
        stop(p)


def test_a_camera_message_says_whether_the_stream_is_paced():
    cam = {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}
    for paced in (True, False, None):
        assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0, paced=paced).encode()).paced is paced
    import msgpack

    d = msgpack.unpackb(wire.CameraMessage("f", "d", cam, 10.0, paced=True).encode())
    d["paced"] = "yes"
    with pytest.raises(wire.WireError, match="paced"):
        wire.CameraMessage.decode(msgpack.packb(d))


def test_a_camera_message_carries_the_detectors_smallest_reliable_apple():
    cam = {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0, min_apple_radius_px=3.0).encode()
                                     ).min_apple_radius_px == 3.0
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0).encode()).min_apple_radius_px == 0.0
    import msgpack

    d = msgpack.unpackb(wire.CameraMessage("f", "d", cam, 10.0, min_apple_radius_px=3.0).encode())
    d["minr"] = -1.0
    with pytest.raises(wire.WireError, match="min apple radius"):
        wire.CameraMessage.decode(msgpack.packb(d))


def test_a_camera_message_carries_the_detectors_box_response():
    cam = {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0, box_response=(0.84, 0.9)).encode()
                                     ).box_response == pytest.approx((0.84, 0.9))
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0).encode()).box_response is None
    import msgpack

    for bad, why in (([0.0, 0.9], "slope"), ([0.84], "slope, intercept"), ([0.84, float("nan")], "intercept")):
        d = msgpack.unpackb(wire.CameraMessage("f", "d", cam, 10.0, box_response=(0.84, 0.9)).encode())
        d["boxr"] = bad
        with pytest.raises(wire.WireError, match=why):
            wire.CameraMessage.decode(msgpack.packb(d))


def test_a_camera_message_carries_the_score_its_model_operates_at():
    cam = {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}
    m = wire.CameraMessage("f", "d", cam, 10.0, score_thresh=0.5, operating_score=0.75)
    back = wire.CameraMessage.decode(m.encode())
    assert back.operating_score == pytest.approx(0.75) and back.score_thresh == pytest.approx(0.5)
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0).encode()).operating_score is None
    import msgpack

    d = msgpack.unpackb(m.encode())
    d["ops"] = -0.2
    with pytest.raises(wire.WireError, match="operating score"):
        wire.CameraMessage.decode(msgpack.packb(d))


def test_a_camera_message_carries_the_score_the_drone_publishes_from():
    cam = {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0, score_thresh=0.7).encode()
                                     ).score_thresh == pytest.approx(0.7)
    assert wire.CameraMessage.decode(wire.CameraMessage("f", "d", cam, 10.0).encode()).score_thresh is None
    import msgpack

    d = msgpack.unpackb(wire.CameraMessage("f", "d", cam, 10.0, score_thresh=0.7).encode())
    d["pubs"] = 1.5
    with pytest.raises(wire.WireError, match="published score"):
        wire.CameraMessage.decode(msgpack.packb(d))
