"""A hostile peer on the link, for test_hostile_link: connects to a ground's zenoh endpoint and, on "go" from
stdin, publishes one of each message in issue 18's table into the live flight; then prints what it sent.

    python tests/hostile_injector.py ENDPOINT FLIGHT_ID DRONE_ID CAMERA_JSON
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import msgpack
import numpy as np
import zenoh

from pomar import transport, wire


def _packed(msg, **fields) -> bytes:
    d = msgpack.unpackb(msg.encode(), raw=False)
    d.update(fields)
    return msgpack.packb(d, use_bin_type=True)


def main() -> int:
    endpoint, flight, drone, camera_json = sys.argv[1:5]
    camera = json.loads(open(camera_json).read())
    fps = json.loads((Path(camera_json).parent / "flight.json").read_text())["fps"]
    w, h = camera["width"], camera["height"]
    session = transport.open_session(connect=[endpoint])
    # a put before the link to the ground is up goes nowhere: wait for it, and for the ground's subscription to
    # be known here, before saying ready, so that on "go" everything lands while the 4-s flight still runs
    t0 = time.monotonic()
    while not list(session.info.peers_zid()) and time.monotonic() - t0 < 30:
        time.sleep(0.1)
    time.sleep(0.5)
    img = np.full((h, w, 3), 128, np.uint8)
    cv2.putText(img, "not this flight", (10, h // 2), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 0, 255), 2)
    jpeg = cv2.imencode(".jpg", img)[1].tobytes()
    tel = wire.Telemetry(-28.5, -50.9, 972.0, (1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 3, 0.5, 0)
    nan_tel = wire.Telemetry(float("nan"), float("inf"), 972.0, (float("nan"), 0.0, 0.0, 1.0), tel.q_gimbal, 3, 0.5, 0)
    one_box = (np.array([[10, 10, 20, 20]], np.float32), np.array([0.99], np.float32))
    million = wire.FrameMessage(flight, "other-drone", 5, 1.5e9, tel, w, h)
    sent = {  # what each case is expected to be refused as ("accepted": a valid message that must do no harm)
        "keyframe 99999": ("keyframes", drone, wire.KeyframeMessage(flight, drone, 99999, jpeg).encode(), "frame_window"),
        "1,000,000 boxes, other drone": ("frames", "other-drone", _packed(
            million, n=1_000_000, boxes=np.zeros((1_000_000, 4), "<f4").tobytes(),
            scores=np.zeros(1_000_000, "<f4").tobytes()), "too_many_boxes"),
        "finished while flying": ("status", drone, wire.StatusMessage(flight, drone, time.time(), 1, 1, 0, 5.0, 0.1,
                                                                      "finished").encode(), "accepted"),
        "keyframe frame 'abc'": ("keyframes", drone, _packed(wire.KeyframeMessage(flight, drone, 3, jpeg), frame="abc"),
                                 "malformed"),
        "camera fps string": ("camera", drone, wire.CameraMessage(flight, drone, camera, "10").encode(), "malformed"),
        "camera fps int": ("camera", drone, wire.CameraMessage(flight, drone, camera, int(fps)).encode(), "accepted"),
        "camera fps changed": ("camera", drone, wire.CameraMessage(flight, drone, camera, 0.01).encode(), "camera_changed"),
        "garbage": ("frames", drone, b"\xc1\x00garbage", "not_msgpack"),
        "valid frame, other drone": ("frames", "evil", wire.FrameMessage(flight, "evil", 6, 1.5e9, tel, w, h,
                                                                         *one_box).encode(), "other_drone"),
    }
    for i in (106, 107, 108):  # NaN / inf telemetry and NaN boxes, under the flight's drone and another
        for who in (drone, "evil"):
            m = wire.FrameMessage(flight, who, i, 1.5e9, nan_tel, w, h, np.full((1, 4), np.nan, np.float32),
                                  np.array([0.9], np.float32))
            sent[f"NaN frame {i} ({who})"] = ("frames", who, m.encode(), "not_finite")
    print("ready", flush=True)
    sys.stdin.readline()
    for name, (kind, who, payload, _) in sent.items():
        # blocking: zenoh's default drops a message (the 20-MB one) when its queue is full
        session.put(f"pomar/{flight}/{who}/{kind}", payload, congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.01)
    print(json.dumps({name: v[3] for name, v in sent.items()}), flush=True)
    sys.stdin.readline()  # the test stops us once the ground is done
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
