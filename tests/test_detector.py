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


ADD256_MODEL = DEFAULT_MODEL.with_name("apple-detector-add256.onnx")


def test_the_add256_model_finds_the_papers_apples():
    """The model for real imagery like ADD256 loads with its metadata (threshold chosen on training
    patches) and, where ADD256 is at hand, finds most apples of some test patches."""
    det = OnnxDetector(ADD256_MODEL)
    m = det.meta
    assert "ADD256 training patches" in m["score_thresh_chosen_on"] and m["training"]["sim_frames"] == 0
    assert m["metrics"]["add256_test"]["ap50"] >= 0.80
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
