"""The apples' size as the drone's detector saw them (ground.link.envelope): frames under the detector's envelope are
counted and said once; the shipped model states its envelope."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ground.link.envelope import ApplesSeen
from pomar import wire
from pomar.apple_scale import envelope_height_m, expected_radius_px
from pomar.rotations import ned_euler_to_rotation, rotation_to_quat_wxyz

CAM = {"model": "PINHOLE", "width": 1280, "height": 720, "params": [1372.0, 1372.0, 640.0, 360.0]}


def _frame(i: int, height_m: float, scale: float) -> wire.FrameMessage:
    q = tuple(rotation_to_quat_wxyz(ned_euler_to_rotation(0.0, -60.0, 0.0, degrees=True)))  # 30 deg off nadir
    tel = wire.Telemetry(-28.5, -50.9, 900.0 + height_m, q, q, 3, 0.5, 0, height_m, 0.1)
    return wire.FrameMessage("f", "d", i, 1e9 + i, tel, 1280, 720, scale=scale)


def test_frames_whose_apples_reach_the_detector_under_its_envelope_are_counted_and_said_once(caplog):
    seen = ApplesSeen()
    seen.take(wire.CameraMessage("f", "d", CAM, 10.0, min_apple_radius_px=3.0))
    with caplog.at_level(logging.WARNING, logger="ground.link.envelope"):
        for i, (h, s) in enumerate([(12.0, 1.0), (12.0, 1.0), (20.0, 1.0), (20.0, 1.0), (20.0, 2.0)]):
            seen.take(wire.decode(_frame(i, h, s).encode()))  # as it comes off the wire
    rep = seen.report()
    r12 = float(expected_radius_px(1372.0, 12.0, 30.0))
    r20 = float(expected_radius_px(1372.0, 20.0, 30.0))
    assert r20 < 3.0 < r12 and 2 * r20 >= 3.0
    assert rep["frames_below"] == 2 and rep["first_frames_below"] == [2, 3]  # enlarged twice, frame 4 is inside
    assert rep["min_supported_px"] == 3.0 and np.isclose(rep["radius_px_min"], r20)
    assert len([m for m in caplog.messages if "below the 3.0 px" in m]) == 1
    # the highest flight inside the envelope, at the frames' own size: apples exactly at the minimum there
    top = envelope_height_m(1372.0, 30.0, 3.0, 1.0)
    assert np.isclose(float(expected_radius_px(1372.0, top, 30.0)), 3.0)


def test_a_drone_that_does_not_state_its_envelope_gets_sizes_but_no_flags():
    seen = ApplesSeen()
    seen.take(wire.CameraMessage("f", "d", CAM, 10.0))
    seen.take(_frame(0, 40.0, 1.0))
    rep = seen.report()
    assert rep["frames_below"] == 0 and rep["min_supported_px"] is None and rep["radius_px_median"] > 0


def test_the_shipped_model_states_its_envelope_below_its_working_size():
    meta = json.loads((Path(__file__).resolve().parents[1] / "onboard/models/apple-detector.json").read_text())
    assert 0 < meta["min_apple_radius_px"] < meta["apple_radius_px"]


def test_a_drone_that_publishes_fewer_detections_than_the_tracks_need_is_said_once(caplog):
    """The onboard node publishes from pomar.countable.PUBLISH_SCORE by default, from every entry point; a drone
    started with a higher --score-thresh leaves out detections the tracks need: the log says so once, the report too."""
    import subprocess
    import sys

    from pomar.countable import PUBLISH_SCORE

    seen = ApplesSeen()
    seen.take(wire.decode(wire.CameraMessage("f", "d", CAM, 10.0, score_thresh=PUBLISH_SCORE).encode()))
    assert seen.detections() == {"published_from": PUBLISH_SCORE, "needed_from": PUBLISH_SCORE, "short": False}
    with caplog.at_level(logging.WARNING, logger="ground.link.envelope"):
        for _ in range(2):  # a restarted drone sends its camera message again
            seen.take(wire.decode(wire.CameraMessage("f", "d", CAM, 10.0, score_thresh=0.9).encode()))
    assert seen.detections()["short"] and seen.detections()["published_from"] == 0.9
    assert len([m for m in caplog.messages if "publishes detections scored 0.90" in m]) == 1
    # every entry point that starts an onboard node says the same default in its help
    for argv in (["onboard", "run", "--help"], ["onboard", "live", "--help"]):
        out = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, timeout=60).stdout
        assert f"for a model without one {PUBLISH_SCORE}, pomar.countable.PUBLISH_SCORE" in " ".join(out.split())


def test_the_publish_score_follows_the_models_operating_score(caplog):
    """A model that stands by its detections from 0.75 publishes from PUBLISH_BELOW under it, as one at 0.9 publishes
    from 0.7: the band of weak views the tracks extend with. A model whose JSON gives its count's scores (chosen on
    tuning flights: the shipped one) confirms and publishes at those. The onboard node takes them from the model's
    JSON and says the confirm score in its camera message; a ground whose drone's model says 0.75 but publishes from
    0.7 says it fell short."""
    from argparse import Namespace

    from onboard.__main__ import _detector
    from onboard.loop import camera_message
    from pomar.countable import PUBLISH_BELOW, PUBLISH_SCORE, count_scores, publish_score

    assert publish_score(None) == PUBLISH_SCORE and publish_score(0.9) == PUBLISH_SCORE
    assert abs(publish_score(0.75) - (0.75 - PUBLISH_BELOW)) < 1e-9 and publish_score(0.1) == 0.0
    assert count_scores({"score_thresh": 0.75}) == (0.75, publish_score(0.75)) and count_scores({}) == (None, 0.7)
    assert count_scores({"score_thresh": 0.75, "count": {"confirm_score": 0.85, "publish_score": 0.55}}) == (0.85, 0.55)
    models = Path(__file__).resolve().parents[1] / "onboard" / "models"
    name = "apple-detector.onnx"
    meta = json.loads((models / name).with_suffix(".json").read_text())
    det = _detector(Namespace(detector="onnx", model=str(models / name), providers=None, score_thresh=None,
                              tile_size=1344, threads=1))
    confirm, publish = count_scores(meta)
    assert abs(det.score_thresh - publish) < 1e-9, name
    msg = wire.decode(camera_message("f", "d", CAM, 1280, 10.0, 0.0, 960, False, det, "takeoff").encode())
    assert msg.operating_score == confirm and msg.score_thresh == msg.needed_score == publish
    seen = ApplesSeen()  # a model whose count publishes further under its confirm score than the rule: not short
    seen.take(msg)
    assert seen.detections() == {"published_from": publish, "needed_from": publish, "short": False}
    seen = ApplesSeen()
    seen.take(wire.decode(wire.CameraMessage("f", "d", CAM, 10.0, score_thresh=publish_score(0.75),
                                             operating_score=0.75).encode()))
    assert not seen.detections()["short"]
    with caplog.at_level(logging.WARNING, logger="ground.link.envelope"):
        seen.take(wire.decode(wire.CameraMessage("f", "d", CAM, 10.0, score_thresh=PUBLISH_SCORE,
                                                 operating_score=0.75).encode()))
    assert seen.detections() == {"published_from": PUBLISH_SCORE, "needed_from": publish_score(0.75), "short": True}
    assert any("the tracks need them from 0.55" in m for m in caplog.messages)
