"""The shipped detector through onnxruntime (no torch): it finds apples, tiling reports a cut apple once,
bad model files give clear errors."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from onboard.detector import DEFAULT_MODEL, ModelError, OnnxDetector, tiles



def test_the_shipped_model_is_in_the_checkout():
    """The model ships with the repository: a checkout without it is broken, not a reason to skip these tests."""
    assert DEFAULT_MODEL.is_file(), f"{DEFAULT_MODEL} is missing from this checkout"


@pytest.fixture(scope="module")
def detector():
    return OnnxDetector()


def _centres(b):
    return np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2])


def test_default_model_is_found_with_its_metadata(detector):
    assert detector.path == DEFAULT_MODEL and detector.providers == ["CPUExecutionProvider"]
    m = detector.meta
    assert m["pixel_convention"].startswith("OpenCV") and 0 < m["score_thresh"] < 1
    assert m["metrics"]["add256_test"]["ap50"] > 0 and "training" in m
    # its threads sleep between operators rather than spin on cores the node shares
    assert detector.session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning") == "0"


def _add256_smoke(det, n: int = 20) -> dict:
    """Precision and recall of ``det`` at its threshold on the first n ADD256 test patches; skips the test
    where ADD256 is not at hand (CI)."""
    from export.data import DataError, add256_split, find_add256, read_rgb
    from export.metrics import evaluate_detections

    try:
        root = find_add256()
    except DataError:  # only its absence skips: a broken split or reader fails the test
        pytest.skip("ADD256 is not available here")
    test = add256_split(root, "test")[:n]
    preds = [det.detect_rgb(read_rgb(p)) for p, _ in test]
    return evaluate_detections(preds, [(b, None) for _, b in test], det.score_thresh)


def test_shipped_model_finds_apples_on_add256(detector):
    m = _add256_smoke(detector)
    assert m["recall"] > 0.5 and m["precision"] > 0.5, m


def test_shipped_model_finds_apples_on_a_frame_of_the_bundled_flight(detector, bundled_flight):
    """Data shipped with the repository: never skipped. A frame of the bundled flight (1280x720, apples of 6-12 px)."""
    from pomar.video import read_frame

    img = read_frame(bundled_flight.video, 80)
    boxes, scores = detector.detect(80, img)
    d = bundled_flight.truth_detections()
    sel = (d["frame"] == 80) & (d["visible_fraction"] >= 0.5)
    truth = np.column_stack([d["u"][sel], d["v"][sel]])
    c = _centres(boxes)
    found = (np.linalg.norm(truth[:, None] - c[None], axis=2).min(1) < 4).mean() if len(c) else 0.0
    assert found > 0.5 and len(boxes) < 3 * len(truth), (found, len(boxes), len(truth))


#: The shipped model sees real orchards (issue 70): MobileNetV2-FPN from ImageNet weights, trained on this CPU
#: (export/training).
REAL_MODEL = DEFAULT_MODEL


def test_the_real_orchard_model_loads_with_what_it_was_chosen_on():
    """The shipped model loads with its metadata: its count's scores chosen on tuning flights (confirming no lower
    than it publishes), its apple size and box response measured on tuning flights, its run the committed training
    state's."""
    from pomar.countable import count_scores

    det = OnnxDetector(REAL_MODEL)
    m = det.meta
    assert "tuning flights" in m["count"]["chosen_on"] and 4 <= det.apple_radius_px <= 7
    confirm, publish = count_scores(m)
    assert 0 < publish < confirm < 1
    assert "tuning flights" in m["apple_radius_px_chosen_on"] and "tune-" in m["box_response"]["measured"]
    assert m["training"]["backbone"] == "mobilenet_v2" and m["training"]["imagenet"] and m["training"]["bbch_tiles"] > 0
    assert m["metrics"]["applebbch76_held_out"]["ap50"] >= 0.75 and m["metrics"]["add256_test"]["ap50"] >= 0.759
    r = _add256_smoke(det)
    assert r["recall"] > 0.6 and r["precision"] > 0.6, r


def test_tiling_reports_an_apple_cut_by_a_tile_border_once(detector, bundled_flight):
    from pomar.video import read_frame

    img = read_frame(bundled_flight.video, 80)
    whole_b, _ = OnnxDetector(detector.path, tile_size=4096).detect(80, img)
    c = _centres(whole_b)
    # A crop 1184 px wide is two tiles of 640 px overlapping by 96: [0, 640) and [544, 1184); the first
    # tile's right border is x = 640, the middle of the overlap (where ownership changes) x = 592.
    assert sorted({t[:3:2] for t in tiles(1184, 720, 640, 96)}) == [(0, 640), (544, 1184)]
    tiled = OnnxDetector(detector.path, tile_size=640, overlap=96)
    checked = 0
    for border in (640.0, 592.0):
        for i in np.argsort(np.abs(c[:, 0] - border - 48)):
            x0 = int(round(c[i, 0] - border))
            if 0 <= x0 <= 1280 - 1184:
                break
        else:
            continue
        crop = np.ascontiguousarray(img[:, x0:x0 + 1184])
        ref = c[i] - [x0, 0]
        assert abs(ref[0] - border) < 1
        whole_here = np.linalg.norm(_centres(OnnxDetector(detector.path, tile_size=4096).detect(0, crop)[0]) - ref, axis=1)
        if (whole_here < 6).sum() != 1:
            continue  # the apple is not found whole in this crop either: nothing to compare
        near = np.linalg.norm(_centres(tiled.detect(0, crop)[0]) - ref, axis=1) < 6
        assert near.sum() == 1, (border, near.sum())
        checked += 1
    assert checked >= 1


def test_missing_and_corrupt_model_files_are_clear_errors(tmp_path):
    with pytest.raises(ModelError, match="nowhere.onnx"):
        OnnxDetector(tmp_path / "nowhere.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"this is not an onnx model")
    with pytest.raises(ModelError, match="bad.json"):
        OnnxDetector(bad)  # the metadata is missing
    shutil.copy(DEFAULT_MODEL.with_suffix(".json"), tmp_path / "bad.json")
    with pytest.raises(ModelError, match="bad.onnx.*onnxruntime cannot load"):
        OnnxDetector(bad)


def test_the_models_box_response_is_read_and_a_bad_one_named(tmp_path, detector):
    """The shipped model says how its boxes answer an apple's size (benchmarks/box_response.py); a malformed one stops
    the node with its file named."""
    import json

    slope, icpt = detector.box_response
    assert 0.5 < slope < 1.5 and abs(icpt) < 3
    shutil.copy(DEFAULT_MODEL, tmp_path / "m.onnx")
    meta = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    for bad in ({"slope": 0.84}, {"slope": "x", "intercept_px": 0.9}, {"slope": 9.0, "intercept_px": 0.9}):
        (tmp_path / "m.json").write_text(json.dumps({**meta, "box_response": bad}))
        with pytest.raises(ModelError, match="m.json: box_response"):
            OnnxDetector(tmp_path / "m.onnx")


#: The real-photo check (issue 70): every 16th of AppleBBCH76's held-out tiles, sorted by name (41 tiles of 40 photos,
#: 547 apples, never trained on), through the model at their own size. The floor is the shipped model's own AP@0.5 on
#: them (0.804, the twelfth cycle; the eleventh's 0.791) minus 0.15, rounded down. The former default, trained on the
#: simulator and ADD256 alone, scores 0.096 on them and fails it (``git show a620280:onboard/models/apple-detector.onnx``,
#: the model card).
BBCH_CHECK_EVERY, BBCH_CHECK_FLOOR = 16, 0.65


def test_the_real_orchard_model_finds_real_apples_on_applebbch76_held_out_tiles():
    """``POMAR_DETECTOR=other.onnx`` scores another model the same way (the former, simulator-trained default fails:
    0.096). Skipped only where AppleBBCH76 is absent."""
    import os

    from export.data import DataError, applebbch76_split, read_rgb, yolo_boxes
    from export.metrics import evaluate_detections

    try:
        tiles = applebbch76_split(None, "held-out")[::BBCH_CHECK_EVERY]
    except DataError:
        pytest.skip("AppleBBCH76 is not available here")
    det = OnnxDetector(os.environ.get("POMAR_DETECTOR") or REAL_MODEL)
    preds, truths = [], []
    for p in tiles:
        img = read_rgb(p)
        preds.append(det.detect_rgb(img, score_thresh=0.05))
        truths.append((yolo_boxes(p.parent.parent / "labels" / f"{p.stem}.txt", img.shape[1], img.shape[0]), None))
    m = evaluate_detections(preds, truths, det.score_thresh)
    assert m["ap50"] >= BBCH_CHECK_FLOOR, (det.path.name, len(tiles), m)
