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
    xy = rng.uniform(0, 600, (n, 2)).astype(np.float32)
    boxes = np.concatenate([xy - 4, xy + 4], axis=1)
    tel = wire.Telemetry(-28.5 + i * 1e-6, -50.9, 972.0, (1.0, 0.0, 0.0, 0.0), (0.5, 0.5, -0.5, 0.5), 3, 0.5, i % 3)
    return wire.FrameMessage("flight-1", "drone-1", i, 1.5e9 + i / 10, tel, 640, 480, boxes, rng.random(n).astype(np.float32))


def assert_same(a: wire.FrameMessage, b: wire.FrameMessage):
    assert (a.flight_id, a.drone_id, a.frame, a.t_capture, a.width, a.height) == (b.flight_id, b.drone_id, b.frame, b.t_capture, b.width, b.height)
    assert a.telemetry == b.telemetry
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)


def test_round_trips():
    for i in range(10):
        assert_same(frame(i), wire.FrameMessage.decode(frame(i).encode()))
    np.testing.assert_allclose(frame(3).centres, (frame(3).boxes[:, :2] + frame(3).boxes[:, 2:]) / 2)
    k = wire.KeyframeMessage("f", "d", 4, b"\xff\xd8\xff\xe0jpegdata")
    assert wire.decode(k.encode()) == k
    s = wire.StatusMessage("f", "d", 12.5, frames_read=10, frames_processed=8, frames_dropped=2, fps=3.0)
    assert wire.decode(s.encode()) == s
    c = wire.CameraMessage("f", "d", {"model": "PINHOLE", "width": 8, "height": 6, "params": [1, 1, 4, 3]}, 10.0, 5.0)
    assert wire.decode(c.encode()) == c


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
    with pytest.raises(wire.WireError, match="malformed"):
        wire.decode(msgpack.packb(d, use_bin_type=True))


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
